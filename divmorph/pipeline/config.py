"""Pipeline profiles (``zoo_configs/divmorph.yml``), validated (rl-zoo entries: :mod:`sb3_divmorph.zoo`).

A profile is plain YAML; every section maps onto a dataclass below, and a key the dataclass does
not have is an error that names it and lists the valid ones (a typo must never be silently
ignored in a run that takes hours).
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from sb3_divmorph.algos.finetune import RECIPES
from sb3_divmorph.zoo import (  # noqa: F401 -- the rl-zoo entries are read in sb3_divmorph.zoo; re-exported here
    BALANCED_SAMPLER,
    PPO_HYPERPARAMETERS,
    REPO_ROOT,
    ZOO_KEYS,
    ConfigError,
    ZooEntry,
    check_ppo_keys,
    load_zoo_entry,
    resolve_path,
    zoo_configs_dir,
)
from divmorph.pipeline.retired import REMOVED_KEYS, RETIRED_RULES
from unimal_envs import env_id
from unimal_envs.contract import HEIGHT_REFERENCES, NOVEL_TASKS, TASK_NAMES, TRAIN_TASKS

DEFAULT_PROFILES = Path("zoo_configs") / "divmorph.yml"


def _from_dict(cls: type, values: dict[str, Any] | None, where: str):
    values = dict(values or {})
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(values) - set(names))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; valid keys: {names}")
    missing = [
        f.name
        for f in dataclasses.fields(cls)
        if f.name not in values and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        raise ConfigError(f"{where}: missing key(s) {missing}")
    return cls(**values)


def _check_tasks(tasks: list[str], allowed: tuple[str, ...], where: str) -> None:
    bad = [t for t in tasks if t not in allowed]
    if bad or not tasks:
        raise ConfigError(f"{where}: unknown or unsuitable task(s) {bad or tasks}; choose from {list(allowed)}")


#: Simulation backends a training stage may use (``env_backend``).
ENV_BACKENDS = ("single", "batched")
#: Policies a teacher may be (``teachers.policy``, ``hyperdistill.teacher_policy``).
TEACHER_POLICIES = ("MetaMorphPolicy", "ModuMorphPolicy", "DivMorphPolicy")


@dataclass
class TeachersConfig:
    """One teacher per training task (MetaMorph unless ``policy`` says otherwise), trained with PPO."""

    #: the training tasks, one teacher each (of ``TRAIN_TASKS``)
    tasks: list[str]
    #: PPO env steps per teacher
    n_timesteps: int
    #: the teachers' policy (default: the rl-zoo entry's, MetaMorphPolicy)
    policy: str | None = None
    #: the rl-zoo hyperparameter file the teachers' PPO settings come from (entry ``Unimal-<task>-v0``)
    hyperparams: str = "zoo_configs/ppo.yml"
    #: PPO settings on top of the zoo entry's, e.g. ``{n_envs: 2, learning_rate: 3e-4}``
    overrides: dict[str, Any] = field(default_factory=dict)
    #: updates of the zoo entry's ``policy_kwargs`` (the network's size, its input encoders)
    policy_kwargs: dict[str, Any] = field(default_factory=dict)
    #: env steps between checkpoints (an interrupted run resumes from the last)
    checkpoint_every: int = 50_000
    #: ``""``: the zoo entry ``Unimal-<task>-v0``; ``"metamorph"``: ``Unimal-<task>-v0-metamorph``,
    #: MetaMorph's training recipe (cosine lr with warm-up, Adam eps 1e-5, KL stop at 0.2,
    #: normalisation clipped at 10, balanced robot sampler; see ``sb3_divmorph.algos.recipe``)
    recipe: str = ""
    #: ``single``: ``n_envs`` C-MuJoCo envs; ``batched``: MuJoCo Warp (:mod:`unimal_envs.batched`),
    #: ``worlds_per_robot`` worlds of every robot on the profile's device (``n_envs`` is then unused)
    env_backend: str = "single"
    worlds_per_robot: int = 16
    #: ``batched`` only: distinct terrains drawn per terrain task (VT, Obstacle, Escape); every
    #: episode picks one (the single env draws new terrain every episode)
    terrain_variants: int = 64


@dataclass
class StudentConfig:
    """The DivMorph student's ``policy_kwargs``, and updates of them for other students."""

    #: the DivMorph student's ``policy_kwargs`` (size, tailors, TopK...; see ``DivMorphPolicy``)
    policy_kwargs: dict[str, Any] = field(default_factory=dict)
    #: per-student updates of the ``policy_kwargs`` a student derives from the profile, by student
    #: name, e.g. ``{deploy-g1k1: {d_model: 64, ff_dim: 256}}`` (a wider deployment student, whose
    #: compact actor's size reduction grows with width); applied last
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)


