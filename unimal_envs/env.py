"""The UNIMAL Gymnasium environment: a robot, an arena and a task, composed."""

from __future__ import annotations

import math
import os
import sys
from collections import OrderedDict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from unimal_envs import contract as C
from unimal_envs.instructions import DEFAULT_ENCODER, embed_instruction
from unimal_envs.morphology.loader import Morphology, MorphologyError, load_morphologies
from unimal_envs.robot import Robot
from unimal_envs.tasks import CONTROL_DT, Task, make_task

_FAULT_WARNINGS = (
    int(mujoco.mjtWarning.mjWARN_BADQPOS),
    int(mujoco.mjtWarning.mjWARN_BADQVEL),
    int(mujoco.mjtWarning.mjWARN_BADQACC),
)
#: Physics timestep; a control step is 4 of them (CONTROL_DT).
_SUBSTEPS = 4
_SUBSTEP = CONTROL_DT / _SUBSTEPS
_ZEROS_HFIELD = np.zeros(C.HFIELD_DIM, dtype=np.float32)
_ZEROS_GOAL = np.zeros(C.GOAL_DIM, dtype=np.float32)
_ZEROS_OBJECT = np.zeros(C.OBJECT_DIM, dtype=np.float32)
#: Clipping planes of rendered frames, in metres. MuJoCo scales its defaults (0.01 and 50) by the
#: model's extent, which the arenas make 140-280 m: a near plane 1.4-2.8 m from a camera standing
#: 4 m from the robot cut the ground out of the bottom of the frame (a band of sky).
CAMERA_NEAR, CAMERA_FAR = 0.05, 400.0
#: Half-width (m) of the region around the camera's target that casts shadows; MuJoCo's default
#: (the model extent) spreads the shadow map over hundreds of metres and speckles the ground.
SHADOW_CLIP = 50.0
#: Side (pixels) of the generated textures of worlds that are never rendered (``render_mode=None``).
UNRENDERED_TEXTURE_SIZE = 8


def _has_display() -> bool:
    """Whether a window can open here (on Linux: an X11 or Wayland display is set)."""
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _check_display() -> None:
    """Refuse ``render_mode="human"`` up front where no window can open: on Linux without an X11
    or Wayland display, MuJoCo's viewer would otherwise fail deep inside GLFW on the first step."""
    if not _has_display():
        raise RuntimeError(
            "render_mode='human' needs a display, and neither DISPLAY nor WAYLAND_DISPLAY is set; "
            "use render_mode='rgb_array' for frames without a display (MUJOCO_GL=egl), e.g. "
            "unimal_envs.rendering.record_episode(env) and write_video(frames, 'clip.mp4')"
        )


def _bounded(vectors: np.ndarray, limit: float) -> np.ndarray:
    """Each row of ``vectors`` (n, 3) longer than ``limit``, scaled to length ``limit`` (``goal_range``)."""
    length = np.linalg.norm(vectors, axis=1, keepdims=True)
    return (vectors * np.minimum(1.0, limit / np.maximum(length, 1e-9))).astype(np.float32)


def compile_world(spec: mujoco.MjSpec, name: str) -> mujoco.MjModel:
    """Compile a world spec; a failure names the morphology (:class:`MorphologyError`)."""
    try:
        return spec.compile()
    except ValueError as err:
        raise MorphologyError(f"{name}: the world does not compile ({err})") from None


@dataclass
class _World:
    """One compiled world (robot + arena + task props) and its simulation state."""

    model: mujoco.MjModel
    data: mujoco.MjData
    robot: Robot
    renderer: mujoco.Renderer | None = None
    #: The arena rewrote heightfield data since the renderer last uploaded it.
    stale_heightfields: bool = True


