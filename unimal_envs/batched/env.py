"""The batched UNIMAL env: every task and MultiTask on MuJoCo Warp, as an SB3 VecEnv and in torch."""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import warp as wp
from stable_baselines3.common.vec_env import VecEnv

from unimal_envs import contract as C
from unimal_envs.batched.tasks import FALL, PHYSICS_FAULT, REASONS, Readings, make_batched_task
from unimal_envs.batched.terrain import HeightMaps, TerrainPool
from unimal_envs.batched.worlds import N_READINGS, OVERFLOW_MASK, OVERFLOWS, READINGS, RobotWorlds, run_physics
from unimal_envs.env import UnimalEnv
from unimal_envs.instructions import DEFAULT_ENCODER
from unimal_envs.morphology.loader import load_morphologies

#: Observation keys, in the contract's order.
KEYS = tuple(C.observation_space().spaces)
#: Keys whose values are fixed per world (its robot and task).
STATIC_KEYS = ("context", "obs_padding_mask", "act_padding_mask", "task_embedding", "task_index")
#: Terrain variants drawn per terrain task (see :func:`make_batched_env`).
DEFAULT_TERRAIN_VARIANTS = 64
#: Refuse a batch whose estimated memory exceeds this share of the device's free memory.
MEMORY_SHARE = 0.8


def _bounded(vectors: torch.Tensor, limit: float) -> torch.Tensor:
    """Each 3-vector (last axis) longer than ``limit``, scaled to length ``limit`` (``goal_range``)."""
    length = torch.linalg.vector_norm(vectors, dim=-1, keepdim=True)
    return vectors * torch.clamp(limit / length.clamp_min(1e-9), max=1.0)