@dataclass
class DistillConfig:
    """DAgger distillation of the teachers into the student."""

    #: DAgger env steps (the student's own rollouts, labelled by the teachers)
    n_timesteps: int
    #: parallel envs of the rollouts (``Unimal-MultiTask-v0``: each episode a training task and robot)
    n_envs: int = 4
    #: env steps per env between distillation updates
    n_steps: int = 256
    #: probability of executing the teacher's action instead of the student's, annealed linearly
    #: from ``beta_start`` to ``beta_end`` over the run
    beta_start: float = 0.5
    beta_end: float = 0.0
    #: passes over the aggregated dataset after each rollout
    epochs: int = 2
    #: minibatch size of the distillation updates
    batch_size: int = 256
    #: the student's Adam learning rate
    learning_rate: float = 1e-3
    #: capacity of the aggregated dataset (states; the oldest leave first)
    buffer_size: int = 50_000
    #: ``true``: the distillation steps run alongside PPO's own update (needs ``beta_start = beta_end = 0``)
    ppo_loss: bool = False
    #: env steps between checkpoints (dataset, optimiser and shuffling state included)
    checkpoint_every: int = 50_000
    #: weight of the optional gate load-balancing term (0 = off; see ``DAggerCallback``)
    load_balance: float = 0.0
    #: DAgger's recipe options (:class:`~sb3_divmorph.algos.distillation.DAggerCallback`):
    #: teachers' action means clipped to +-``target_bound`` as targets (null: unbounded), the
    #: optimiser (``adam`` / ``adamw``) and its weight decay, and the weight of the student critic's
    #: regression onto each state's teacher critic (0: critic not distilled)
    target_bound: float | None = None
    optimizer: str = "adam"
    weight_decay: float = 0.0
    value_weight: float = 0.0
    #: ``single``: ``n_envs`` C-MuJoCo envs; ``batched``: MuJoCo Warp (:mod:`unimal_envs.batched`),
    #: ``worlds_per_robot`` worlds of every robot on the profile's device (``n_envs`` is then unused)
    env_backend: str = "single"
    worlds_per_robot: int = 16
    #: ``batched`` only: distinct terrains drawn per terrain task (VT, Obstacle, Escape); every
    #: episode picks one (the single env draws new terrain every episode)
    terrain_variants: int = 64


