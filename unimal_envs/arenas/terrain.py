"""Procedural terrain arenas: the variable-terrain corridor, the obstacle course, and the bowl."""

from __future__ import annotations

import functools
import math

import mujoco
import numpy as np

from unimal_envs.arenas.base import WALL_HEIGHT, Arena, add_ground_material, add_walls
from unimal_envs.arenas.heightfield import HeightGrid


class VariableTerrain(Arena):
    """A 40 m wide corridor of flat stretches and obstacle segments along +x (MetaMorph ``csr.yaml``).

    The course starts with a flat 6 m (x in [-3, 3]), then alternates a flat stretch (half-length
    drawn from ``flat_half_lengths`` m) and a segment drawn uniformly from ``segment_types``, until it
    reaches ``length`` m. Segments (half-length in m, profile along x):

    ================  =============  =================================================================
    ``curve_slope``   4 or 8         a sine hump ``c sin(0..pi)``, c in {0.6, 0.7, ..., 1.2} m
    ``steps``         12 or 16       8 equal terraces of height 0, .2, .4, .6, .6, .4, .2, 0 m
    ``rugged_square`` 4 or 8         y-bands of 1-1.9 m, each a triangle wave over x (10 or 15
                                     half-periods from phase 0, range 0-2 m) clipped at 0.2 or 0.3 m
    ================  =============  =================================================================

    Terrain is one heightfield (0.1 m cells) used both for physics and for the height-map
    observation; it is redrawn every episode.

    :param length: course length in m (MetaMorph: 2 x 55).
    :param half_width: corridor half-width in m (20).
    :param start_flat: the course starts at x = -start_flat with 2 x start_flat m of flat ground.
    """

    has_height_map = True
    segment_types = ("curve_slope", "steps", "rugged_square")
    flat_half_lengths = (1, 2, 3)

    def __init__(self, length: float = 110.0, half_width: float = 20.0, start_flat: float = 3.0):
        self.half_width = half_width
        self.start_flat = start_flat
        self.grid = HeightGrid((int(2 * half_width * 10), int(length * 10)), x0=-start_flat, y0=-half_width, max_height=1.2)

    def build(self, spec: mujoco.MjSpec) -> None:
        self.grid.add_to_spec(spec, "terrain", material=add_ground_material(spec))

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        super().bind(model, data)
        self.grid.bind(model, "terrain")

    def reset(self, rng: np.random.Generator) -> None:
        heights = self.grid.heights
        heights[:] = 0.0
        rows, cols = heights.shape
        col = int(2 * self.start_flat * 10)
        while col < cols:
            col += int(2 * 10 * rng.choice(self.flat_half_lengths))
            segment = self._segment(str(rng.choice(self.segment_types)), rows, rng)
            if col + segment.shape[1] <= cols:
                heights[:, col : col + segment.shape[1]] = segment
                col += segment.shape[1]
        self.grid.upload(self.model)

    @staticmethod
    def _segment(kind: str, rows: int, rng: np.random.Generator) -> np.ndarray:
        if kind == "curve_slope":
            n = 20 * int(rng.choice((4, 8)))
            height = rng.choice(np.arange(0.6, 1.21, 0.1))
            return np.broadcast_to(height * np.sin(np.linspace(0.0, math.pi, n)), (rows, n))
        if kind == "steps":
            n = 20 * int(rng.choice((12, 16)))
            terraces = np.array([0.0, 0.2, 0.4, 0.6, 0.6, 0.4, 0.2, 0.0])
            return np.broadcast_to(np.repeat(terraces, n // 8 + 1)[:n], (rows, n))
        if kind == "rugged_square":
            n = 20 * int(rng.choice((4, 8)))
            segment = np.empty((rows, n))
            row = 0
            while row < rows:
                band = int(rng.integers(10, 20))
                half_periods = int(rng.choice((10, 15)))
                t = np.linspace(0.0, half_periods, n)  # every band starts at phase 0, as in the reference
                triangle = 2.0 * np.abs((t % 2.0) - 1.0)  # in [0, 2]
                segment[row : row + band] = np.minimum(triangle, rng.choice((0.2, 0.3)))
                row += band
            return segment
        raise ValueError(f"unknown terrain segment '{kind}'")

    def ground_height(self, x: float, y: float) -> float:
        return self.grid.height(x, y)

    def height_map(self, x: float, y: float, yaw: float) -> np.ndarray:
        return self.grid.height_map(x, y, yaw)


#: Heights the Obstacle height map shows for blocks and walls (the reference's values, see below).
OBSERVED_BLOCK = 2.0
OBSERVED_WALL = 3.0


class ObstacleCourse(Arena):
    """A flat walled corridor with static 4 m tall boxes (MetaMorph ``obstacle.yaml``).

    ``count`` boxes with half-sizes drawn from {0.5, 0.6, ..., 1.0} m (length and width
    independently) are placed uniformly at x in [3 + s, 91 - s] (a 6 m buffer at both ends), anywhere
    across the width, without overlapping (up to 10 tries each; a box that finds no room is parked
    at :data:`PARKED`, under the floor, out of the course). They are redrawn every episode.
    The height map shows them and the walls with the reference's values, not their physical
    heights: blocks +2 m (MetaMorph raises its height array to the blocks' half-height), walls +3 m
    (its wall padding of 4 over a floor at 1), and off the course -11 m (:data:`OUTSIDE`). Every
    height-map sample whose point lies inside a block's footprint (its faces included) reads +2.

    **How blocks move without recompiling, and stay solid.** Each block is the box geom of its own
    *mocap* body. A geom of the world body cannot be moved at run time: MuJoCo bounds the world
    body's geoms once, at compile time (its bounding-volume hierarchy), and MuJoCo Warp computes
    world-body geom poses once, in ``make_data``, so a moved world geom is drawn where it was put
    but collides where it was compiled (robots would walk through the blocks). A mocap body's pose is state (``data.mocap_pos``), read by both engines every step.
    Sizes change through ``model.geom_size`` (with ``geom_aabb`` and ``geom_rbound``); every block
    is compiled at the largest size, so the compile-time bounding volumes of MuJoCo's midphase
    contain every size a block takes. Blocks and floor are both fixed, so MuJoCo never pairs them.

    Deliberate change: the original boxes float 0.1 m above the ground (spec 4.4); here they stand
    on it, so nothing can crawl underneath.

    :param length: course length in m (2 x 50).
    :param half_width: corridor half-width in m (20).
    :param start_flat: the course starts at x = -start_flat.
    :param count: number of boxes (50).
    """

    has_height_map = True
    half_sizes = np.round(np.arange(0.5, 1.01, 0.1), 1)
    buffer = 6.0

    def __init__(self, length: float = 100.0, half_width: float = 20.0, start_flat: float = 3.0, count: int = 50):
        self.length, self.half_width, self.start_flat, self.count = length, half_width, start_flat, count
        x_min, x_max = -start_flat, length - start_flat
        self.bounds = (x_min, x_max, -half_width, half_width)
        # The observation grid includes 1 m around the course, where the walls stand.
        self.grid = HeightGrid((int(2 * (half_width + 1) * 10), int((length + 2) * 10)), x0=x_min - 1, y0=-half_width - 1)
        #: (count, 6) the current episode's blocks: centre (x, y, z) and half-sizes, parked ones included.
        self.layout = np.tile(np.array([*PARKED, *self.largest_half_size()]), (count, 1))

    def largest_half_size(self) -> tuple[float, float, float]:
        """The half-size every block is compiled at (the largest it can take)."""
        return (float(self.half_sizes.max()), float(self.half_sizes.max()), WALL_HEIGHT / 2)

    def build(self, spec: mujoco.MjSpec) -> None:
        spec.worldbody.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[self.length, self.half_width + 10, 0.1],
            pos=[self.length / 2 - self.start_flat, 0, 0],
            material=add_ground_material(spec),
        )
        add_walls(spec, *self.bounds)
        spec.add_material(name="divmorph_obstacle", rgba=[0.35, 0.45, 0.6, 1.0])
        for i in range(self.count):
            body = spec.worldbody.add_body(name=f"obstacle/{i}", mocap=True, pos=list(PARKED))
            body.add_geom(
                name=f"obstacle/{i}", type=mujoco.mjtGeom.mjGEOM_BOX, size=list(self.largest_half_size()), material="divmorph_obstacle"
            )

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        super().bind(model, data)
        self._geoms = np.array([model.geom(f"obstacle/{i}").id for i in range(self.count)])
        self._mocap = np.array([model.body_mocapid[model.body(f"obstacle/{i}").id] for i in range(self.count)])

    def reset(self, rng: np.random.Generator) -> None:
        heights = self.grid.heights
        heights[:] = 0.0
        heights[:10, :] = heights[-10:, :] = heights[:, :10] = heights[:, -10:] = OBSERVED_WALL
        x_min, x_max, y_min, y_max = self.bounds
        free = np.ones((int((y_max - y_min) * 10), int((x_max - x_min) * 10)), dtype=bool)
        layout = self.layout
        layout[:, :3] = PARKED
        layout[:, 3:] = self.largest_half_size()
        for block in layout:
            sx, sy = rng.choice(self.half_sizes, size=2)
            # Whole cells: half-sizes are multiples of 0.1 m (round, as 10 x 0.6 is 6.000000000000001).
            cx, cy = round(10 * sx), round(10 * sy)
            for _ in range(10):
                col = int(rng.integers(cx + 10 * self.buffer, free.shape[1] - cx - 10 * self.buffer))
                row = int(rng.integers(cy, free.shape[0] - cy))
                footprint = (slice(row - cy, row + cy), slice(col - cx, col + cx))
                if free[footprint].all():
                    free[footprint] = False
                    block[:] = (x_min + col / 10, y_min + row / 10, WALL_HEIGHT / 2, sx, sy, WALL_HEIGHT / 2)
                    self.grid.fill_rectangle(block[0] - sx, block[0] + sx, block[1] - sy, block[1] + sy, OBSERVED_BLOCK)
                    break
        apply_block_layout(self.model, self.data, self._geoms, self._mocap, layout)

    def height_map(self, x: float, y: float, yaw: float) -> np.ndarray:
        return self.grid.height_map(x, y, yaw)


#: Where an obstacle block that found no room waits: under the floor, out of every robot's way.
PARKED = (0.0, 0.0, -10.0)


def apply_block_layout(model: mujoco.MjModel, data: mujoco.MjData, geoms: np.ndarray, mocap: np.ndarray, layout: np.ndarray) -> None:
    """Put box blocks in place: mocap body ``mocap[i]`` at ``layout[i, :3]``, its box geom
    ``geoms[i]`` resized to half-sizes ``layout[i, 3:]`` (with consistent collision bounds).
    Call ``mj_forward`` (or step) afterwards so the new poses reach the kinematics."""
    data.mocap_pos[mocap] = layout[:, :3]
    half = layout[:, 3:]
    model.geom_size[geoms] = half
    model.geom_aabb[geoms, :3] = 0.0
    model.geom_aabb[geoms, 3:] = half
    model.geom_rbound[geoms] = np.linalg.norm(half, axis=1)


class Bowl(Arena):
    """A bumpy bowl to climb out of (DERL ``escape.yml``), one 100 x 100 m heightfield.

    Height = bumps x shape x 1.3 m, where shape = 0.5 - cos(2 pi rho) / 2 of the normalised radius
    rho = r / 50 (clipped to [0.04, 1]): 0 at the centre, 1 at 25 m, back to 0 at 50 m; bumps are
    U(0.15, 1) on a 50 x 50 grid zoomed to the 0.1 m grid with a cubic spline. Redrawn every episode.

    :param half_size: half-side of the square bowl in m (50).
    :param max_height: 1.3 m.
    """

    has_height_map = True

    def __init__(self, half_size: float = 50.0, max_height: float = 1.3, bump_cells: int = 50):
        self.half_size, self.max_height, self.bump_cells = half_size, max_height, bump_cells
        n = int(2 * half_size * 10)
        self.grid = HeightGrid((n, n), x0=-half_size, y0=-half_size, max_height=max_height)
        centres = (np.arange(n) + 0.5) / 10 - half_size
        rho = np.clip(np.hypot(*np.meshgrid(centres, centres)) / half_size, 0.04, 1.0)
        self._shape = (0.5 - np.cos(2 * math.pi * rho) / 2).astype(np.float32)
        self._zoom = _cubic_zoom_matrix(bump_cells, n)

    def build(self, spec: mujoco.MjSpec) -> None:
        self.grid.add_to_spec(spec, "bowl", material=add_ground_material(spec))

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        super().bind(model, data)
        self.grid.bind(model, "bowl")

    def reset(self, rng: np.random.Generator) -> None:
        bumps = rng.uniform(0.15, 1.0, size=(self.bump_cells, self.bump_cells)).astype(np.float32)
        smooth = np.clip(self._zoom @ bumps @ self._zoom.T, 0.0, 1.0)
        np.multiply(smooth, self._shape * self.max_height, out=self.grid.heights)
        self.grid.upload(self.model)

    def ground_height(self, x: float, y: float) -> float:
        return self.grid.height(x, y)

    def height_map(self, x: float, y: float, yaw: float) -> np.ndarray:
        return self.grid.height_map(x, y, yaw)


@functools.lru_cache(maxsize=4)
def _cubic_zoom_matrix(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) matrix of scipy's order-3 spline zoom: zoom(X) == A @ X @ A.T for 2-D X.

    The spline zoom is linear and separable, so zooming the unit vectors once gives the matrix and
    every episode costs two small matrix products instead of a full 2-D spline fit.
    """
    from scipy import ndimage

    return np.stack([ndimage.zoom(np.eye(n_in)[i], n_out / n_in, order=3) for i in range(n_in)], axis=1).astype(np.float32)
