"""Flat ground."""

from __future__ import annotations

import mujoco
import numpy as np

from unimal_envs.arenas.base import Arena, add_ground_material


class Floor(Arena):
    """An infinite flat floor whose surface is at z = 0.

    MetaMorph uses a 200 x 200 m box with its top at z = 1; we put the surface at z = 0 instead, so
    heights in observations are heights above the ground (a constant offset that normalisation
    removes anyway). Physics are unaffected: a robot walking 100 m in 20 s stays far inside.

    :param half_size: visual half-extent of the plane in metres (collision is unbounded).
    """

    def __init__(self, half_size: float = 100.0):
        self.half_size = half_size

    def build(self, spec: mujoco.MjSpec, rng: np.random.Generator) -> None:
        spec.worldbody.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[self.half_size, self.half_size, 0.1],
            material=add_ground_material(spec),
            condim=3,
            friction=[0.7, 0.1, 0.1],
        )

    def ground_height(self, x: float, y: float) -> float:
        return 0.0