@dataclass
class TransferConfig:
    """Transfer of the student to novel tasks (and the MetaMorph-from-scratch comparison)."""

    #: the novel tasks to transfer to (of ``NOVEL_TASKS``)
    tasks: list[str]
    #: PPO env steps of every transfer run (arm x task x seed)
    n_timesteps: int
    #: learning-rate ratio of the shared knowledge (learngenes, embedding, encoders) to the selected
    #: tailors in the DivMorph-way arms
    learngene_lr_scale: float = 0.1
    #: ``{task: instruction}``: a novel task described in your own words (re-embedded by the
    #: text encoder; the gates read it); default: the task's built-in instruction
    instructions: dict[str, str] = field(default_factory=dict)
    #: PPO settings on top of the novel task's zoo entry, for every arm
    overrides: dict[str, Any] = field(default_factory=dict)
    #: PPO settings applied on top of ``overrides`` for the arms that start from trained weights
    #: (every arm but ``scratch`` and ``modumorph``), e.g. ``{learning_rate: lin_3e-4}``: a rate
    #: chosen for training from scratch takes large first steps away from a trained policy
    finetune_overrides: dict[str, Any] = field(default_factory=dict)
    #: env steps at the start of those arms' runs during which only the critic trains (the actor
    #: is frozen): they come without a critic for the novel task (see
    #: :class:`~sb3_divmorph.algos.finetune.CriticWarmup`); 0 = none
    critic_warmup: int = 0
    #: learning-rate multiple of the critic's parameters in those arms' runs: their actor fine-tunes
    #: at ``finetune_overrides``' rate, while their critic (random, or another task's) has a new
    #: task's values to learn, as scratch's does at the teachers' rate; e.g. 10 with lin_1e-4 gives
    #: the critic lin_1e-3 (``results/critic-start/critic_start.py`` measures it on a training task)
    critic_lr_scale: float = 1.0
    #: env steps between checkpoints of each run
    checkpoint_every: int = 50_000
    #: the arms to race (see :data:`divmorph.pipeline.arms.ARMS`); default: ``divmorph`` and ``scratch``
    arms: list[str] | None = None
    #: one run per arm and seed (the seed offsets the PPO seed; the robots are the same)
    seeds: list[int] = field(default_factory=lambda: [0])
    #: how the ``closest`` arm picks its teacher: ``embedding`` (cosine of the instruction
    #: embeddings) or ``return`` (best zero-shot return on the novel task)
    closest_by: str = "embedding"
    #: ``single``: ``n_envs`` C-MuJoCo envs; ``batched``: MuJoCo Warp (:mod:`unimal_envs.batched`),
    #: ``worlds_per_robot`` worlds of every robot on the profile's device (``n_envs`` is then unused)
    env_backend: str = "single"
    worlds_per_robot: int = 16
    #: ``batched`` only: distinct terrains drawn per terrain task (VT, Obstacle, Escape); every
    #: episode picks one (the single env draws new terrain every episode)
    terrain_variants: int = 64
    #: deterministic evaluation on the training and the novel robots every this many env steps
    #: (and at step 0 and at the end); 0 = no evaluation curves (no transfer metrics)
    eval_every: int = 0
    #: episodes per robot of each of those evaluations (deterministic policy; the episodes differ
    #: by their reset noise and terrain)
    eval_episodes: int = 3
    #: where those evaluations run: ``single`` (each robot's episodes in turn, C MuJoCo) or
    #: ``batched`` (every episode of every robot at once, a MuJoCo Warp world each, on the profile's
    #: device: many draws per point at the cost of one episode; :mod:`~divmorph.pipeline.batched_evaluation`).
    #: Curves of one backend compare with each other, not episode for episode with the other's
    eval_backend: str = "single"
    #: robots per split of those evaluations: the first N training and the first N novel robots
    #: (a fixed subset, chosen by position, never by result); ``null``: every robot of both splits
    eval_robots: int | None = None
    #: Adam's ``eps`` of every arm's optimiser (one rule for the whole race). DivMorph's per-unit
    #: learning rates need it far below a distilled student's gradients
    #: (:data:`~sb3_divmorph.algos.finetune.TRANSFER_ADAM_EPS`), so every arm gets that value
    adam_eps: float = 1e-10
    #: learning-rate scale of the parts a DivMorph ablation does not divert (``no-kdiv-*``: every unit
    #: of the undiverted part would otherwise be a learngene, trained ``learngene_lr_scale`` times
    #: slower); 1.0: the full rate, like any fine-tuned network
    undiverted_lr_scale: float = 1.0
    #: learning-rate scale of the Cayley generators of the DivMorph-way arms' square factors, relative
    #: to the rate of the units they rotate (1.0: the same rate; 0: rotations frozen). Adam moves
    #: every generator entry by about the rate at once and each turns two whole singular
    #: directions, so at 1.0 the rotations can dominate an update where the policy is far from its
    #: training (measured: ``docs/claims/transfer.md``). It also applies to ``divmorph-finetuned``
    #: (every Cayley generator at this multiple of its rate) and to the free square factors of the
    #: ``no-orthogonality`` ablation (0: every square factor fixed, orthogonal or not)
    rotation_lr_scale: float = 1.0
    #: where the task gates of the arms that start from a DivMorph student come from (fixed in the
    #: DivMorph-way arms, the start of ``divmorph-finetuned``'s): ``instruction`` (the novel task's own
    #: instruction through the gate network, the paper's rule) or ``closest`` (the instruction of the
    #: training task the ``closest`` arm starts from, chosen by ``closest_by`` as for MetaMorph->).
    #: A gate network trained on five instructions does not place a sixth: on PointNav the cpu100
    #: student's own gates return 56 zero-shot, Patrol's 113 (``results/novel-task-gates``)
    task_gates: str = "instruction"
    #: std of the Gaussian the arms that start from trained weights sample from while they fine-tune
    #: (``null``: the source's, MetaMorph's fixed 0.9). Their deterministic (mean) action is what the
    #: race evaluates; under std 0.9 PPO improves the noisy policy, which need not improve its mean
    #: (``results/finetune-known-task``, section 5). The deterministic actions at step 0 do not change
    action_std: float | None = None
    #: ``null`` (default): every arm at its nominal rate. A KL, e.g. 0.01: every arm's learning rate
    #: is multiplied after each PPO update so that updates move the policy by about that KL
    #: (:class:`~sb3_divmorph.algos.adaptive_rate.AdaptiveLearningRate`, rsl_rl's ``desired_kl``
    #: rule), so arms of different parameterisations are compared at equal policy change per update
    desired_kl: float | None = None
    #: what the DivMorph-way arms train under their fixed gates
    #: (:data:`~sb3_divmorph.algos.finetune.RECIPES`): ``fixed-gates`` (the paper's: selected tailors,
    #: learngenes ``learngene_lr_scale`` times slower), ``singular-values`` (FINE's: only the
    #: singular values of the active units), ``kind`` (KIND's for a large shift: the selected task
    #: tailors re-initialised, then as ``fixed-gates``) or ``adapter`` (LoRA's: a zero-initialised
    #: adapter of width ``adapter_rank`` on every factorized actor layer, the only part that trains)
    recipe: str = "fixed-gates"
    #: width of each layer's low-rank adapter under ``recipe: adapter`` (ignored by the other recipes)
    adapter_rank: int = 4

    def arm_list(self) -> list[str]:
        """The arms to run: ``arms``, or ``divmorph`` and ``scratch``."""
        return list(self.arms) if self.arms is not None else ["divmorph", "scratch"]