class _TaskBlock:
    """The worlds of one task: one :class:`RobotWorlds` per robot, ``worlds`` each, and the
    task's batched twin over all of them (rows ordered robot by robot)."""

    def __init__(self, env: UnimalEnv, worlds: int, device: str, variants: int, seed: int, generator: torch.Generator):
        self.env, self.task_name = env, env.task.name
        probe = env._get_world(0)  # the single env's own compiled world draws the terrain pool
        self.pool = TerrainPool.draw(env.arena, probe.model, probe.data, variants, np.random.default_rng(seed))
        env.close()
        self.groups: list[RobotWorlds] = []
        for i in range(len(env.morphologies)):  # the first robot's model holds the pool's height fields
            self.groups.append(RobotWorlds(env, i, worlds, device, self.pool, terrain_from=self.groups[0] if i else None))
        dev = self.groups[0].torch_device
        self.n, self.worlds, self.device, self.generator = worlds * len(self.groups), worlds, dev, generator
        self.heightmaps = HeightMaps(self.pool, dev) if self.pool is not None else None
        self.layout = (
            torch.as_tensor(self.pool.obstacle_layout, dtype=torch.float32, device=dev)
            if self.pool is not None and self.pool.obstacle_layout is not None
            else None
        )
        self.task = make_batched_task(env.task, self.n, dev, self.heightmaps, generator)
        # The buffers every robot's physics program reads (actions) and writes (observations).
        self.actions = torch.zeros(self.n, C.ACTION_DIM, device=dev)
        self.proprio = torch.zeros(self.n, C.MAX_TOKENS, C.PROPRIO_DIM, device=dev)
        self.readings = torch.zeros(self.n, N_READINGS, device=dev)
        for i, group in enumerate(self.groups):
            rows = self.rows(i)
            group.bind_buffers(self.actions[rows], self.proprio[rows], self.readings[rows])
        self.variant = torch.zeros(self.n, dtype=torch.long, device=dev)
        per_robot = lambda values: torch.as_tensor(np.repeat(np.stack(values), worlds, axis=0), device=dev)  # noqa: E731
        morphologies = [g.morphology for g in self.groups]
        self.static = {
            "context": per_robot([m.context for m in morphologies]),
            "obs_padding_mask": per_robot([m.obs_padding_mask for m in morphologies]),
            "act_padding_mask": per_robot([m.act_padding_mask for m in morphologies]),
            "task_embedding": torch.as_tensor(env._task_embedding, device=dev).expand(self.n, -1),
            "task_index": torch.as_tensor(env._task_index, device=dev).expand(self.n, -1),
        }
        self.real_slots = 1.0 - self.static["act_padding_mask"]
        # height_reference "ground": every real token's z is measured from the ground under the torso, as in the single env
        self.ground_reference = env.height_reference == "ground"
        self.goal_range = env.goal_range
        self.real_tokens = self.static["obs_padding_mask"] < 0.5
        self.fall_height = per_robot([[g.fall_height] for g in self.groups])[:, 0].float()
        self.names = [m.name for m in morphologies for _ in range(worlds)]

    def rows(self, i: int) -> slice:
        return slice(i * self.worlds, (i + 1) * self.worlds)

    def read(self) -> Readings:
        """The readings the last physics program wrote (a copy: tasks keep some across steps)."""
        readings = self.readings.clone()
        column = lambda name: readings[:, READINGS[name]]  # noqa: E731
        r = Readings(column("torso"), column("torso_velocity"), column("torso_xmat").view(self.n, 3, 3), self.variant)
        if self.task.has_box:
            r.box, r.box_velocity, r.box_angular, r.reach = column("box"), column("box_velocity"), column("box_angular"), column("reach")
        return r

    def observe(self, r: Readings) -> dict[str, torch.Tensor]:
        proprioceptive = self.proprio.clone()
        if self.ground_reference:
            proprioceptive[..., C.Z_COLUMN] -= self.task.ground_height(r)[:, None] * self.real_tokens
        obs = {
            "proprioceptive": proprioceptive,
            **self.static,
            "hfield": torch.zeros(self.n, C.HFIELD_DIM, device=self.device),
            "goal": torch.zeros(self.n, C.GOAL_DIM, device=self.device),
            "object": torch.zeros(self.n, C.OBJECT_DIM, device=self.device),
        }
        obs.update(self.task.observations(r))
        if self.goal_range is not None:
            obs["goal"] = _bounded(obs["goal"], self.goal_range)
            rows = obs["object"].view(self.n, 4, 3).clone()
            rows[:, list(C.OBJECT_POSITION_ROWS)] = _bounded(rows[:, list(C.OBJECT_POSITION_ROWS)], self.goal_range)
            obs["object"] = rows.view(self.n, -1)
        return obs

    def reset(self, mask: torch.Tensor, noise: float) -> None:
        """New episodes where ``mask`` (N,) is true: terrain variant, props, robot state, task state."""
        if self.pool is not None:
            draw = torch.randint(self.pool.variants, (self.n,), generator=self.generator, device=self.device)
            self.variant = torch.where(mask, draw, self.variant)
        props = self.task.props(mask)
        for i, group in enumerate(self.groups):
            rows = self.rows(i)
            if self.pool is not None:
                group.select_terrain(mask[rows], self.variant[rows], self.layout)
            placed = None
            if props is not None:
                assert group.box_qpos is not None  # props are the box's pose: its robot's world has the box
                placed = (group.box_qpos, props[rows])
            group.reset(mask[rows], noise, self.generator, placed)
        run_physics(self.groups, "sync")
        self.task.reset(mask, self.read())

    def take_overflow(self) -> torch.Tensor:
        """(N,) the capacity-overflow bits (:data:`OVERFLOWS`) each world raised since the last
        call, which clears them."""
        flags = torch.cat([g.overflow for g in self.groups]) & OVERFLOW_MASK
        for group in self.groups:
            group.overflow.zero_()
        return flags

    def step(self, actions: torch.Tensor, ctrl_cost_weight: float):
        """One control step of every world: (readings, reward, reward terms, reason codes)."""
        before = self.readings[:, READINGS["torso"]].clone()
        self.actions.copy_(actions)
        run_physics(self.groups, "step")
        r = self.read()
        faults = self.readings[:, READINGS["fault"]] > 0
        terms = self.task.reward_terms(r, before)
        if ctrl_cost_weight:
            real = actions.clamp(-1.0, 1.0) * self.real_slots
            terms["ctrl"] = -ctrl_cost_weight * (real * real).sum(1)
        reward = sum(terms.values())
        reason = self.task.termination(r)
        fell = r.torso[:, 2] - self.task.ground_height(r) <= self.fall_height
        reason = torch.where(fell, FALL, reason)
        reason = torch.where(faults, PHYSICS_FAULT, reason)
        reward = torch.where(faults, 0.0, reward)
        return r, reward, terms, reason