class UnimalEnv(gym.Env):
    """A UNIMAL robot doing a task; one morphology is drawn per episode.

    Registered as ``Unimal-<task>-v<N>`` (:func:`unimal_envs.env_id`, e.g. ``gym.make("Unimal-FT-v0")``; each
    task's docstring has its Version History). Every task and every
    morphology shares the same observation and action spaces (:mod:`unimal_envs.contract`), so a
    single policy and a single vectorised env can mix them.

    **Observation** — ``spaces.Dict`` (float32, fresh arrays every step):

    ====================  =========  ==========================================================
    key                   shape      content
    ====================  =========  ==========================================================
    ``proprioceptive``    (12, 52)   per token (torso, then limbs in MuJoCo body order): body
                                     position (x relative to the torso), linear and angular
                                     velocity, orientation quaternion, 17 static body features,
                                     and for the "x" and "y" hinge slots: normalised angle,
                                     angular velocity, anchor, range, axis, gear; zero rows for
                                     padding
    ``context``           (12, 35)   static morphology features rescaled to [-1, 1]
    ``obs_padding_mask``  (12,)      1.0 = padded token
    ``act_padding_mask``  (24,)      1.0 = no hinge behind this action slot
    ``hfield``            (1410,)    egocentric height map (terrain tasks), else zeros
    ``goal``              (3,)       goal in the torso frame (goal tasks), else zeros
    ``object``            (12,)      object state in the torso frame (box tasks), else zeros
    ``task_embedding``    (384,)     all-MiniLM-L6-v2 embedding of the instruction
    ``task_index``        (1,)       index of the task in ``contract.TASK_NAMES``
    ====================  =========  ==========================================================

    Positions and velocities all describe the state after the step (see :mod:`unimal_envs.robot`
    for the velocity convention).

    **Action** — ``Box(-1, 1, (24,))``: two slots per token, slot 0 drives the limb's "x" hinge,
    slot 1 its "y" hinge; a torque of ``gear x action`` is applied. Slots flagged in
    ``act_padding_mask`` are ignored. An action of the wrong shape, or with NaN/inf in a real
    slot, raises ``ValueError`` *before* the simulation is touched (the episode can continue
    with a valid action); non-finite values in padded slots are ignored.

    **Reward** — the task's terms (``info["reward_<term>"]``) minus
    ``ctrl_cost_weight x sum(clip(action_real, -1, 1)**2)`` (``reward_ctrl``).

    **Episode end** — ``terminated`` when the robot falls (torso height above the ground
    <= ``task.fall_height_ratio`` x standing height), on a task-specific event, or on a physics
    fault (MuJoCo reported a diverging state and reset it; ``info["physics_fault"]`` is True and
    the step's reward is 0). ``truncated`` after ``max_episode_steps`` (1000 = 20 s at 50 Hz;
    a ``gym.make`` argument).

    **Simulation** — timestep 0.005 s, 4 substeps per control step (50 Hz). Reset noise
    U(-0.005, 0.005) on every robot qpos and qvel entry.

    :param task: task name (``"FT"``, ...) or a :class:`~unimal_envs.tasks.Task` instance.
    :param morphologies: ``"train"`` / ``"novel"`` (shipped generated sets, 100 each),
        ``"unimals100-train"`` / ``"unimals100-test"`` / ``"unimals100-mutants"`` (the official sets,
        fetched once with ``python -m unimal_envs.morphology fetch``), a directory in the unimals_100
        layout (``DIR/xml/*.xml``), or a list of MJCF paths.
    :param instruction: replaces the task's instruction; embedded with ``text_encoder``.
    :param text_encoder: encoder for a custom ``instruction`` (``"minilm"`` or ``"hash"``).
    :param ctrl_cost_weight: weight of the control cost (0.0 as in MetaMorph; DERL used 1e-3).
    :param reset_noise_scale: half-width of the uniform reset noise.
    :param render_mode: ``"rgb_array"`` (headless with ``MUJOCO_GL=egl``) or ``"human"``.
    :param width: rendered image width in pixels.
    :param height: rendered image height in pixels.
    :param world_cache_size: compiled worlds (one per morphology) kept in memory; terrain and props
        are re-randomised in place every episode, so a world is only compiled on a cache miss.
    :param height_reference: what the height column of ``proprioceptive`` (z of every body) is measured from:
        ``"world"`` (the z = 0 plane, MetaMorph's convention, default) or ``"ground"`` (the ground
        under the torso, ``arena.ground_height(x, y)``, subtracted from every real token's z): on an
        incline, a terrain or in a bowl the same posture then gives the same observation, so one set
        of normalisation statistics fits every task.
    :param goal_range: ``None`` (default, the reference's observation): ``goal`` and the position rows
        of ``object`` in raw metres. A distance R: each of those vectors longer than R is observed at
        length R in its own direction (nearer ones unchanged), so a far goal reads as "that way, far".
        PointNav's goals lie up to ~60 m away, Patrol's (the only training task with a goal) within
        ~10 m: with R = 10 a policy trained on Patrol sees PointNav's goals in the range it knows.
        Rewards and ``info`` are unchanged.
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": round(1.0 / CONTROL_DT)}

    def __init__(
        self,
        task: str | Task = "FT",
        morphologies: str | Path | Iterable[str | Path | Morphology] = "train",
        instruction: str | None = None,
        text_encoder: str = DEFAULT_ENCODER,
        ctrl_cost_weight: float = 0.0,
        reset_noise_scale: float = 0.005,
        render_mode: str | None = None,
        width: int = 480,
        height: int = 480,
        world_cache_size: int = 16,
        height_reference: str = "world",
        goal_range: float | None = None,
    ):
        if height_reference not in C.HEIGHT_REFERENCES:
            raise ValueError(
                f"height_reference must be one of {C.HEIGHT_REFERENCES} (what body heights in "
                f"'proprioceptive' are measured from), got {height_reference!r}"
            )
        self.height_reference = height_reference
        self.goal_range = C.check_goal_range(goal_range)
        if not float(reset_noise_scale) >= 0:  # (NaN included)
            raise ValueError(f"reset_noise_scale is the half-width of the uniform reset noise and must be >= 0, got {reset_noise_scale}")
        if int(world_cache_size) < 1:
            raise ValueError(f"world_cache_size is how many compiled worlds are kept and must be >= 1, got {world_cache_size}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be one of {self.metadata['render_modes']} or None, got {render_mode!r}")
        if render_mode == "human":
            _check_display()
        # An instance lists the render modes it can serve here: without a display, not "human"
        # (so that Gymnasium's check_env, which makes the env once per listed mode, passes headless).
        self.metadata = {**self.metadata, "render_modes": [m for m in self.metadata["render_modes"] if m != "human" or _has_display()]}
        self.task = make_task(task)
        self.morphologies: list[Morphology] = load_morphologies(morphologies)
        self.arena = self.task.arena
        self.instruction = instruction if instruction is not None else self.task.instruction
        self._task_embedding = embed_instruction(self.instruction, text_encoder)
        self._task_index = np.array([C.TASK_NAMES.index(self.task.name)], dtype=np.float32)
        self.ctrl_cost_weight = float(ctrl_cost_weight)
        self.reset_noise_scale = float(reset_noise_scale)
        self.render_mode = render_mode
        self.width, self.height = int(width), int(height)
        self.observation_space = C.observation_space()
        self.action_space = C.action_space()
        self.world_cache_size = int(world_cache_size)
        self._worlds: OrderedDict[int, _World] = OrderedDict()  # compiled worlds, least recently used first
        #: Per-morphology draw probabilities (``None``: uniform), set by a robot sampler.
        self._morphology_probabilities: np.ndarray | None = None
        self._world: _World | None = None
        self._viewer: Any = None  # mujoco.viewer's passive Handle, opened by the first human render
        #: Tracking camera: distance to the torso (``None`` = from the robot's size), azimuth, elevation.
        self.camera_distance: float | None = None
        self.camera_angles = (135.0, -20.0)
        #: World-frame offset (m) of the camera's look-at point from the torso (it still follows the robot).
        self.camera_offset = (0.0, 0.0, 0.0)

    # ------------------------------------------------------------------ world
    def world_spec(self, index: int) -> tuple[mujoco.MjSpec, Robot]:
        """The uncompiled world of morphology ``index`` (robot at the task's spawn pose, arena, task
        props) and its robot; the batched backend compiles the very same spec."""
        robot = Robot(self.morphologies[index])
        pos, quat = self.task.spawn_pose(robot)
        spec = robot.build_spec(pos, quat)
        self.arena.build(spec)
        self.task.build(spec)
        spec.visual.global_.offwidth = max(spec.visual.global_.offwidth, self.width)
        spec.visual.global_.offheight = max(spec.visual.global_.offheight, self.height)
        if self.render_mode is None:
            # Nothing draws this env's worlds, so its generated textures can be tiny: at full size
            # they are 13.8 MB of every compiled world (the 800x800 skybox alone 11.5 MB), which
            # made 32 envs x 16 cached worlds of 100 robots ~8 GB. Physics does not read them.
            for texture in spec.textures:
                if texture.builtin != mujoco.mjtBuiltin.mjBUILTIN_NONE:
                    texture.width, texture.height = (
                        min(texture.width, UNRENDERED_TEXTURE_SIZE),
                        min(texture.height, UNRENDERED_TEXTURE_SIZE),
                    )
        return spec, robot

    def _build_world(self, index: int) -> _World:
        spec, robot = self.world_spec(index)
        model = compile_world(spec, robot.morphology.name)
        model.vis.map.znear = CAMERA_NEAR / model.stat.extent
        model.vis.map.zfar = CAMERA_FAR / model.stat.extent
        model.vis.map.shadowclip = SHADOW_CLIP / model.stat.extent
        data = mujoco.MjData(model)
        robot.bind(model, data)
        return _World(model, data, robot)

    def _get_world(self, index: int) -> _World:
        """The compiled world of morphology ``index``, from the LRU cache or freshly built."""
        world = self._worlds.pop(index, None) or self._build_world(index)
        self._worlds[index] = world  # most recently used last
        while len(self._worlds) > self.world_cache_size:
            _, evicted = self._worlds.popitem(last=False)
            self._release(evicted)
        return world

    @property
    def _current(self) -> _World:
        """The world of the current episode (an AttributeError, as before, until :meth:`reset` made one)."""
        if self._world is None:
            raise AttributeError("no episode yet: call reset() first")
        return self._world

    @property
    def robot(self) -> Robot:
        """The robot of the current episode."""
        return self._current.robot

    @property
    def morphology(self) -> Morphology:
        """The morphology of the current episode."""
        return self._current.robot.morphology

    @property
    def model(self) -> mujoco.MjModel:
        return self._current.model

    @property
    def data(self) -> mujoco.MjData:
        return self._current.data

    # ------------------------------------------------------------------ gym API
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode with a randomly drawn morphology.

        :param seed: seeds the env's generator (morphology draw, terrain, noise).
        :param options: ``{"morphology": name or index}`` to choose the robot instead of drawing it.
        """
        super().reset(seed=seed)
        index = self._choose_morphology((options or {}).get("morphology"))
        world = self._world = self._get_world(index)
        model, data = world.model, world.data
        mujoco.mj_resetData(model, data)
        self.arena.bind(model, data)
        self.arena.reset(self.np_random)
        world.robot.reset(self.np_random, self.reset_noise_scale)
        mujoco.mj_forward(model, data)
        self.task.bind(model, data)
        self.task.reset(world.robot, self.np_random)
        world.stale_heightfields = True
        self._fall_height = self.task.fall_height_ratio * world.robot.morphology.standing_height
        self._fault_count_at_reset = self._fault_count()
        return self._observation(), {"morphology": world.robot.morphology.name, "task": self.task.name}

    def step(self, action: np.ndarray):
        world = self._world
        if world is None:
            raise RuntimeError("call reset() before step()")
        robot, data = world.robot, world.data
        action = self._checked_action(action)
        torso_before = robot.torso_position
        robot.apply_action(action)
        time_before = data.time
        mujoco.mj_step(world.model, data, nstep=_SUBSTEPS)
        robot.sync()

        info: dict[str, Any] = {"morphology": robot.morphology.name, "task": self.task.name, "physics_fault": False}
        # MuJoCo resets the data (time = 0) when the state diverges (non-finite or huge qpos,
        # qvel, qacc), so a step that ends earlier than 4 substeps later had a physics fault. A
        # reset during the first step of an episode keeps the time, so there count the warnings.
        faulted = data.time < time_before + 3.5 * _SUBSTEP
        if time_before == 0.0:
            faulted = faulted or self._fault_count() != self._fault_count_at_reset
        if faulted:
            info["physics_fault"] = True
            info["termination"] = "physics_fault"
            info["mujoco_warnings"] = self._fault_warnings()
            return self._observation(), 0.0, True, False, info

        reward = 0.0
        for term, value in self.task.reward_terms(robot, torso_before).items():
            info["reward_" + term] = value
            reward += value
        if self.ctrl_cost_weight:
            # Cost of the control the motors get (UNIMAL motors have ctrlrange [-1, 1], which MuJoCo
            # clamps to): an out-of-range action costs no more than the torque it produces, and a
            # huge finite one cannot turn the reward into -inf.
            real = np.clip(action[robot.real_slots], -1.0, 1.0)
            info["reward_ctrl"] = ctrl = -self.ctrl_cost_weight * float(real @ real)
            reward += ctrl

        reason = self.task.termination(robot)
        x, y, z = robot.torso_qpos.tolist()
        if z - self.arena.ground_height(x, y) <= self._fall_height:
            reason = "fall"
        info.update(self.task.metrics(robot))
        if reason is not None:
            info["termination"] = reason
        if self.render_mode == "human":
            self.render()
        return self._observation(), reward, reason is not None, False, info

    def _observation(self) -> dict[str, np.ndarray]:
        robot = self._current.robot
        morphology = robot.morphology
        # Eight small copies (~2 us) beat one packed copy handed out as views (~3 us, measured).
        proprioception = robot.proprioception()
        if self.height_reference == "ground":
            x, y = robot.torso_qpos[:2]
            proprioception[morphology.obs_padding_mask < 0.5, C.Z_COLUMN] -= self.arena.ground_height(float(x), float(y))
        obs = {
            "proprioceptive": proprioception,
            "context": morphology.context.copy(),
            "obs_padding_mask": morphology.obs_padding_mask.copy(),
            "act_padding_mask": morphology.act_padding_mask.copy(),
            "hfield": _ZEROS_HFIELD.copy(),
            "goal": _ZEROS_GOAL.copy(),
            "object": _ZEROS_OBJECT.copy(),
            "task_embedding": self._task_embedding.copy(),
            "task_index": self._task_index.copy(),
        }
        obs.update(self.task.observations(robot))
        if self.goal_range is not None:
            obs["goal"] = _bounded(obs["goal"][None], self.goal_range)[0]
            rows = obs["object"].reshape(4, 3)
            rows[list(C.OBJECT_POSITION_ROWS)] = _bounded(rows[list(C.OBJECT_POSITION_ROWS)], self.goal_range)
            obs["object"] = rows.reshape(-1)
        return obs

    def _checked_action(self, action: np.ndarray) -> np.ndarray:
        action = np.asarray(action)
        if action.shape != (C.ACTION_DIM,):
            raise ValueError(
                f"action has shape {action.shape}; Unimal envs take shape ({C.ACTION_DIM},) "
                f"({C.SLOTS_PER_TOKEN} hinge slots x {C.MAX_TOKENS} tokens, padded slots ignored)"
            )
        # One dot product is the cheapest finiteness test on the hot path; inspect only on failure.
        if not math.isfinite(action @ action):
            real = self._current.robot.real_slots
            bad = real[~np.isfinite(action[real])]
            if bad.size:
                raise ValueError(
                    f"action has non-finite values {action[bad].tolist()} in real hinge slots {bad.tolist()} "
                    f"(morphology {self.morphology.name}); the simulation was not stepped"
                )
        return action

    @property
    def morphology_names(self) -> list[str]:
        """Names of this env's morphologies, in draw order (the order of sampling probabilities)."""
        return [m.name for m in self.morphologies]

    def set_morphology_probabilities(self, probabilities: np.ndarray | None) -> None:
        """Draw morphologies with these probabilities from the next reset on (``None``: uniform).

        Used by MetaMorph's balanced robot sampler
        (:class:`sb3_divmorph.algos.recipe.BalancedRobotSampler`), through ``VecEnv.env_method``.

        :param probabilities: one non-negative weight per morphology (:attr:`morphology_names`
            order), normalised here.
        :raises ValueError: wrong length, negative, non-finite or all-zero weights.
        """
        if probabilities is None:
            self._morphology_probabilities = None
            return
        p = np.asarray(probabilities, dtype=np.float64)
        if p.shape != (len(self.morphologies),) or not np.all(np.isfinite(p)) or np.any(p < 0) or p.sum() <= 0:
            raise ValueError(
                f"morphology probabilities must be {len(self.morphologies)} finite non-negative weights "
                f"with a positive sum, got shape {p.shape}"
            )
        self._morphology_probabilities = p / p.sum()

    def _choose_morphology(self, choice: int | str | None) -> int:
        if choice is None:
            if self._morphology_probabilities is not None:
                return int(self.np_random.choice(len(self.morphologies), p=self._morphology_probabilities))
            return int(self.np_random.integers(len(self.morphologies)))
        if isinstance(choice, (int, np.integer)):
            if not 0 <= choice < len(self.morphologies):
                raise ValueError(f"morphology index {choice} out of range [0, {len(self.morphologies)})")
            return int(choice)
        names = [m.name for m in self.morphologies]
        if choice not in names:
            raise ValueError(f"unknown morphology '{choice}'; this env has {len(names)}: {names[:5]}...")
        return names.index(choice)

    def _fault_count(self) -> int:
        warnings = self._current.data.warning
        return sum(int(warnings[w].number) for w in _FAULT_WARNINGS)

    def _fault_warnings(self) -> dict[str, int]:
        warnings = self._current.data.warning
        return {mujoco.mjtWarning(w).name: int(warnings[w].number) for w in _FAULT_WARNINGS if warnings[w].number}

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        """An RGB frame (``rgb_array``) from a camera tracking the torso, or update the viewer (``human``)."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' to gym.make")
            return None
        world = self._current
        if self.render_mode == "human":
            self._render_human(world)
            return None
        if world.renderer is None:
            world.renderer = mujoco.Renderer(world.model, self.height, self.width)
        if world.stale_heightfields and world.model.nhfield:
            # The renderer keeps its own GPU copy of each heightfield; refresh it after a reset.
            world.renderer._gl_context.make_current()
            for hfield in range(world.model.nhfield):
                mujoco.mjr_uploadHField(world.model, world.renderer._mjr_context, hfield)
            world.stale_heightfields = False
        world.renderer.update_scene(world.data, camera=self._camera(world))
        return world.renderer.render()

    def _camera(self, world: _World) -> mujoco.MjvCamera:
        """A camera tracking the torso from :attr:`camera_distance` m (default: 2.5 m + 3 standing
        heights) at :attr:`camera_angles` (azimuth, elevation in degrees; azimuth 0 looks along +x,
        the forward direction of the locomotion tasks), aimed at the torso plus
        :attr:`camera_offset`. Clipping planes: :data:`CAMERA_NEAR`, :data:`CAMERA_FAR`."""
        camera = mujoco.MjvCamera()
        if any(self.camera_offset):  # a free camera re-aimed at the torso + offset every frame
            camera.type = mujoco.mjtCamera.mjCAMERA_FREE
            camera.lookat[:] = world.data.xpos[world.robot.torso_id] + np.asarray(self.camera_offset)
        else:
            camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
            camera.trackbodyid = world.robot.torso_id
        camera.distance = self.camera_distance or 2.5 + 3.0 * world.robot.morphology.standing_height
        camera.azimuth, camera.elevation = self.camera_angles
        return camera

    def _render_human(self, world: _World) -> None:
        import mujoco.viewer

        if self._viewer is None or self._viewer.m is not world.model:
            if self._viewer is not None:
                self._viewer.close()
            self._viewer = mujoco.viewer.launch_passive(world.model, world.data)
        self._viewer.sync()

    @staticmethod
    def _release(world: _World) -> None:
        if world.renderer is not None:
            world.renderer.close()
            world.renderer = None

    def close(self) -> None:
        for world in self._worlds.values():
            self._release(world)
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None
