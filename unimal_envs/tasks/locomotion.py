"""Locomotion tasks: move forward (+x) as fast as possible."""

from __future__ import annotations

import numpy as np

from unimal_envs.arenas import Arena, Floor
from unimal_envs.robot import Robot
from unimal_envs.tasks.base import CONTROL_DT, Task


class FlatTerrain(Task):
    """**FT** — walk forward on flat ground (MetaMorph ``ft.yaml``).

    ==============  ===========================================================================
    arena           :class:`~unimal_envs.arenas.Floor` (surface at z = 0)
    start           torso at (0, 0, spawn height of the morphology file), upright
    reward          ``forward`` = (x_after - x_before) / 0.02 (torso forward speed, m/s)
    termination     fall: torso height <= 0.5 x standing height
    observations    proprioception only (``hfield``, ``goal``, ``object`` are zeros)
    ==============  ===========================================================================

    With no control cost, an episode return is about 50 x the forward distance in metres.
    """

    name = "FT"

    def make_arena(self) -> Arena:
        return Floor()

    def reward_terms(self, robot: Robot, torso_before: np.ndarray) -> dict[str, float]:
        return {"forward": (robot.torso_x - float(torso_before[0])) / CONTROL_DT}