@dataclass
class ExportConfig:
    """Pruned compact actors for a few robots and tasks."""

    #: the tasks whose compact actors are exported
    tasks: list[str]
    #: robots exported per split (the first of the training and of the novel robots)
    robots_per_split: int = 1
    #: forward passes timed for the batch-1 latency
    latency_repeats: int = 200


@dataclass
class HyperDistillConfig:
    """HyperDistill: a hypernetwork student distilled from per-task teachers into per-robot MLPs."""

    #: teachers to distil: the run's own (``teachers/``) when their policy is this one, otherwise
    #: teachers of this policy are trained with the ``teachers`` settings into ``hyperdistill/teachers/``
    teacher_policy: str = "ModuMorphPolicy"
    #: the hypernetwork student's ``policy_kwargs`` (see ``HyperDistillPolicy``)
    policy_kwargs: dict[str, Any] = field(default_factory=dict)
    #: teacher-rollout states for the offline phase (authors: ~16k per robot); 0 = no offline phase
    rollout_samples: int = 16384
    #: the offline fit's loss: ``nll`` (the authors') or ``kl``
    loss: str = "nll"
    #: passes of the offline fit over the teacher-rollout states
    epochs: int = 50
    #: minibatch size of the fit and of DAgger (authors: 5120)
    batch_size: int = 5120
    #: Adam learning rate of the fit and of DAgger
    learning_rate: float = 3e-4
    #: DAgger steps after the offline phase (0 = none)
    dagger_timesteps: int = 0
    #: passes over the aggregated dataset after each DAgger rollout
    dagger_epochs: int = 2
    #: parallel envs of the rollouts
    n_envs: int = 4
    #: env steps per env between DAgger updates
    n_steps: int = 256
    #: capacity of DAgger's aggregated dataset (states)
    buffer_size: int = 50_000


@dataclass
class GRLConfig:
    """GRL (Feng et al., 2023) adapted to the Transformer: a population of MetaMorph agents evolved on
    the training tasks; the inheritable fragment (learngene) is a set of whole layers
    (see :mod:`divmorph.pipeline.grl`)."""

    #: agents per generation
    population: int = 8
    #: generations of the evolution (each trains and selects ``population`` agents)
    generations: int = 3
    #: PPO steps each agent trains (GRL: 50 x 4096)
    steps_per_agent: int = 50_000
    #: whole layers in a learngene (GRL: a pair of its 6 layers)
    learngene_layers: int = 2
    #: tournament size of parent selection (GRL: 3)
    tournament: int = 3
    #: probability that a child's learngene swaps one of its layers for another
    mutation: float = 0.2
    #: PPO settings of the agents (updates the training task's zoo entry, like ``teachers.overrides``)
    overrides: dict[str, Any] = field(default_factory=dict)


@dataclass
class EvaluateConfig:
    """Per-morphology evaluation."""

    #: deterministic episodes per robot (they differ by reset noise and terrain)
    episodes: int = 3


