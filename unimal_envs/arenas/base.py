"""The arena interface."""

from __future__ import annotations

import mujoco
import numpy as np

# Our own look for the ground; added once per world spec.
_GROUND_MATERIAL = "divmorph_ground"


def add_ground_material(spec: mujoco.MjSpec) -> str:
    """Add a checkered ground material to ``spec`` (idempotent) and return its name."""
    if spec.material(_GROUND_MATERIAL) is None:
        texture = spec.add_texture(
            name=_GROUND_MATERIAL,
            type=mujoco.mjtTexture.mjTEXTURE_2D,
            builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
            rgb1=[0.22, 0.25, 0.3],
            rgb2=[0.3, 0.33, 0.38],
            mark=mujoco.mjtMark.mjMARK_EDGE,
            markrgb=[0.45, 0.48, 0.52],
            width=300,
            height=300,
        )
        material = spec.add_material(name=_GROUND_MATERIAL, texrepeat=[1, 1], texuniform=True, reflectance=0.1)
        material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = texture.name
    return _GROUND_MATERIAL


class Arena:
    """Terrain and static props. Subclasses add geoms to a world spec and answer height queries.

    An arena instance belongs to one env; :meth:`build` is called whenever the world is rebuilt
    (once per morphology for static arenas, every episode for randomised ones).
    """

    #: True if :meth:`build` samples anything, i.e. the world must be rebuilt every episode.
    randomised: bool = False

    def build(self, spec: mujoco.MjSpec, rng: np.random.Generator) -> None:
        """Add the arena to ``spec``."""
        raise NotImplementedError

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Called after compiling; write heightfield data or resolve ids here."""

    def ground_height(self, x: float, y: float) -> float:
        """Height of the ground surface under world point (x, y)."""
        raise NotImplementedError