class BatchedUnimalEnv(VecEnv):
    """A UNIMAL task (or MultiTask) in ``robots x worlds_per_robot`` MuJoCo Warp worlds.

    Every world follows :class:`~unimal_envs.env.UnimalEnv` -- same compiled world, observation
    contract, reward terms, terminations and 1000-step truncation -- with two differences that
    batching imposes: each world keeps its robot (world ``i`` simulates robot
    ``i // worlds_per_robot``; MetaMorph's robot sampling does not apply), and random terrain is
    drawn from a pool of ``terrain_variants`` arenas (every reset picks one per world).

    Two interfaces on one object:

    * **SB3 VecEnv** (numpy): ``reset()`` / ``step(actions)`` with dict observations of shape
      ``(num_envs, ...)``, per-world auto-reset with ``info["terminal_observation"]`` and
      ``info["TimeLimit.truncated"]``, so ``PPO(DivMorphPolicy, env)`` and ``VecNormalize`` work.
    * **torch** (on the device): :meth:`reset_tensors` and :meth:`step_tensors`.

    A world whose state becomes non-finite (or beyond MuJoCo's 1e10 limit) ends its episode with
    ``info["physics_fault"] = True`` and reward 0, as in the single env; other worlds go on.

    **No silent departures.** MuJoCo Warp allocates contacts and constraint rows up front
    (:data:`~unimal_envs.batched.worlds.CONTACTS_PER_WORLD`, ``CONSTRAINTS_PER_WORLD``) and keeps
    a bounded number of contacts per height-field pair; past those limits it drops contacts. Every
    step's overflow bits are reported per world (``info["overflow"]``: a (N,) bitmask tensor in
    :meth:`step_tensors`; in the VecEnv infos, ``info["overflow"]``: the names, only for worlds that
    overflowed) and counted in :attr:`overflow_counts` (world-steps per kind,
    :meth:`overflow_report`).

    Build it with :func:`unimal_envs.batched.make_batched_env`.
    """

    def __init__(
        self, blocks: list[_TaskBlock], device: str, seed: int, max_episode_steps: int, ctrl_cost_weight: float, reset_noise_scale: float
    ):
        self.blocks = blocks
        self.warp_device = device
        self.torch_device = blocks[0].device
        self.max_episode_steps = int(max_episode_steps)
        self.ctrl_cost_weight = float(ctrl_cost_weight)
        self.reset_noise_scale = float(reset_noise_scale)
        self.worlds_per_robot = blocks[0].worlds
        n = sum(b.n for b in blocks)
        self.render_mode = None
        super().__init__(n, C.observation_space(), C.action_space())
        #: what the height column of ``proprioceptive`` is measured from (``world`` or ``ground``, as the single env's)
        self.height_reference = blocks[0].env.height_reference
        #: ``None`` or the length beyond which goal and object positions are observed at that length (as the single env's)
        self.goal_range = blocks[0].env.goal_range
        self.morphology_names = [name for b in blocks for name in b.names]
        self.task_names = [b.task_name for b in blocks for _ in range(b.n)]
        self.steps = torch.zeros(n, dtype=torch.long, device=self.torch_device)
        #: world-steps that hit each capacity overflow (:data:`~unimal_envs.batched.worlds.OVERFLOWS` order)
        self.overflow_counts = torch.zeros(len(OVERFLOWS), dtype=torch.long, device=self.torch_device)
        self._overflow_bits = torch.tensor(list(OVERFLOWS.values()), device=self.torch_device)
        self._actions: np.ndarray | None = None
        self._static_numpy: dict[str, np.ndarray] | None = None
        self._seed = seed
        self.seed(seed)

    # ------------------------------------------------------------------ torch interface
    def reset_tensors(self) -> dict[str, torch.Tensor]:
        """Start an episode in every world; observations as (num_envs, ...) tensors on the device."""
        everywhere = torch.ones(self.num_envs, dtype=torch.bool, device=self.torch_device)
        self.steps.zero_()
        for block, rows in self._rows():
            block.reset(everywhere[rows], self.reset_noise_scale)
        return self._observe()

    def step_tensors(self, actions: torch.Tensor):
        """Step every world with (num_envs, 24) actions on the device.

        :return: ``(obs, reward, terminated, truncated, info)``: ``obs`` after auto-reset; ``info``
            holds ``final_observation`` (the observations before the reset), ``termination``
            (reason codes, :data:`unimal_envs.batched.tasks.REASONS`), ``physics_fault`` and the
            reward terms ``reward_<term>`` (tensors; terms of tasks a world does not run are 0).
        """
        actions = torch.as_tensor(actions, dtype=torch.float32, device=self.torch_device)
        if actions.shape != (self.num_envs, C.ACTION_DIM):
            raise ValueError(f"actions have shape {tuple(actions.shape)}; this env takes ({self.num_envs}, {C.ACTION_DIM})")
        reward = torch.empty(self.num_envs, device=self.torch_device)
        reason = torch.empty(self.num_envs, dtype=torch.long, device=self.torch_device)
        terms: dict[str, torch.Tensor] = {}
        readings = []
        for block, rows in self._rows():
            r, reward[rows], block_terms, reason[rows] = block.step(actions[rows], self.ctrl_cost_weight)
            readings.append(r)
            for term, value in block_terms.items():
                terms.setdefault("reward_" + term, torch.zeros(self.num_envs, device=self.torch_device))[rows] = value
        overflow = torch.cat([block.take_overflow() for block in self.blocks]).long()
        self.overflow_counts += ((overflow[:, None] & self._overflow_bits) != 0).sum(0)
        self.steps += 1
        terminated = reason > 0
        truncated = (self.steps >= self.max_episode_steps) & ~terminated
        final = self._observe(readings)
        done = terminated | truncated
        info = {"final_observation": final, "termination": reason, "physics_fault": reason == PHYSICS_FAULT, "overflow": overflow, **terms}
        info["metrics"] = (
            {k: v for block, r in zip(self.blocks, readings) for k, v in block.task.metrics(r).items()} if len(self.blocks) == 1 else {}
        )
        if bool(done.any()):
            self.steps.masked_fill_(done, 0)
            for block, rows in self._rows():
                block.reset(done[rows], self.reset_noise_scale)
            obs = self._observe()
        else:
            obs = final
        return obs, reward, terminated, truncated, info

    def overflow_report(self) -> dict[str, int]:
        """World-steps so far that hit each capacity overflow (only the kinds that occurred)."""
        return {name: int(n) for name, n in zip(OVERFLOWS, self.overflow_counts.tolist()) if n}

    def _rows(self):
        start = 0
        for block in self.blocks:
            yield block, slice(start, start + block.n)
            start += block.n

    def _observe(self, readings: list[Readings] | None = None) -> dict[str, torch.Tensor]:
        parts = [b.observe(r) for b, r in zip(self.blocks, readings or [b.read() for b in self.blocks])]
        if len(parts) == 1:
            return parts[0]
        return {k: torch.cat([p[k] for p in parts]) for k in KEYS}

    # ------------------------------------------------------------------ SB3 VecEnv
    def reset(self) -> dict[str, np.ndarray]:
        self.reset_infos = [{"morphology": m, "task": t} for m, t in zip(self.morphology_names, self.task_names)]
        return self._numpy(self.reset_tensors())

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self):
        obs, reward, terminated, truncated, info = self.step_tensors(torch.as_tensor(np.asarray(self._actions)))
        obs_np = self._numpy(obs)
        reward_np = reward.cpu().numpy()
        terminated_np, truncated_np = terminated.cpu().numpy(), truncated.cpu().numpy()
        dones = terminated_np | truncated_np
        infos: list[dict[str, Any]] = [{"morphology": m, "task": t} for m, t in zip(self.morphology_names, self.task_names)]
        overflow = info["overflow"].cpu().numpy()
        for i in np.flatnonzero(overflow):
            infos[i]["overflow"] = [name for name, bit in OVERFLOWS.items() if overflow[i] & bit]
        ended = np.flatnonzero(dones)
        if ended.size:
            index = torch.as_tensor(ended, device=self.torch_device)
            final = {k: v[index].cpu().numpy() for k, v in info["final_observation"].items()}
            faults = info["physics_fault"][index].cpu().numpy()
            reasons = info["termination"][index].cpu().numpy()
            metrics = {k: v[index].cpu().numpy() for k, v in info["metrics"].items()}
            for j, i in enumerate(ended):
                terminal = {k: np.nan_to_num(v[j]) if faults[j] else v[j] for k, v in final.items()}
                infos[i].update(
                    terminal_observation=terminal, physics_fault=bool(faults[j]), **{k: float(v[j]) for k, v in metrics.items()}
                )
                infos[i]["TimeLimit.truncated"] = bool(truncated_np[i])
                if reasons[j]:
                    infos[i]["termination"] = REASONS[reasons[j]]
        return obs_np, reward_np.astype(np.float32), dones, infos

    def _numpy(self, obs: dict[str, torch.Tensor]) -> dict[str, np.ndarray]:
        """Observations on the host; the keys that never change (morphology, task) are copied from
        a host cache instead of from the device."""
        if self._static_numpy is None:
            self._static_numpy = {k: obs[k].cpu().numpy() for k in STATIC_KEYS}
        return {k: self._static_numpy[k].copy() if k in STATIC_KEYS else obs[k].cpu().numpy() for k in KEYS}

    def close(self) -> None:
        self.blocks = []

    def seed(self, seed: int | None = None) -> list[int | None]:
        """Seed the device generator (terrain draws, reset noise, goals, props)."""
        seed = self._seed if seed is None else int(seed)
        for block in self.blocks:
            block.generator.manual_seed(seed)
        return [seed] * self.num_envs

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        """Per-world ``morphology`` / ``task`` names, else this env's attribute once per world."""
        rows = self._get_indices(indices)
        if attr_name == "morphology":
            return [self.morphology_names[i] for i in rows]
        if attr_name == "task":
            return [self.task_names[i] for i in rows]
        return [getattr(self, attr_name)] * len(list(self._get_indices(indices)))

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        raise AttributeError(f"the batched env's worlds have no settable attribute {attr_name!r}")

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        if method_name == "set_morphology_probabilities":
            raise NotImplementedError(
                "the batched backend simulates every robot in its own fixed worlds (worlds_per_robot each), "
                "so robot sampling (set_morphology_probabilities, the balanced robot sampler) does not apply; "
                "use the single backend for MetaMorph's robot sampler"
            )
        raise AttributeError(f"the batched env has no per-world method {method_name!r}")

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False] * len(list(self._get_indices(indices)))

    def get_images(self):
        raise NotImplementedError("the batched env does not render; render a world with the single env (gym.make)")


