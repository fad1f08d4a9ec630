"""Arenas: the ground and static props a robot is placed on (dm_control's *arena*)."""

from unimal_envs.arenas.base import Arena
from unimal_envs.arenas.floor import Floor

__all__ = ["Arena", "Floor"]
