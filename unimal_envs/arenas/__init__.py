"""Arenas: the ground and static props a robot is placed on (dm_control's *arena*)."""

from unimal_envs.arenas.base import Arena
from unimal_envs.arenas.floor import Floor
from unimal_envs.arenas.incline import Incline
from unimal_envs.arenas.terrain import Bowl, ObstacleCourse, VariableTerrain

__all__ = ["Arena", "Bowl", "Floor", "Incline", "ObstacleCourse", "VariableTerrain"]
