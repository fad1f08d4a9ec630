"""A tilted plane."""

from __future__ import annotations

import math

import mujoco

from unimal_envs.arenas.base import Arena, add_ground_material


class Incline(Arena):
    """A 150 x 40 m slab rising toward +x at ``angle_deg`` (DERL ``incline.yml``).

    Its surface is the plane z = tan(angle) x through the origin.

    :param angle_deg: slope in degrees (10).
    :param half_length: half-length of the slab along the slope, in m (75).
    :param half_width: half-width in m (20).
    """

    def __init__(self, angle_deg: float = 10.0, half_length: float = 75.0, half_width: float = 20.0):
        self.angle = math.radians(angle_deg)
        self.half_length, self.half_width = half_length, half_width
        self.slope = math.tan(self.angle)

    @property
    def quat(self) -> tuple[float, float, float, float]:
        """Rotation (w, x, y, z) that tilts +x up the slope (about y by -angle)."""
        return (math.cos(-self.angle / 2), 0.0, math.sin(-self.angle / 2), 0.0)

    def build(self, spec: mujoco.MjSpec) -> None:
        thickness = 1.0
        # The slab's top face passes through the origin: centre = -normal x half-thickness.
        normal = (-math.sin(self.angle), 0.0, math.cos(self.angle))
        spec.worldbody.add_geom(
            name="incline",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[self.half_length, self.half_width, thickness],
            pos=[-n * thickness for n in normal],
            quat=self.quat,
            material=add_ground_material(spec),
            condim=3,
            friction=[0.7, 0.1, 0.1],
        )

    def ground_height(self, x: float, y: float) -> float:
        return self.slope * x