@dataclass
class Profile:
    """A whole pipeline configuration (one entry of ``zoo_configs/divmorph.yml``)."""

    #: the profile's name (its key in the profiles file)
    name: str
    teachers: TeachersConfig
    student: StudentConfig
    distill: DistillConfig
    transfer: TransferConfig
    export: ExportConfig
    evaluate: EvaluateConfig
    #: the run's seed (every stage derives its own from it)
    seed: int = 0
    #: ``auto`` (CUDA when there is one), ``cpu`` or ``cuda``; what was used is recorded in ``run.json``
    device: str = "auto"
    #: torch threads of the stage commands
    torch_threads: int = 2
    #: the training robots: a shipped set name (``train``/``novel``), a directory of MJCF files
    #: (``DIR/xml/*.xml``, e.g. the official unimals_100 set), relative paths resolved like files
    train_set: str = "train"
    #: the novel robots, used only for evaluation; robots of the training list are never among them
    #: (so one directory can serve both: the novel robots are then the ones after the training ones).
    #: With the official training robots, the official held-out robots (``unimals100-test``): the
    #: split the field reports zero-shot on
    novel_set: str = "novel"
    #: the first N robots of ``train_set`` (``null``: all)
    train_robots: int | None = None
    #: the first N robots of ``novel_set`` (``null``: all)
    novel_robots: int | None = None
    #: an out-of-distribution robot set, evaluated zero-shot and reported apart from the novel robots
    #: (split ``ood``), e.g. the shipped generated ``novel`` set beside official training robots
    #: (taller, lighter, random designs: ``results/morphology_sets.md``); ``None``: none
    ood_set: str | None = None
    #: the first N robots of ``ood_set`` (``null``: all)
    ood_robots: int | None = None
    #: episode length limit of every env of the run
    max_episode_steps: int = 1000
    #: what body heights in the robots' proprioception are measured from, in every env of the run
    #: (``gym.make(..., height_reference=...)``): ``world`` (MetaMorph's convention, default) or
    #: ``ground`` (above the ground under the torso: the same statistics on every task, the better
    #: input for a multi-task student, ``results/normalizer_drift.md``); single env backend only
    height_reference: str = "world"
    #: ``null`` (raw metres, the reference's) or a distance in metres beyond which the ``goal`` and
    #: ``object`` position inputs are observed at that distance in their own direction
    #: (``gym.make(..., goal_range=...)``), in every env of the run: PointNav's goals lie up to ~60 m
    #: away, Patrol's within ~10 m, so 10 keeps a novel goal in the range the teachers saw
    goal_range: float | None = None
    #: the HyperDistill baseline; the pipeline runs it only when the profile has this section
    hyperdistill: HyperDistillConfig | None = None
    #: GRL's evolution settings (the ``grl`` transfer arm); defaults apply when absent
    grl: GRLConfig = field(default_factory=GRLConfig)

    @classmethod
    def from_dict(cls, name: str, values: dict[str, Any]) -> Profile:
        sections = {
            "teachers": TeachersConfig,
            "student": StudentConfig,
            "distill": DistillConfig,
            "transfer": TransferConfig,
            "export": ExportConfig,
            "evaluate": EvaluateConfig,
        }
        values = dict(values)
        check_removed_keys(values, f"profile {name!r}")
        parsed = {
            key: _from_dict(section, values.pop(key, None), f"profile {name!r}, section {key!r}") for key, section in sections.items()
        }
        if values.get("grl") is not None:
            parsed["grl"] = _from_dict(GRLConfig, values.pop("grl"), f"profile {name!r}, section 'grl'")
        else:
            values.pop("grl", None)
        if values.get("hyperdistill") is not None:
            parsed["hyperdistill"] = _from_dict(HyperDistillConfig, values.pop("hyperdistill"), f"profile {name!r}, section 'hyperdistill'")
        profile = _from_dict(cls, {**values, **parsed, "name": name}, f"profile {name!r}")
        _check_tasks(profile.teachers.tasks, TRAIN_TASKS, f"profile {name!r}, teachers.tasks")
        _check_tasks(profile.transfer.tasks, NOVEL_TASKS, f"profile {name!r}, transfer.tasks")
        _check_tasks(profile.export.tasks, TASK_NAMES, f"profile {name!r}, export.tasks")
        for where, policy in (
            ("teachers.policy", profile.teachers.policy),
            ("hyperdistill.teacher_policy", profile.hyperdistill.teacher_policy if profile.hyperdistill else None),
        ):
            if policy is not None and policy not in TEACHER_POLICIES:
                raise ConfigError(f"profile {name!r}: unknown teacher policy {policy!r} in {where}; choose from {list(TEACHER_POLICIES)}")
        d = profile.distill
        if d.optimizer not in ("adam", "adamw"):
            raise ConfigError(f"profile {name!r}: distill.optimizer must be 'adam' or 'adamw', got {d.optimizer!r}")
        if (d.target_bound is not None and d.target_bound <= 0) or d.weight_decay < 0 or d.value_weight < 0:
            raise ConfigError(
                f"profile {name!r}: distill.target_bound must be positive or null, distill.weight_decay and "
                f"distill.value_weight >= 0; got {d.target_bound!r}, {d.weight_decay!r}, {d.value_weight!r}"
            )
        if profile.hyperdistill is not None and profile.hyperdistill.loss not in ("nll", "kl"):
            raise ConfigError(f"profile {name!r}: hyperdistill.loss must be 'nll' or 'kl', got {profile.hyperdistill.loss!r}")
        for key in ("task_input", "observation_statistics", "normalized_keys"):
            if profile.hyperdistill is not None and key in profile.hyperdistill.policy_kwargs:
                raise ConfigError(
                    f"profile {name!r}: hyperdistill.policy_kwargs.{key} is set by the pipeline (the task's index in, "
                    "each state normalised with its task's teacher's statistics)"
                )
        if profile.height_reference not in HEIGHT_REFERENCES:
            raise ConfigError(
                f"profile {name!r}: height_reference must be one of {list(HEIGHT_REFERENCES)}, got {profile.height_reference!r}"
            )
        if profile.transfer.desired_kl is not None and not profile.transfer.desired_kl > 0:
            raise ConfigError(f"profile {name!r}: transfer.desired_kl must be null or a KL > 0, got {profile.transfer.desired_kl!r}")
        if profile.goal_range is not None and not profile.goal_range > 0:
            raise ConfigError(f"profile {name!r}: goal_range must be null or a distance > 0 (m), got {profile.goal_range!r}")
        for section in ("teachers", "distill", "transfer"):
            cfg = getattr(profile, section)
            if cfg.env_backend not in ENV_BACKENDS or cfg.worlds_per_robot < 1 or cfg.terrain_variants < 1:
                raise ConfigError(
                    f"profile {name!r}: {section}.env_backend must be one of {list(ENV_BACKENDS)}, "
                    f"{section}.worlds_per_robot >= 1 and {section}.terrain_variants >= 1, got "
                    f"{cfg.env_backend!r}, {cfg.worlds_per_robot}, {cfg.terrain_variants}"
                )
        if profile.transfer.action_std is not None and not (
            isinstance(profile.transfer.action_std, (int, float))
            and not isinstance(profile.transfer.action_std, bool)
            and profile.transfer.action_std > 0
        ):
            raise ConfigError(
                f"profile {name!r}: transfer.action_std must be a positive number or null, got {profile.transfer.action_std!r}"
            )
        if profile.transfer.eval_backend not in ENV_BACKENDS:
            raise ConfigError(
                f"profile {name!r}: transfer.eval_backend must be one of {list(ENV_BACKENDS)}, got {profile.transfer.eval_backend!r}"
            )
        for section in ("teachers", "distill", "transfer"):
            for key in ("n_timesteps", "checkpoint_every"):
                value = getattr(getattr(profile, section), key)
                if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 1 or not float(value).is_integer():
                    raise ConfigError(f"profile {name!r}: {section}.{key} must be a positive whole number of env steps, got {value!r}")
                setattr(getattr(profile, section), key, int(value))  # 2e7 in YAML arrives as a float
        for section in ("teachers", "transfer", "grl"):
            check_ppo_keys(getattr(profile, section).overrides, f"profile {name!r}, {section}.overrides")
        check_ppo_keys(profile.transfer.finetune_overrides, f"profile {name!r}, transfer.finetune_overrides")
        check_transfer(profile.transfer, f"profile {name!r}, transfer")
        if profile.grl.population < 1 or profile.grl.generations < 1 or profile.grl.learngene_layers < 1 or profile.grl.tournament < 1:
            raise ConfigError(f"profile {name!r}: grl.population, generations, learngene_layers and tournament must be >= 1")
        stray = sorted(set(profile.transfer.instructions) - set(profile.transfer.tasks))
        if stray:
            raise ConfigError(
                f"profile {name!r}: transfer.instructions for {stray}, which are not in transfer.tasks {profile.transfer.tasks}"
            )
        if not 0 <= profile.distill.beta_start <= 1 or not 0 <= profile.distill.beta_end <= 1:
            raise ConfigError(f"profile {name!r}: distill.beta_start/beta_end must be in [0, 1]")
        if profile.distill.ppo_loss and max(profile.distill.beta_start, profile.distill.beta_end) > 0:
            raise ConfigError(f"profile {name!r}: distill.ppo_loss needs beta_start = beta_end = 0 (mixing is off-policy)")
        return profile


