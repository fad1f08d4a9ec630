"""Height grids: one array that is both the physical terrain and the source of ``hfield`` observations.

The original code kept a height array for observations whose row 0 was +y while MuJoCo's
heightfield row 0 is -y, so on y-varying terrain the observed map was the mirror image of the
physical one (spec 4.2). Here a single :class:`HeightGrid` (row index grows with +y, MuJoCo's order)
is written to the physics heightfield *and* sampled for observations, so the two always agree.

Terrain is re-randomised every episode by rewriting ``model.hfield_data`` in place: the world is
compiled once per morphology and never recompiled for new terrain.
"""

from __future__ import annotations

import functools
import math
import struct

import mujoco
import numpy as np

from unimal_envs import contract as C

#: Value of the height map outside the terrain: MetaMorph pads its height array with -10 around a
#: floor whose top is at 1, so off the course the observed relative height is -11.
OUTSIDE = -11.0


def log_offsets(n: int) -> np.ndarray:
    """MetaMorph's non-uniform 1-D sampler: dense near 0, sparse far away, ending at ``n``.

    ``p = k/n`` for ``k < n`` is mapped to ``-log(1-p)``, rescaled so the last value is ``n``,
    truncated to integers and de-duplicated (``log_offsets(10) == [0, 1, 2, 3, 5, 6, 10]``).
    """
    p = np.arange(n) / n
    values = -np.log(1.0 - p)
    return np.unique(np.floor(values * n / values[-1] + 1e-9).astype(int))


#: Forward offsets (0.1 m cells) of the 30 height-map columns: 1 m behind to 4 m ahead.
FORWARD_CELLS = np.union1d(-log_offsets(10), log_offsets(40))
#: Lateral offsets (0.1 m cells, + = the robot's left) of the 47 height-map rows, left to right.
LATERAL_CELLS = np.union1d(-log_offsets(40), log_offsets(40))[::-1]
assert (len(LATERAL_CELLS), len(FORWARD_CELLS)) == (C.HFIELD_ROWS, C.HFIELD_COLS)
#: Largest |offset| of the height-map grid along each axis, in 0.1 m cells.
_MAX_OFFSET_CELLS = (int(np.abs(LATERAL_CELLS).max()), int(np.abs(FORWARD_CELLS).max()))
_FORWARD, _LATERAL = (a.astype(np.float64) * 0.1 for a in np.meshgrid(FORWARD_CELLS, LATERAL_CELLS))


