"""The arena interface and shared building blocks (ground material, boundary walls)."""

from __future__ import annotations

import abc

import mujoco
import numpy as np

_GROUND_MATERIAL = "divmorph_ground"
_WALL_MATERIAL = "divmorph_wall"
#: Boundary walls: 0.5 m thick, 4 m tall (MetaMorph's half-thickness 0.5 and half-height 2 -> 1 m thick).
WALL_HALF_THICKNESS = 0.5
WALL_HEIGHT = 4.0


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


def add_walls(spec: mujoco.MjSpec, x_min: float, x_max: float, y_min: float, y_max: float) -> None:
    """Four static boundary walls just outside the rectangle [x_min, x_max] x [y_min, y_max]."""
    if spec.material(_WALL_MATERIAL) is None:
        spec.add_material(name=_WALL_MATERIAL, rgba=[0.55, 0.5, 0.42, 1.0])
    t, h = WALL_HALF_THICKNESS, WALL_HEIGHT / 2
    cx, cy = (x_min + x_max) / 2, (y_min + y_max) / 2
    hx, hy = (x_max - x_min) / 2 + 2 * t, (y_max - y_min) / 2
    for name, pos, size in (
        ("wall/front", [x_max + t, cy, h], [t, hy, h]),
        ("wall/back", [x_min - t, cy, h], [t, hy, h]),
        ("wall/left", [cx, y_max + t, h], [hx, t, h]),
        ("wall/right", [cx, y_min - t, h], [hx, t, h]),
    ):
        spec.worldbody.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_BOX, pos=pos, size=size, material=_WALL_MATERIAL)


class Arena(abc.ABC):
    """Terrain and static props.

    The world is compiled once per morphology (:meth:`build`); every episode :meth:`reset`
    re-randomises the arena *in place* in the compiled model (heightfield data, prop positions).
    One arena instance belongs to one env and is re-bound to whichever world is current.

    **Moving things at reset without breaking collisions.** What a compiled model may change at
    run time and still collide where it is drawn, in MuJoCo and MuJoCo Warp alike:

    * height-field *data* (``model.hfield_data``): collision reads it directly; the geom's bounds
      come from the height field's size, which never changes;
    * the pose of a *mocap* body (``data.mocap_pos``): state, read by both engines every step;
    * the size of a geom (``geom_size`` with ``geom_aabb``, ``geom_rbound``) only if it was compiled
      at its largest size (MuJoCo's per-body bounding volumes are fixed at compile time).

    What may **not** change: the position of a world-body geom (``model.geom_pos``). MuJoCo bounds
    world geoms once, at compile time, and MuJoCo Warp computes their poses once, in ``make_data``:
    the geom is drawn where it was moved and collides where it was compiled.

    Audit of every arena and task (what changes at reset, and how):

    ====================  =========================================================================
    Floor, walls          static geoms, never moved
    Incline               a static slab, never moved
    VariableTerrain       height-field data rewritten (batched: a pool of height fields picked per
                          world with ``geom_dataid``, one device copy per task)
    Bowl (Escape)         as VariableTerrain
    ObstacleCourse        50 mocap bodies placed through ``mocap_pos``, box sizes rewritten with
                          their bounds, compiled at the largest size (batched: per-world
                          ``mocap_pos``, batched sizes and bounds)
    box tasks             the box is a free body placed through ``qpos``
    goal tasks            the goal marker is a visual site (no collision); ``site_pos`` is moved
    ====================  =========================================================================

    ``tests/test_scenarios.py`` checks each of these physically, on both backends.
    """

    #: True if :meth:`height_map` gives a real height map (terrain tasks observe it as ``hfield``).
    has_height_map: bool = False

    @abc.abstractmethod
    def build(self, spec: mujoco.MjSpec) -> None:
        """Add the arena's geoms and assets to ``spec``."""

    def bind(self, model: mujoco.MjModel, data: mujoco.MjData) -> None:
        """Resolve ids in the current compiled world (called every episode, before :meth:`reset`)."""
        self.model, self.data = model, data

    def reset(self, rng: np.random.Generator) -> None:
        """Re-randomise the arena for a new episode. Default: static arena."""

    def ground_height(self, x: float, y: float) -> float:
        """Height of the ground surface under world point (x, y)."""
        return 0.0

    def height_map(self, x: float, y: float, yaw: float) -> np.ndarray | None:
        """The (1410,) egocentric height map, or ``None`` for arenas without one."""
        return None
