"""Flat ground, optionally walled."""

from __future__ import annotations

import mujoco

from unimal_envs.arenas.base import Arena, add_ground_material, add_walls


class Floor(Arena):
    """A flat floor whose surface is at z = 0, optionally enclosed by boundary walls.

    MetaMorph uses a box with its top at z = 1; we put the surface at z = 0, so heights in
    observations are heights above the ground (a constant offset that normalisation removes).

    :param half_size: half-extent of the floor in x and y, in metres.
    :param walls: ``(x_min, x_max, y_min, y_max)`` of a walled rectangle, or ``None``.
    :param bounded: the floor ends at ``±half_size`` like MetaMorph's floor box (a box geom, 1 m
        thick, top at z = 0: a robot that walks past the edge falls off); otherwise an infinite plane
        (cheaper contacts; used where walls keep the robot on the floor anyway).
    """

    def __init__(self, half_size: float = 100.0, walls: tuple[float, float, float, float] | None = None, bounded: bool = False):
        self.half_size = half_size
        self.walls = walls
        self.bounded = bounded

    def build(self, spec: mujoco.MjSpec) -> None:
        h = self.half_size
        spec.worldbody.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_BOX if self.bounded else mujoco.mjtGeom.mjGEOM_PLANE,
            size=[h, h, 1.0] if self.bounded else [h, h, 0.1],
            pos=[0.0, 0.0, -1.0] if self.bounded else [0.0, 0.0, 0.0],
            material=add_ground_material(spec),
            condim=3,
            friction=[0.7, 0.1, 0.1],
        )
        if self.walls is not None:
            add_walls(spec, *self.walls)