class HeightGrid:
    """Heights sampled on a regular grid: ``heights[row, col]`` is the terrain height at world point
    ``(x0 + col * resolution, y0 + row * resolution)``.

    These are the vertices of MuJoCo's heightfield (which interpolates between them), so at every
    sample point the physical surface and the observed height are the same number. Queries between
    samples read the nearest sample.

    :param shape: (rows, cols); rows run along +y, columns along +x.
    :param x0: world x of the grid's left edge.
    :param y0: world y of the grid's lower edge.
    :param resolution: cell size in metres.
    :param max_height: heights are clipped to [0, max_height] for physics (the heightfield's z scale).
    """

    def __init__(self, shape: tuple[int, int], x0: float, y0: float, resolution: float = 0.1, max_height: float = 1.0):
        # The heights live inside a margin of OUTSIDE values wide enough for any rotated sample, so
        # the height map is one gather with no bounds checks; ``heights`` is a view of the interior.
        rows, cols = shape
        self._margin = m = int(math.ceil(math.hypot(*_MAX_OFFSET_CELLS) * 0.1 / resolution)) + 2
        self._padded = np.full((rows + 2 * m, cols + 2 * m), OUTSIDE, dtype=np.float32)
        self._padded_flat = self._padded.reshape(-1)
        self.heights = self._padded[m : m + rows, m : m + cols]
        self.x0, self.y0, self.resolution, self.max_height = float(x0), float(y0), float(resolution), float(max_height)
        self._hfield_adr: int | None = None
        self._map_offsets = rotated_offsets(resolution, self._padded.shape[1])

    @property
    def padded(self) -> np.ndarray:
        """The heights inside their margin of :data:`OUTSIDE` (``heights`` is a view of its interior)."""
        return self._padded

    @property
    def margin(self) -> int:
        """Width of the margin around ``heights`` in :attr:`padded`, in samples."""
        return self._margin

    @property
    def hfield_address(self) -> int | None:
        """Address of this grid's heightfield in the bound model's ``hfield_data`` (``None`` unbound)."""
        return self._hfield_adr

    @property
    def size_x(self) -> float:
        """Extent along x, from the first to the last sample."""
        return (self.heights.shape[1] - 1) * self.resolution

    @property
    def size_y(self) -> float:
        """Extent along y, from the first to the last sample."""
        return (self.heights.shape[0] - 1) * self.resolution

    def cell(self, x: float, y: float) -> tuple[int, int]:
        """(row, col) of the sample nearest to world point (x, y); may lie outside the grid."""
        return math.floor((y - self.y0) / self.resolution + 0.5), math.floor((x - self.x0) / self.resolution + 0.5)

    def height(self, x: float, y: float) -> float:
        """Terrain height at (x, y); 0 outside the grid."""
        row, col = self.cell(x, y)
        rows, cols = self.heights.shape
        if 0 <= row < rows and 0 <= col < cols:
            return float(self.heights[row, col])
        return 0.0

    def columns_at(self, x: np.ndarray) -> np.ndarray:
        """Column indices of the samples nearest to world x coordinates."""
        return np.floor((np.asarray(x) - self.x0) / self.resolution + 0.5).astype(int)

    def rows_at(self, y: np.ndarray) -> np.ndarray:
        """Row indices of the samples nearest to world y coordinates."""
        return np.floor((np.asarray(y) - self.y0) / self.resolution + 0.5).astype(int)

    def fill_rectangle(self, x_min: float, x_max: float, y_min: float, y_max: float, value: float) -> None:
        """Set every sample whose point lies in the closed rectangle [x_min, x_max] x [y_min, y_max]
        (edges included, to 1e-6 m) to ``value``; samples outside the grid are ignored."""
        eps = 1e-6 / self.resolution
        rows, cols = self.heights.shape
        c0 = max(math.ceil((x_min - self.x0) / self.resolution - eps), 0)
        c1 = min(math.floor((x_max - self.x0) / self.resolution + eps), cols - 1)
        r0 = max(math.ceil((y_min - self.y0) / self.resolution - eps), 0)
        r1 = min(math.floor((y_max - self.y0) / self.resolution + eps), rows - 1)
        if c0 <= c1 and r0 <= r1:
            self.heights[r0 : r1 + 1, c0 : c1 + 1] = value

    # ------------------------------------------------------------------ physics
    def add_to_spec(self, spec: mujoco.MjSpec, name: str, material: str | None = None) -> None:
        """Add a MuJoCo heightfield whose vertices are the grid's samples (base 0.5 m below z = 0)."""
        self.add_hfield_asset(spec, name)
        geom = spec.worldbody.add_geom(
            name=name,
            type=mujoco.mjtGeom.mjGEOM_HFIELD,
            hfieldname=name,
            pos=[self.x0 + self.size_x / 2, self.y0 + self.size_y / 2, 0.0],
            condim=3,
            friction=[0.7, 0.1, 0.1],
        )
        if material is not None:
            geom.material = material

    def add_hfield_asset(self, spec: mujoco.MjSpec, name: str) -> None:
        """Add a flat MuJoCo heightfield asset of this grid's shape and extent (no geom uses it yet)."""
        rows, cols = self.heights.shape
        # MuJoCo's binary hfield format through an in-memory asset: far faster than userdata lists.
        blob = struct.pack("<ii", rows, cols) + np.zeros(rows * cols, dtype=np.float32).tobytes()
        assets = dict(spec.assets)
        assets[f"{name}.bin"] = blob
        spec.assets = assets
        spec.add_hfield(name=name, size=[self.size_x / 2, self.size_y / 2, self.max_height, 0.5], file=f"{name}.bin")

    def bind(self, model: mujoco.MjModel, name: str) -> None:
        """Remember where this grid's heightfield lives in a compiled model."""
        self._hfield_adr = int(model.hfield_adr[model.hfield(name).id])

    def upload(self, model: mujoco.MjModel) -> None:
        """Write the current heights into the bound model's heightfield (call after changing them)."""
        rows, cols = self.heights.shape
        target = model.hfield_data[self._hfield_adr : self._hfield_adr + rows * cols].reshape(rows, cols)
        np.clip(self.heights / self.max_height, 0.0, 1.0, out=target)

    # ------------------------------------------------------------------ observation
    def height_map(self, x: float, y: float, yaw: float) -> np.ndarray:
        """The (1410,) egocentric height map around (x, y), rotated by the torso yaw.

        Heights are sampled on MetaMorph's 47 x 30 non-uniform grid (1 m behind to 4 m ahead, 4 m
        to each side) at the torso's sample plus the rotated offsets rounded to whole samples (as in
        the original; the yaw is taken to the nearest degree), relative to the height under the
        torso. Points beyond the grid read :data:`OUTSIDE` (relative to the ground at the torso).
        """
        rows, cols = self.heights.shape
        row, col = self.cell(x, y)
        row, col = min(max(row, 0), rows - 1), min(max(col, 0), cols - 1)  # a robot off the grid sees its edge
        width = self._padded.shape[1]
        centre = (row + self._margin) * width + col + self._margin
        degree = int(round(math.degrees(yaw))) % 360
        sampled = self._padded_flat.take(self._map_offsets[degree] + centre)
        sampled -= self._padded_flat[centre]
        return sampled


@functools.lru_cache(maxsize=8)
def rotated_offsets(resolution: float, row_stride: int) -> np.ndarray:
    """(360, 1410) flat-index offsets of the height-map samples for every whole-degree heading, in
    a padded grid whose rows are ``row_stride`` samples long (:attr:`HeightGrid.padded`)."""
    table = np.empty((360, C.HFIELD_DIM), dtype=np.intp)
    for degree in range(360):
        c, s = math.cos(math.radians(degree)), math.sin(math.radians(degree))
        d_row = np.rint((s * _FORWARD + c * _LATERAL) / resolution).astype(np.intp)
        d_col = np.rint((c * _FORWARD - s * _LATERAL) / resolution).astype(np.intp)
        table[degree] = (d_row * row_stride + d_col).reshape(-1)
    return table


def torso_yaw(xmat: np.ndarray) -> float:
    """Heading of the torso: angle from world +x to the xy-projection of the torso's x-axis."""
    return math.atan2(xmat[1, 0], xmat[0, 0])