def check_removed_keys(values: dict[str, Any], where: str) -> None:
    """A profile that sets a key removed in 0.2, or a kept key to its retired value, is an error naming
    it and what replaces it (a run recorded before 0.2 is migrated once: ``divmorph migrate``)."""
    for key, instead in REMOVED_KEYS.items():
        section_name, name = key.split(".")
        if isinstance(values.get(section_name), dict) and name in values[section_name]:
            raise ConfigError(f"{where}: {key} was removed in divmorph 0.2: {instead}")
    for rule in RETIRED_RULES:
        section = values.get(rule.section)
        if rule.kept and isinstance(section, dict) and rule.name in section and section[rule.name] == rule.value:
            raise ConfigError(f"{where}: {rule.key}: {rule.value!r} selected a rule retired in divmorph 0.2; today's is {rule.today!r}")


def check_arms(arms: list[str], where: str) -> None:
    """Unknown or repeated arms are an error that lists the valid ones."""
    from divmorph.pipeline.arms import ARMS

    unknown = [a for a in arms if a not in ARMS]
    if unknown:
        raise ConfigError(f"{where}: unknown arm(s) {unknown}; valid arms: {list(ARMS)}")
    repeated = sorted({a for a in arms if arms.count(a) > 1})
    if repeated or not arms:
        raise ConfigError(f"{where}: arm(s) {repeated or arms} given twice or none given")


