"""Per-world terrain for the batched backend: a pool of arena variants, one chosen per world.

Worlds of one MuJoCo Warp model share their height-field data, but each world may point its
terrain geom at a different height-field asset (a batched ``geom_dataid``), place its own mocap
bodies (``data.mocap_pos`` is per world) and resize its own geoms (batched ``geom_size``,
``geom_aabb``, ``geom_rbound``). So a task with random terrain draws a pool of ``variants`` arenas
once, with the single env's own arena code (:meth:`Arena.reset`), and every world picks one of
them at every reset:

* height-field arenas (VT's corridor, Escape's bowl): each variant is a height-field asset of the
  compiled world;
* the obstacle course: each variant is a layout of the 50 blocks (centres and half-sizes), put in
  place exactly as the single env does (:func:`~unimal_envs.arenas.terrain.apply_block_layout`:
  mocap bodies, so the blocks collide where they are drawn; see
  :class:`~unimal_envs.arenas.ObstacleCourse`).

How many variants a run sees is :func:`~unimal_envs.batched.make_batched_env`'s
``terrain_variants`` (a profile's ``batched.terrain_variants``): a pool of ``V`` variants gives
every episode one of ``V`` terrains (and ``V`` height fields of memory per robot on the device).

The egocentric height map is gathered on the device from the variants' padded height grids with
the single env's rotated-offset table, so observation and physics read the same numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from unimal_envs.arenas import Arena
from unimal_envs.arenas.heightfield import HeightGrid, rotated_offsets
from unimal_envs.arenas.terrain import ObstacleCourse


@dataclass
class TerrainPool:
    """``variants`` draws of one arena, ready to install in every robot's model.

    :param grid: the arena's height grid (its geometry; the heights are in ``padded``).
    :param padded: (variants, padded rows x padded cols) float32 height grids with their margins.
    :param hfield: (variants, rows x cols) normalised height-field data, or ``None`` (no height field).
    :param obstacle_layout: (variants, blocks, 6) block centres and half-sizes
        (:attr:`ObstacleCourse.layout`), or ``None``.
    """

    grid: HeightGrid
    padded: np.ndarray
    hfield: np.ndarray | None
    obstacle_layout: np.ndarray | None

    @property
    def variants(self) -> int:
        return len(self.padded)

    @classmethod
    def draw(cls, arena: Arena, model: mujoco.MjModel, data: mujoco.MjData, variants: int, rng: np.random.Generator) -> TerrainPool | None:
        """Draw ``variants`` arenas with the arena's own :meth:`~Arena.reset`, in a compiled world
        of that arena (``None`` for arenas without random terrain)."""
        grid: HeightGrid | None = getattr(arena, "grid", None)
        if grid is None:
            return None
        arena.bind(model, data)
        padded, hfield, layout = [], [], []
        size = grid.heights.size
        for _ in range(variants):
            arena.reset(rng)
            padded.append(grid.padded.reshape(-1).copy())
            if grid.hfield_address is not None:
                hfield.append(model.hfield_data[grid.hfield_address : grid.hfield_address + size].copy())
            if isinstance(arena, ObstacleCourse):
                layout.append(arena.layout.copy())
        return cls(grid, np.stack(padded), np.stack(hfield) if hfield else None, np.stack(layout) if layout else None)

    def add_assets(self, spec: mujoco.MjSpec) -> None:
        """Add a height-field asset for every variant but the first (which is the arena's own)."""
        if self.hfield is not None:
            for k in range(1, self.variants):
                self.grid.add_hfield_asset(spec, f"terrain-variant/{k}")

    def hfield_ids(self, model: mujoco.MjModel) -> tuple[int, np.ndarray]:
        """The terrain geom of a compiled world and the height-field id of every variant, after
        writing the variants' data into the model."""
        if self.hfield is None:
            raise ValueError("this terrain pool has no height fields")
        geom = int(np.flatnonzero(model.geom_type == mujoco.mjtGeom.mjGEOM_HFIELD)[0])
        ids = [int(model.geom_dataid[geom])] + [model.hfield(f"terrain-variant/{k}").id for k in range(1, self.variants)]
        for k, hfield in enumerate(ids):
            adr = model.hfield_adr[hfield]
            model.hfield_data[adr : adr + self.hfield.shape[1]] = self.hfield[k]
        return geom, np.array(ids)


class HeightMaps:
    """Egocentric height maps and ground heights of a pool's variants, on the device.

    The same sampling as :meth:`HeightGrid.height_map`: the torso's nearest sample (clamped to the
    grid), the heading rounded to a whole degree, the 47 x 30 rotated offsets, heights relative to
    the sample under the torso.
    """

    def __init__(self, pool: TerrainPool, device: torch.device):
        grid = pool.grid
        self.grid = grid
        self.padded = torch.as_tensor(pool.padded, device=device)
        self.flat = self.padded.reshape(-1)
        self.stride = self.padded.shape[1]
        self.margin = grid.margin
        self.rows, self.cols = grid.heights.shape
        self.width = grid.padded.shape[1]
        self.offsets = torch.as_tensor(rotated_offsets(grid.resolution, self.width), device=device)

    def _cells(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        g = self.grid
        row = torch.floor((xy[:, 1] - g.y0) / g.resolution + 0.5).long()
        col = torch.floor((xy[:, 0] - g.x0) / g.resolution + 0.5).long()
        return row, col

    def height_map(self, variant: torch.Tensor, xy: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
        """(N, 1410) height maps of worlds on ``variant`` at torso ``xy`` with heading ``yaw`` (rad)."""
        row, col = self._cells(xy)
        row, col = row.clamp(0, self.rows - 1), col.clamp(0, self.cols - 1)
        centre = variant * self.stride + (row + self.margin) * self.width + col + self.margin
        degree = torch.remainder(torch.round(torch.rad2deg(yaw)).long(), 360)
        sampled = self.flat[self.offsets[degree] + centre[:, None]]
        return sampled - self.flat[centre][:, None]

    def ground_height(self, variant: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
        """(N,) terrain height under ``xy`` (nearest sample; 0 off the grid), as ``HeightGrid.height``."""
        row, col = self._cells(xy)
        inside = (row >= 0) & (row < self.rows) & (col >= 0) & (col < self.cols)
        index = variant * self.stride + (row.clamp(0, self.rows - 1) + self.margin) * self.width + col.clamp(0, self.cols - 1) + self.margin
        return torch.where(inside, self.flat[index], torch.zeros_like(xy[:, 0]))