def _warp_device(device: str) -> str:
    """A Warp device name for ``device`` (``cpu``, ``cuda``, ``cuda:N``, ``auto``), checked to exist."""
    if device == "auto":
        device = "cuda" if wp.is_cuda_available() else "cpu"
    if device == "cuda":
        device = "cuda:0"
    available = [str(d) for d in wp.get_devices()]
    if device not in available:
        raise ValueError(
            f"device {device!r} does not exist here; available Warp devices: {available}"
            + ("" if wp.is_cuda_available() else " (no CUDA driver found)")
        )
    return device


def _free_memory(device: str) -> int:
    if device == "cpu":
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    return int(wp.get_device(device).free_memory)


def estimate_memory(env: UnimalEnv, device: str, terrain_variants: int) -> tuple[int, int, int]:
    """(bytes per world, fixed bytes per robot, bytes per task) of a task's worlds on ``device``:
    the data of a 1- and a 2-world allocation of the first robot's world, and the task's pool of
    height fields (one copy per task, shared by its robots)."""
    import mujoco_warp as mjw

    from unimal_envs.batched.worlds import CONSTRAINTS_PER_WORLD, CONTACTS_PER_WORLD

    spec, _ = env.world_spec(0)
    model = spec.compile()

    def size(n: int) -> int:
        with wp.ScopedDevice(device):
            data = mjw.make_data(model, nworld=n, nconmax=CONTACTS_PER_WORLD, njmax=CONSTRAINTS_PER_WORLD)
        return sum(v.capacity for v in vars(data).values() if isinstance(v, wp.array))

    one, two = size(1), size(2)
    return two - one, 2 * one - two, 4 * model.nhfielddata * terrain_variants