def check_seeds(seeds: list[int], where: str) -> None:
    """Seeds must be distinct non-negative integers (a seed given twice would race itself)."""
    if not seeds or any(not isinstance(s, int) or isinstance(s, bool) or s < 0 for s in seeds):
        raise ConfigError(f"{where}: seeds must be a non-empty list of integers >= 0, got {seeds}")
    repeated = sorted({s for s in seeds if seeds.count(s) > 1})
    if repeated:
        raise ConfigError(f"{where}: seed(s) {repeated} given twice; each seed is one run folder")


def check_transfer(cfg: TransferConfig, where: str) -> None:
    check_arms(cfg.arm_list(), f"{where}.arms")
    check_seeds(list(cfg.seeds), f"{where}.seeds")
    if cfg.closest_by not in ("embedding", "return"):
        raise ConfigError(f"{where}.closest_by must be 'embedding' or 'return', got {cfg.closest_by!r}")
    if cfg.eval_every < 0 or cfg.eval_episodes < 1:
        raise ConfigError(f"{where}: eval_every must be >= 0 and eval_episodes >= 1")
    if cfg.eval_robots is not None and cfg.eval_robots < 1:
        raise ConfigError(f"{where}.eval_robots must be >= 1 or null (every robot), got {cfg.eval_robots!r}")
    if cfg.critic_warmup < 0:
        raise ConfigError(f"{where}.critic_warmup must be >= 0 env steps, got {cfg.critic_warmup}")
    if not cfg.critic_lr_scale > 0:
        raise ConfigError(f"{where}.critic_lr_scale must be > 0, got {cfg.critic_lr_scale}")
    try:
        cfg.adam_eps = float(cfg.adam_eps)  # YAML reads 1e-10 (no dot) as a string
    except (TypeError, ValueError):
        raise ConfigError(f"{where}.adam_eps must be a number > 0, got {cfg.adam_eps!r}") from None
    if not cfg.adam_eps > 0:
        raise ConfigError(f"{where}.adam_eps must be a number > 0, got {cfg.adam_eps!r}")
    if not 0 <= cfg.rotation_lr_scale <= 1:
        raise ConfigError(f"{where}.rotation_lr_scale must be in [0, 1], got {cfg.rotation_lr_scale}")
    if cfg.recipe not in RECIPES:
        raise ConfigError(f"{where}.recipe must be one of {list(RECIPES)}, got {cfg.recipe!r}")
    if isinstance(cfg.adapter_rank, bool) or not isinstance(cfg.adapter_rank, int) or cfg.adapter_rank < 1:
        raise ConfigError(f"{where}.adapter_rank must be an integer >= 1, got {cfg.adapter_rank!r}")
    if not isinstance(cfg.undiverted_lr_scale, (int, float)) or not 0 <= cfg.undiverted_lr_scale <= 1:
        raise ConfigError(f"{where}.undiverted_lr_scale must be in [0, 1], got {cfg.undiverted_lr_scale!r}")


