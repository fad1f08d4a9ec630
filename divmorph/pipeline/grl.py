"""GRL (Genetic Reinforcement Learning, Feng et al. 2023) adapted to the morphology-aware Transformer.

GRL evolves a population of RL agents; what a child inherits from its parent (its *learngene*) is
a fragment of the parent's trained network, the rest of the child is initialised afresh, and the
child trains all of it (Lamarckian: nothing frozen). In GRL the agents are 6-layer MLPs and a
learngene is a pair of their layers. Here the agents are MetaMorph policies, and the inheritable
fragments are whole layers of the *actor* (:func:`layer_units`): the token embedding, each
Transformer block (attention + FFN + its layer norms), the exteroception encoders, and the
per-token decoder with its action head. A learngene is a set of ``grl.learngene_layers`` of them.

Evolution (``divmorph grl``; folders ``grl/gen-<g>/agent-<i>/``):

1. generation 0: ``grl.population`` agents, random init, each with a random learngene (which of its
   layers it will pass on), each trained with PPO for ``grl.steps_per_agent`` steps on a training
   task (agent ``i`` on task ``i mod T``), on the profile's training robots;
2. fitness: the agent's final training return (mean ``rollout/ep_rew_mean`` of its last 10% of
   rollouts), standardised within its task over every agent trained on that task so far (tasks'
   returns have different scales; a task with one agent gives 0);
3. generation ``g+1``: each child picks its parent by a tournament of ``grl.tournament`` agents of
   generation ``g``, inherits the parent's learngene layers (weights and observation statistics),
   with probability ``grl.mutation`` swaps one layer of the learngene for another, and trains;
4. after ``grl.generations`` generations the fittest agent of the last one gives the learngene
   (``grl/learngene.json``): the ``grl`` transfer arm builds a new MetaMorph, copies those layers
   into it, and trains everything on the novel task.

Simplifications against GRL: no gene pool with decayed, back-propagated credit (the learngene is
the fittest last-generation agent's), and fitness is not normalised by layer size. Every agent
uses ``teachers.policy_kwargs`` on the policy's preset (one architecture for every task, so that
layers fit into any agent); the agents of a generation are independent runs of the grid
(:mod:`divmorph.pipeline.grid`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3 import PPO

from divmorph.pipeline.config import Profile, grl_policy_kwargs, load_zoo_entry  # noqa: F401 -- re-exported
from divmorph.pipeline.folders import agent_folder, grl_folder, learngene_file, read_learngene  # noqa: F401 -- re-exported
from divmorph.pipeline.envs import inherited_normalizer, make_vec_env, normalizer_for, profile_env_kwargs, resolve_device, task_env_name
from divmorph.pipeline.files import atomic_write_json, is_done, mark_done, read_progress
from divmorph.pipeline.robots import profile_robots
from divmorph.pipeline.training import TrainingRun, stage_model
from sb3_divmorph.policies.learngene import inherit, layer_units, unit_tensors  # noqa: F401 -- re-exported

POLICY = "MetaMorphPolicy"


@dataclass
class AgentPlan:
    """One agent of a generation: its task, its learngene and (after generation 0) its parent."""

    index: int
    task: str
    learngene: list[str]
    parent: int | None = None


def _rng(profile: Profile, generation: int) -> np.random.Generator:
    return np.random.default_rng([profile.seed, 4242, generation])


def _unit_names(profile: Profile) -> list[str]:
    """Names of the inheritable layers of this profile's agents."""
    import gymnasium as gym

    from sb3_divmorph.policies.morphology_transformer import MetaMorphPolicy

    env = gym.make(task_env_name(profile.teachers.tasks[0]), morphologies=profile_robots(profile, "train")[:1])
    assert isinstance(env.observation_space, gym.spaces.Dict) and isinstance(env.action_space, gym.spaces.Box)
    policy = MetaMorphPolicy(env.observation_space, env.action_space, lambda _: 1e-3, **grl_policy_kwargs(profile))
    env.close()
    return list(layer_units(policy))