def make_batched_env(
    task: str = "FT",
    morphologies: str | Path | Iterable[str | Path] = "train",
    worlds_per_robot: int = 16,
    device: str = "auto",
    seed: int = 0,
    max_episode_steps: int = 1000,
    tasks: Sequence[str] | None = None,
    terrain_variants: int = DEFAULT_TERRAIN_VARIANTS,
    ctrl_cost_weight: float = 0.0,
    reset_noise_scale: float = 0.005,
    instruction: str | None = None,
    text_encoder: str = DEFAULT_ENCODER,
    height_reference: str = "world",
    goal_range: float | None = None,
) -> BatchedUnimalEnv:
    """A UNIMAL task on MuJoCo Warp: ``len(morphologies) x worlds_per_robot`` worlds (see
    :class:`BatchedUnimalEnv`).

    :param task: a task name (``"FT"``, ...) or ``"MultiTask"`` (the worlds of every robot are
        repeated for each of ``tasks``, so a batch mixes tasks evenly).
    :param morphologies: as for :class:`~unimal_envs.env.UnimalEnv` (a set name, a folder, paths).
    :param worlds_per_robot: worlds simulated per robot (and per task for MultiTask).
    :param device: ``"cuda"``, ``"cuda:N"``, ``"cpu"`` (CPU Warp: slow, for tests) or ``"auto"``.
    :param seed: seeds terrain pools, reset noise, goals and props.
    :param max_episode_steps: truncation, as ``gym.make``'s (1000).
    :param tasks: MultiTask's tasks (default: the five training tasks).
    :param terrain_variants: arenas drawn per terrain task (VT, Obstacle, Escape), once, with the
        single env's arena code; every reset picks one per world, so a run sees this many distinct
        terrains. One copy per task lives on the device, shared by its robots: a VT variant is
        1.8 MB of height field, an Escape variant 4 MB (64 variants: 113 MB and 256 MB), an
        Obstacle variant 1.2 KB. 64 by default (a 2e7-step run of 100 robots sees each terrain
        ~300 times); profiles set it per stage (``terrain_variants``).
    :param ctrl_cost_weight: as for the single env.
    :param reset_noise_scale: as for the single env.
    :param instruction: replaces the task's instruction (its embedding is the ``task_embedding``
        observation), embedded with ``text_encoder``; not with MultiTask.
    :param height_reference: what the height column of ``proprioceptive`` is measured from, as for
        :class:`~unimal_envs.env.UnimalEnv`: ``"world"`` (z = 0) or ``"ground"`` (the ground under
        the torso: the incline's plane, the terrain variant's height field; flat arenas: 0).
    :param goal_range: as for :class:`~unimal_envs.env.UnimalEnv`: ``None`` (raw metres) or the
        length beyond which ``goal`` and ``object``'s positions are observed at that length.
    :raises ValueError: unknown task, a device that does not exist, fewer than one world, or more
        worlds than the device's free memory holds (estimated before anything is allocated).
    :raises MorphologyError: a robot whose world MuJoCo Warp cannot simulate (named, with the feature).
    """
    if int(worlds_per_robot) < 1:
        raise ValueError(f"worlds_per_robot must be at least 1, got {worlds_per_robot}")
    if int(terrain_variants) < 1:
        raise ValueError(f"terrain_variants must be at least 1, got {terrain_variants}")
    warp_device = _warp_device(device)
    if device == "auto":
        print(f"[batched] device auto -> {warp_device}")
    names = list(tasks or C.TRAIN_TASKS) if task == "MultiTask" else [task]
    if task == "MultiTask" and instruction is not None:
        raise ValueError("MultiTask uses each task's own instruction; 'instruction' is not accepted")
    robots = load_morphologies(morphologies)
    envs = [
        UnimalEnv(
            name,
            robots,
            instruction=instruction,
            text_encoder=text_encoder,
            ctrl_cost_weight=ctrl_cost_weight,
            reset_noise_scale=reset_noise_scale,
            height_reference=height_reference,
            goal_range=goal_range,
        )
        for name in names
    ]
    total = len(robots) * int(worlds_per_robot) * len(envs)
    per_world, per_robot, per_task = estimate_memory(envs[0], warp_device, int(terrain_variants))
    needed = per_world * total + (per_robot * len(robots) + per_task) * len(envs)
    free = _free_memory(warp_device)
    if needed > MEMORY_SHARE * free:
        raise ValueError(
            f"{total} worlds ({len(robots)} robots x {worlds_per_robot} worlds x {len(envs)} task(s)) need about "
            f"{needed / 2**30:.1f} GiB on {warp_device} (estimated from the first robot: {per_world / 2**20:.2f} MiB "
            f"per world), but only {free / 2**30:.1f} GiB is free; lower worlds_per_robot to at most "
            f"{max(1, int(MEMORY_SHARE * free / max(per_world, 1) / (len(robots) * len(envs))))}"
        )
    generator = torch.Generator(device=torch.device(warp_device))
    blocks = [_TaskBlock(env, int(worlds_per_robot), warp_device, int(terrain_variants), seed + k, generator) for k, env in enumerate(envs)]
    return BatchedUnimalEnv(blocks, warp_device, seed, max_episode_steps, ctrl_cost_weight, reset_noise_scale)