def load_profiles(path: str | Path = DEFAULT_PROFILES) -> dict[str, dict[str, Any]]:
    """The raw profile entries of a profiles file."""
    resolved = resolve_path(path)
    if not resolved.is_file():
        raise ConfigError(f"profiles file {path} not found (looked in {Path.cwd()}, in the shipped {zoo_configs_dir()} and in {REPO_ROOT})")
    with open(resolved) as f:
        data = yaml.safe_load(f) or {}
    if not isinstance(data, dict):
        raise ConfigError(f"{resolved}: expected a mapping of profile names")
    return data


def apply_overrides(values: dict[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """A copy of a raw profile with ``{"section.key" or "key": value}`` overrides applied.

    Keys are validated afterwards exactly like the YAML's (an unknown key names the valid ones);
    a dotted key whose section is not a mapping is an error here.
    """
    values = copy.deepcopy(values)
    for dotted, value in overrides.items():
        *sections, key = dotted.split(".")
        target = values
        for section in sections:
            node = target.setdefault(section, {})
            if not isinstance(node, dict):
                raise ConfigError(f"override {dotted}={value!r}: {section!r} is not a section of the profile")
            target = node
        target[key] = value
    return values


def parse_override(text: str) -> tuple[str, Any]:
    """``"teachers.n_timesteps=5000"`` -> ``("teachers.n_timesteps", 5000)`` (the value read as YAML)."""
    key, sep, raw = text.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"--set takes KEY=VALUE (e.g. teachers.n_timesteps=5000), got {text!r}")
    return key.strip(), yaml.safe_load(raw)


def load_profile(name: str, path: str | Path = DEFAULT_PROFILES, overrides: Mapping[str, Any] | None = None) -> Profile:
    """Load and validate one profile; unknown names list the available ones.

    :param overrides: ``{"section.key": value}`` applied before validation (``divmorph ... --set``).
    """
    profiles = load_profiles(path)
    if name not in profiles:
        raise ConfigError(f"unknown profile {name!r}; profiles in {resolve_path(path)}: {sorted(profiles)}")
    try:
        return Profile.from_dict(name, apply_overrides(profiles[name], overrides or {}))
    except ConfigError as error:
        # name where the bad value came from: the command line's --set, or the file (the same
        # profile name may live in several)
        given = [f"{key}={value!r}" for key, value in (overrides or {}).items() if key in str(error) or key.split(".")[-1] in str(error)]
        source = f"--set {', '.join(given)} (on profile {name!r} of {resolve_path(path)})" if given else str(resolve_path(path))
        raise ConfigError(f"{source}: {error}") from None


def grl_policy_kwargs(profile: Profile) -> dict[str, Any]:
    """Every GRL agent's (and the ``grl`` arm's) MetaMorph kwargs: ``teachers.policy_kwargs`` on the
    policy's preset, not the tasks' zoo entries, whose exteroception differs per task: one
    architecture for all tasks, so that any agent's layers fit into any other."""
    return dict(profile.teachers.policy_kwargs)


def zoo_entry_id(profile: Profile, task: str) -> str:
    """The rl-zoo entry of ``task``'s teacher: ``Unimal-<task>-v0``, or its ``-<recipe>`` variant."""
    env_name = env_id(task)
    return f"{env_name}-{profile.teachers.recipe}" if profile.teachers.recipe else env_name


def teacher_policy(profile: Profile, task: str) -> str:
    """The policy of the run's teacher of ``task``: ``teachers.policy``, else the zoo entry's."""
    cfg = profile.teachers
    return cfg.policy or load_zoo_entry(cfg.hyperparams, zoo_entry_id(profile, task), cfg.overrides).policy