def fitness(out: Path, plans: dict[int, list[AgentPlan]]) -> dict[tuple[int, int], float]:
    """``{(generation, agent): fitness}`` for every trained agent (see the module docstring)."""
    raw: dict[tuple[int, int], tuple[str, float]] = {}
    for generation, agents in plans.items():
        for agent in agents:
            progress = read_progress(agent_folder(out, generation, agent.index))
            values = progress.get("rollout/ep_rew_mean", np.array([]))
            values = values[np.isfinite(values)]
            final = float(values[-max(1, len(values) // 10) :].mean()) if len(values) else float("-inf")
            raw[(generation, agent.index)] = (agent.task, final)
    scores = {}
    for key, (task, value) in raw.items():
        same = np.array([v for t, v in raw.values() if t == task and np.isfinite(v)])
        sd = same.std() if len(same) > 1 else 0.0
        scores[key] = float((value - same.mean()) / sd) if sd > 0 and np.isfinite(value) else (0.0 if np.isfinite(value) else -np.inf)
    return scores


def read_plan(out: Path, generation: int) -> list[AgentPlan]:
    """The planned agents of ``generation``."""
    return [AgentPlan(**a) for a in json.loads((grl_folder(out) / f"gen-{generation}" / "plan.json").read_text())]


def plan_generation(profile: Profile, out: Path, generation: int, plans: dict[int, list[AgentPlan]]) -> list[AgentPlan]:
    """The agents of ``generation`` (read back if planned before, so a resumed evolution is the same)."""
    path = grl_folder(out) / f"gen-{generation}" / "plan.json"
    if path.is_file():
        return read_plan(out, generation)
    cfg = profile.grl
    rng = _rng(profile, generation)
    tasks = list(profile.teachers.tasks)
    units = _unit_names(profile)
    size = min(cfg.learngene_layers, len(units))
    agents = []
    if generation == 0:
        for i in range(cfg.population):
            learngene = sorted(rng.choice(units, size, replace=False).tolist())
            agents.append(AgentPlan(i, tasks[i % len(tasks)], learngene))
    else:
        previous = plans[generation - 1]
        scores = fitness(out, {g: p for g, p in plans.items() if g < generation})
        for i in range(cfg.population):
            entrants = rng.choice(len(previous), min(cfg.tournament, len(previous)), replace=False)
            parent = max(entrants, key=lambda j: (scores[(generation - 1, previous[j].index)], -j))
            learngene = list(previous[parent].learngene)
            others = [u for u in units if u not in learngene]
            if others and rng.random() < cfg.mutation:
                learngene[rng.integers(len(learngene))] = str(rng.choice(others))
            agents.append(AgentPlan(i, tasks[i % len(tasks)], sorted(learngene), int(previous[parent].index)))
    atomic_write_json(path, [a.__dict__ for a in agents])
    return agents


def agent_run(profile: Profile, out: Path, generation: int, index: int, progress_bar: bool = True) -> TrainingRun:
    """The (resumable) PPO run of one agent; a child inherits its parent's learngene when built.

    :param generation: the agent's generation (its plan, ``grl/gen-<g>/plan.json``, must exist).
    :param index: the agent's index in that generation.
    """
    plan = {a.index: a for a in read_plan(out, generation)}[index]
    env_name = task_env_name(plan.task)
    entry = load_zoo_entry(profile.teachers.hyperparams, env_name, {**profile.teachers.overrides, **profile.grl.overrides})
    robots = profile_robots(profile, "train")
    seed = profile.seed + 20_000 + 100 * generation + index
    device = resolve_device(profile.device)
    gamma = entry.ppo_kwargs.get("gamma", 0.99)
    kwargs = grl_policy_kwargs(profile)

    def make_env():
        return make_vec_env(env_name, entry.n_envs, seed, profile.max_episode_steps, morphologies=robots, **profile_env_kwargs(profile))

    def make_model():
        if plan.parent is None:
            venv = normalizer_for(make_env(), entry.normalize, gamma)
            return PPO(POLICY, venv, policy_kwargs=kwargs, seed=seed, device=device, **entry.ppo_kwargs)
        parent_folder = agent_folder(out, generation - 1, plan.parent)
        venv = inherited_normalizer(parent_folder, make_env(), gamma)
        model = PPO(POLICY, venv, policy_kwargs=kwargs, seed=seed, device=device, **entry.ppo_kwargs)
        parent = PPO.load(stage_model(parent_folder), device=device)
        inherit(model.policy, parent.policy, plan.learngene)
        return model

    return TrainingRun(
        agent_folder(out, generation, index),
        profile.grl.steps_per_agent,
        profile.teachers.checkpoint_every,
        make_model,
        make_env,
        device=device,
        progress_bar=progress_bar,
    )


def evolve(profile: Profile, out: Path, backend=None, progress_bar: bool = True) -> dict[str, Any]:
    """Run (or resume, or skip when done) GRL's evolution; returns the learngene.

    :param backend: a :mod:`~divmorph.pipeline.grid` backend for each generation's agents (default: local).
    """
    from divmorph.pipeline.grid import Job, LocalBackend, run_grid

    out = Path(out)
    if is_done(grl_folder(out)):
        return read_learngene(out)
    backend = backend or LocalBackend()
    cfg = profile.grl
    plans: dict[int, list[AgentPlan]] = {}
    for generation in range(cfg.generations):
        plans[generation] = plan_generation(profile, out, generation, plans)
        print(
            f"[grl] generation {generation + 1}/{cfg.generations}: {len(plans[generation])} agents x "
            f"{cfg.steps_per_agent} steps -> {grl_folder(out) / f'gen-{generation}'}"
        )
        jobs = [
            Job(
                f"{__name__}:agent_run",
                (generation, a.index),
                agent_folder(out, generation, a.index),
                f"grl gen {generation} agent {a.index} ({a.task}, learngene {'+'.join(a.learngene)})",
            )
            for a in plans[generation]
        ]
        run_grid(profile, out, jobs, backend, progress_bar=progress_bar).raise_on_failure()
    scores = fitness(out, plans)
    last = cfg.generations - 1
    best = max(plans[last], key=lambda a: (scores[(last, a.index)], -a.index))
    learngene = {
        "units": best.learngene,
        "generation": last,
        "agent": best.index,
        "task": best.task,
        "fitness": scores[(last, best.index)],
        "folder": str(agent_folder(out, last, best.index).relative_to(out)),
    }
    atomic_write_json(learngene_file(out), learngene)
    mark_done(grl_folder(out), learngene=learngene)
    print(
        f"[grl] learngene: {'+'.join(best.learngene)} of agent {best.index} (generation {last}, {best.task}, "
        f"fitness {learngene['fitness']:.2f})"
    )
    return learngene
