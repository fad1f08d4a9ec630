"""Locomotion tasks: move forward (+x) as fast as possible (FT, VT, Incline, Obstacle)."""

from __future__ import annotations

import math

import numpy as np

from unimal_envs.arenas import Arena, Floor, Incline, ObstacleCourse, VariableTerrain
from unimal_envs.robot import Robot
from unimal_envs.tasks.base import CONTROL_DT, Task, height_map


class FlatTerrain(Task):
    """**FT** — walk forward on flat ground (MetaMorph ``ft.yaml``).

    ==============  ===========================================================================
    arena           :class:`~unimal_envs.arenas.Floor`: a 200 x 200 m floor box (surface at z = 0)
                    that ends at x = +-100 m like MetaMorph's (a fast robot can walk off it and fall)
    start           torso at (0, 0, spawn height of the morphology file), upright
    reward          ``forward`` = (x_after - x_before) / 0.02 (torso forward speed, m/s)
    termination     fall: torso height <= 0.5 x standing height
    observations    proprioception only (``hfield``, ``goal``, ``object`` are zeros)
    info            ``x_position``
    ==============  ===========================================================================

    With no control cost, an episode return is about 50 x the forward distance in metres.

    Version History:

    * v0: first release.
    """

    name = "FT"

    def make_arena(self) -> Arena:
        return Floor(half_size=100.0, bounded=True)

    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        return {"forward": (robot.torso_x - float(torso_before[0])) / CONTROL_DT}

    def metrics(self, robot: Robot) -> dict[str, float]:
        return {"x_position": robot.torso_x}


class _Corridor(FlatTerrain):
    """Forward locomotion in a corridor: the episode also ends at its side edges (|y| >= half-width - 1)."""

    half_width = 20.0

    def termination(self, robot: Robot) -> str | None:
        return "edge" if abs(float(robot.torso_qpos[1])) >= self.half_width - 1.0 else None


class VariableTerrainTask(_Corridor):
    """**VT** — walk forward across variable terrain (MetaMorph ``csr.yaml``).

    ==============  ===========================================================================
    arena           :class:`~unimal_envs.arenas.VariableTerrain`: x in [-3, 107] m, |y| <= 20 m;
                    flat stretches of 2-6 m between sine humps, terraced steps and rugged squares,
                    redrawn every episode
    start           torso at (0, 0, spawn height), upright, on the initial 6 m of flat ground
    reward          ``forward`` = torso forward speed (m/s)
    termination     fall: torso height above the terrain <= **0.3** x standing height;
                    ``edge``: |y| >= 19 m
    observations    ``hfield``: 47 x 30 egocentric height map (see below)
    info            ``x_position``
    ==============  ===========================================================================

    The height map samples the terrain 1 m behind to 4 m ahead and 4 m to each side on a grid that
    is dense near the robot, rotated with the torso heading, relative to the height under the
    torso; rows run from the robot's left to its right, columns from behind to ahead.

    Deliberate change: the original observed a y-mirrored copy of the physical terrain (spec 4.2);
    here physics and observation read the same array, so what the robot sees is what it walks on.

    Version History:

    * v0: first release.
    """

    name = "VT"
    observation_keys = ("hfield",)
    fall_height_ratio = 0.3

    def make_arena(self) -> Arena:
        return VariableTerrain(length=110.0, half_width=self.half_width, start_flat=3.0)

    def observations(self, robot: Robot) -> dict[str, np.ndarray]:
        return {"hfield": height_map(self, robot)}


class ObstacleTask(_Corridor):
    """**Obstacle** — walk forward through a field of 4 m tall blocks (MetaMorph ``obstacle.yaml``).

    ==============  ===========================================================================
    arena           :class:`~unimal_envs.arenas.ObstacleCourse`: walled corridor x in [-3, 97] m,
                    |y| <= 20 m, 50 blocks of 1-2 m x 1-2 m at x in [3, 91] m, redrawn every episode
    start           torso at (0, 0, spawn height), upright
    reward          ``forward`` = torso forward speed (m/s)
    termination     fall (0.5 x standing height); ``edge``: |y| >= 19 m
    observations    ``hfield``: the height map shows the blocks at +2 m and the walls at +3 m
                    (the reference's values; both are physically 4 m tall), -11 m off the course
    info            ``x_position``
    ==============  ===========================================================================

    Deliberate change: blocks stand on the ground instead of floating 0.1 m above it (spec 4.4).

    Version History:

    * v1: the blocks are solid. In v0 they were world-body geoms moved at reset, which MuJoCo keeps
      colliding at their compiled place (under the floor), so robots walked through them; a v0
      return is not comparable with a v1 one.
    * v0: first release.
    """

    name = "Obstacle"
    version = 1
    observation_keys = ("hfield",)

    def make_arena(self) -> Arena:
        return ObstacleCourse(length=100.0, half_width=self.half_width, start_flat=3.0, count=50)

    def observations(self, robot: Robot) -> dict[str, np.ndarray]:
        return {"hfield": height_map(self, robot)}


class InclineTask(_Corridor):
    """**Incline** — walk up a 10 degree slope (DERL ``incline.yml``).

    ==============  ===========================================================================
    arena           :class:`~unimal_envs.arenas.Incline`: a 150 x 40 m slab rising 10 degrees
                    toward +x; its surface is z = tan(10 deg) x
    start           on the slope at x = -73 cos(10 deg) m, the robot tilted with the slope
    reward          ``forward`` = (x_after - x_before) / 0.02 / cos(10 deg): speed along the slope
    termination     fall: torso height above the slope <= **0.2** x standing height;
                    ``edge``: |y| >= 19 m
    observations    proprioception only
    info            ``x_position``, ``distance_along_slope``
    ==============  ===========================================================================

    Version History:

    * v0: first release.
    """

    name = "Incline"
    arena: Incline  # make_arena's (spawn_pose reads its quat)
    fall_height_ratio = 0.2
    angle_deg = 10.0
    start_along_slope = -73.0

    def __init__(self) -> None:
        super().__init__()
        # Per-step constants: the reward divides by cos(10 deg) every step.
        self._along_slope = 1.0 / math.cos(math.radians(self.angle_deg))
        self._start_x = self.start_along_slope * math.cos(math.radians(self.angle_deg))

    def make_arena(self) -> Arena:
        return Incline(self.angle_deg, half_length=75.0, half_width=self.half_width)

    def spawn_pose(self, robot: Robot):
        x = self.start_along_slope * math.cos(math.radians(self.angle_deg))
        return (x, 0.0, self.arena.ground_height(x, 0.0) + robot.morphology.torso_height), self.arena.quat

    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        return {"forward": (robot.torso_x - float(torso_before[0])) / CONTROL_DT * self._along_slope}

    def metrics(self, robot: Robot) -> dict[str, float]:
        x = robot.torso_x
        return {"x_position": x, "distance_along_slope": (x - self._start_x) * self._along_slope}
