"""The keys of a pipeline profile (``zoo_configs/divmorph.yml``): one dataclass per section, each field
with its default and what it means. Importing this module imports nothing heavy, so the command line
can refuse an unknown ``--set`` key at once; :mod:`divmorph.pipeline.config` loads and validates a
whole profile (:func:`~divmorph.pipeline.config.profile_from_dict`).
"""

from __future__ import annotations

import dataclasses
import difflib
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NoReturn

#: Simulation backends a training stage may use (``env_backend``).
ENV_BACKENDS = ("single", "batched")
#: Policies a teacher may be (``teachers.policy``, ``hyperdistill.teacher_policy``).
TEACHER_POLICIES = ("MetaMorphPolicy", "ModuMorphPolicy", "DivMorphPolicy")


def _refuse(message: str) -> NoReturn:
    """Raise the pipeline's ``ConfigError`` (imported here, on a mistake: its module loads torch)."""
    from sb3_divmorph.zoo import ConfigError

    raise ConfigError(message)


def _check_tasks(tasks: list[str], allowed: tuple[str, ...], where: str) -> None:
    bad = [t for t in tasks if t not in allowed]
    if bad or not tasks:
        _refuse(f"{where}: unknown or unsuitable task(s) {bad or tasks}; choose from {list(allowed)}")


def _check_teacher_policy(policy: str | None, key: str, where: str) -> None:
    if policy is not None and policy not in TEACHER_POLICIES:
        _refuse(f"{where}: unknown teacher policy {policy!r} in {key}; choose from {list(TEACHER_POLICIES)}")


def _check_ppo_keys(overrides: dict[str, Any], where: str) -> None:
    from sb3_divmorph.zoo import check_ppo_keys  # the rl-zoo's keys: imported when a profile is checked

    check_ppo_keys(overrides, where)


def check_arms(arms: list[str], where: str) -> None:
    """Unknown or repeated arms are an error that lists the valid ones."""
    from divmorph.pipeline.arms import ARMS

    unknown = [a for a in arms if a not in ARMS]
    if unknown:
        _refuse(f"{where}: unknown arm(s) {unknown}; valid arms: {list(ARMS)}")
    repeated = sorted({a for a in arms if arms.count(a) > 1})
    if repeated or not arms:
        _refuse(f"{where}: arm(s) {repeated or arms} given twice or none given")


def check_seeds(seeds: list[int], where: str) -> None:
    """Seeds must be distinct non-negative integers (a seed given twice would race itself)."""
    if not seeds or any(not isinstance(s, int) or isinstance(s, bool) or s < 0 for s in seeds):
        _refuse(f"{where}: seeds must be a non-empty list of integers >= 0, got {seeds}")
    repeated = sorted({s for s in seeds if seeds.count(s) > 1})
    if repeated:
        _refuse(f"{where}: seed(s) {repeated} given twice; each seed is one run folder")


@dataclass(kw_only=True)
class SimulationSettings:
    """Where a training stage's envs run: the keys ``teachers``, ``distill`` and ``transfer`` share.

    Each such section also has ``n_timesteps`` and ``checkpoint_every`` (in env steps, described by
    the section), which :meth:`check_steps` checks and makes integers.
    """

    #: ``single``: ``n_envs`` C-MuJoCo envs; ``batched``: MuJoCo Warp (:mod:`unimal_envs.batched`),
    #: ``worlds_per_robot`` worlds of every robot on the profile's device (``n_envs`` is then unused)
    env_backend: str = "single"
    worlds_per_robot: int = 16
    #: ``batched`` only: distinct terrains drawn per terrain task (VT, Obstacle, Escape); every
    #: episode picks one (the single env draws new terrain every episode)
    terrain_variants: int = 64

    def check_simulation(self, where: str, key: str) -> None:
        """A known backend and counts >= 1 (``where``: the profile, ``key``: the section's key)."""
        if self.env_backend not in ENV_BACKENDS or self.worlds_per_robot < 1 or self.terrain_variants < 1:
            _refuse(
                f"{where}: {key}.env_backend must be one of {list(ENV_BACKENDS)}, "
                f"{key}.worlds_per_robot >= 1 and {key}.terrain_variants >= 1, got "
                f"{self.env_backend!r}, {self.worlds_per_robot}, {self.terrain_variants}"
            )

    def check_steps(self, where: str, key: str) -> None:
        """``n_timesteps`` and ``checkpoint_every`` are positive whole numbers of env steps, made ``int``."""
        for name in ("n_timesteps", "checkpoint_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 1 or not float(value).is_integer():
                _refuse(f"{where}: {key}.{name} must be a positive whole number of env steps, got {value!r}")
            setattr(self, name, int(value))  # 2e7 in YAML arrives as a float


@dataclass
class TeachersConfig(SimulationSettings):
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

    def check(self, where: str) -> None:
        """Check the section's values (``where``: the profile); :raises ConfigError: a bad one."""
        from unimal_envs.contract import TRAIN_TASKS

        _check_tasks(self.tasks, TRAIN_TASKS, f"{where}, teachers.tasks")
        _check_teacher_policy(self.policy, "teachers.policy", where)
        self.check_simulation(where, "teachers")
        self.check_steps(where, "teachers")
        _check_ppo_keys(self.overrides, f"{where}, teachers.overrides")


@dataclass
class StudentConfig:
    """The DivMorph student's ``policy_kwargs``, and updates of them for other students."""

    #: the DivMorph student's ``policy_kwargs`` (size, tailors, TopK...; see ``DivMorphPolicy``)
    policy_kwargs: dict[str, Any] = field(default_factory=dict)
    #: per-student updates of the ``policy_kwargs`` a student derives from the profile, by student
    #: name, e.g. ``{deploy-g1k1: {d_model: 64, ff_dim: 256}}`` (a wider deployment student, whose
    #: compact actor's size reduction grows with width); applied last
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)

    def check(self, where: str) -> None:
        """Nothing to check beyond the keys: the policy checks its ``policy_kwargs`` (``where``: the profile)."""


@dataclass
class DistillConfig(SimulationSettings):
    """DAgger distillation of the teachers into the student."""

    #: DAgger env steps (the student's own rollouts, labelled by the teachers)
    n_timesteps: int
    #: parallel envs of the rollouts (``Unimal-MultiTask-v1``: each episode a training task and robot)
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

    def check(self, where: str) -> None:
        """Check the section's values (``where``: the profile); :raises ConfigError: a bad one."""
        if self.optimizer not in ("adam", "adamw"):
            _refuse(f"{where}: distill.optimizer must be 'adam' or 'adamw', got {self.optimizer!r}")
        if (self.target_bound is not None and self.target_bound <= 0) or self.weight_decay < 0 or self.value_weight < 0:
            _refuse(
                f"{where}: distill.target_bound must be positive or null, distill.weight_decay and "
                f"distill.value_weight >= 0; got {self.target_bound!r}, {self.weight_decay!r}, {self.value_weight!r}"
            )
        self.check_simulation(where, "distill")
        self.check_steps(where, "distill")
        if not 0 <= self.beta_start <= 1 or not 0 <= self.beta_end <= 1:
            _refuse(f"{where}: distill.beta_start/beta_end must be in [0, 1]")
        if self.ppo_loss and max(self.beta_start, self.beta_end) > 0:
            _refuse(f"{where}: distill.ppo_loss needs beta_start = beta_end = 0 (mixing is off-policy)")


@dataclass
class TransferConfig(SimulationSettings):
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
    #: the critic lin_1e-3 (choose it on a training task, never on the novel ones)
    critic_lr_scale: float = 1.0
    #: keep the observation statistics a fine-tuned arm inherits exactly as they were (its weights were trained
    #: on inputs normalised by them); ``false`` lets them go on learning the novel task's states, as a model
    #: trained from scratch does (a diagnostic: the inputs then drift under the inherited weights)
    freeze_statistics: bool = True
    #: env steps between checkpoints of each run
    checkpoint_every: int = 50_000
    #: the arms to race (see :data:`divmorph.pipeline.arms.ARMS`); default: ``divmorph`` and ``scratch``
    arms: list[str] | None = None
    #: one run per arm and seed (the seed offsets the PPO seed; the robots are the same)
    seeds: list[int] = field(default_factory=lambda: [0])
    #: how the ``closest`` arm picks its teacher: ``embedding`` (cosine of the instruction
    #: embeddings) or ``return`` (best zero-shot return on the novel task)
    closest_by: str = "embedding"
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
    #: the robot splits those evaluations roll out: ``train`` and ``novel`` (the held-out robots), or one
    #: of them (a study that reads one split spends no episodes on the other)
    eval_splits: list[str] = field(default_factory=lambda: ["train", "novel"])
    #: the robots each run trains on: ``all`` (every training robot of the profile) or ``eval`` (only
    #: the ``eval_robots`` its curves are read on, spread over the set: fewer robots share the budget,
    #: and the curves read the robots the run trained on)
    train_robots: str = "all"
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
    #: training. It also applies to ``divmorph-finetuned``
    #: (every Cayley generator at this multiple of its rate) and to the free square factors of the
    #: ``no-orthogonality`` ablation (0: every square factor fixed, orthogonal or not)
    rotation_lr_scale: float = 1.0
    #: where the task gates of the arms that start from a DivMorph student come from (fixed in the
    #: DivMorph-way arms, the start of ``divmorph-finetuned``'s): ``instruction`` (the novel task's own
    #: instruction through the gate network, the paper's rule) or ``closest`` (the instruction of the
    #: training task the ``closest`` arm starts from, chosen by ``closest_by`` as for MetaMorph->).
    #: A gate network trained on five instructions does not place a sixth well, so the closest
    #: training task's gates can be the better start
    task_gates: str = "instruction"
    #: std of the Gaussian the arms that start from trained weights sample from while they fine-tune
    #: (``null``: the source's, MetaMorph's fixed 0.9). Their deterministic (mean) action is what the
    #: race evaluates; under std 0.9 PPO improves the noisy policy, which need not improve its mean.
    #: The deterministic actions at step 0 do not change
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

    def check(self, where: str) -> None:
        """Check the section's values (``where``: the profile); :raises ConfigError: a bad one."""
        from sb3_divmorph.algos.finetune import RECIPES  # the library's recipes: imported when a profile is checked
        from unimal_envs.contract import NOVEL_TASKS

        _check_tasks(self.tasks, NOVEL_TASKS, f"{where}, transfer.tasks")
        if self.desired_kl is not None and not self.desired_kl > 0:
            _refuse(f"{where}: transfer.desired_kl must be null or a KL > 0, got {self.desired_kl!r}")
        self.check_simulation(where, "transfer")
        if self.action_std is not None and not (
            isinstance(self.action_std, (int, float)) and not isinstance(self.action_std, bool) and self.action_std > 0
        ):
            _refuse(f"{where}: transfer.action_std must be a positive number or null, got {self.action_std!r}")
        if self.eval_backend not in ENV_BACKENDS:
            _refuse(f"{where}: transfer.eval_backend must be one of {list(ENV_BACKENDS)}, got {self.eval_backend!r}")
        self.check_steps(where, "transfer")
        _check_ppo_keys(self.overrides, f"{where}, transfer.overrides")
        _check_ppo_keys(self.finetune_overrides, f"{where}, transfer.finetune_overrides")
        at = f"{where}, transfer"
        check_arms(self.arm_list(), f"{at}.arms")
        check_seeds(list(self.seeds), f"{at}.seeds")
        if self.closest_by not in ("embedding", "return"):
            _refuse(f"{at}.closest_by must be 'embedding' or 'return', got {self.closest_by!r}")
        if self.eval_every < 0 or self.eval_episodes < 1:
            _refuse(f"{at}: eval_every must be >= 0 and eval_episodes >= 1")
        if self.eval_robots is not None and self.eval_robots < 1:
            _refuse(f"{at}.eval_robots must be >= 1 or null (every robot), got {self.eval_robots!r}")
        if not self.eval_splits or not set(self.eval_splits) <= {"train", "novel"} or len(set(self.eval_splits)) < len(self.eval_splits):
            _refuse(f"{at}.eval_splits must list 'train' and/or 'novel' once each, got {self.eval_splits!r}")
        if self.train_robots not in ("all", "eval"):
            _refuse(f"{at}.train_robots must be 'all' or 'eval', got {self.train_robots!r}")
        if self.critic_warmup < 0:
            _refuse(f"{at}.critic_warmup must be >= 0 env steps, got {self.critic_warmup}")
        if not self.critic_lr_scale > 0:
            _refuse(f"{at}.critic_lr_scale must be > 0, got {self.critic_lr_scale}")
        try:
            self.adam_eps = float(self.adam_eps)  # YAML reads 1e-10 (no dot) as a string
        except (TypeError, ValueError):
            _refuse(f"{at}.adam_eps must be a number > 0, got {self.adam_eps!r}")
        if not self.adam_eps > 0:
            _refuse(f"{at}.adam_eps must be a number > 0, got {self.adam_eps!r}")
        if not 0 <= self.rotation_lr_scale <= 1:
            _refuse(f"{at}.rotation_lr_scale must be in [0, 1], got {self.rotation_lr_scale}")
        if self.recipe not in RECIPES:
            _refuse(f"{at}.recipe must be one of {list(RECIPES)}, got {self.recipe!r}")
        if isinstance(self.adapter_rank, bool) or not isinstance(self.adapter_rank, int) or self.adapter_rank < 1:
            _refuse(f"{at}.adapter_rank must be an integer >= 1, got {self.adapter_rank!r}")
        if not isinstance(self.undiverted_lr_scale, (int, float)) or not 0 <= self.undiverted_lr_scale <= 1:
            _refuse(f"{at}.undiverted_lr_scale must be in [0, 1], got {self.undiverted_lr_scale!r}")
        stray = sorted(set(self.instructions) - set(self.tasks))
        if stray:
            _refuse(f"{where}: transfer.instructions for {stray}, which are not in transfer.tasks {self.tasks}")


@dataclass
class ExportConfig:
    """Pruned compact actors for a few robots and tasks."""

    #: the tasks whose compact actors are exported
    tasks: list[str]
    #: robots exported per split (the first of the training and of the novel robots)
    robots_per_split: int = 1
    #: forward passes timed for the batch-1 latency
    latency_repeats: int = 200

    def check(self, where: str) -> None:
        """Check the section's values (``where``: the profile); :raises ConfigError: a bad one."""
        from unimal_envs.contract import TASK_NAMES

        _check_tasks(self.tasks, TASK_NAMES, f"{where}, export.tasks")


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

    def check(self, where: str) -> None:
        """Check the section's values (``where``: the profile); :raises ConfigError: a bad one."""
        _check_teacher_policy(self.teacher_policy, "hyperdistill.teacher_policy", where)
        if self.loss not in ("nll", "kl"):
            _refuse(f"{where}: hyperdistill.loss must be 'nll' or 'kl', got {self.loss!r}")
        for key in ("task_input", "observation_statistics", "normalized_keys"):
            if key in self.policy_kwargs:
                _refuse(
                    f"{where}: hyperdistill.policy_kwargs.{key} is set by the pipeline (the task's index in, "
                    "each state normalised with its task's teacher's statistics)"
                )


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

    def check(self, where: str) -> None:
        """Check the section's values (``where``: the profile); :raises ConfigError: a bad one."""
        _check_ppo_keys(self.overrides, f"{where}, grl.overrides")
        if self.population < 1 or self.generations < 1 or self.learngene_layers < 1 or self.tournament < 1:
            _refuse(f"{where}: grl.population, generations, learngene_layers and tournament must be >= 1")


@dataclass
class EvaluateConfig:
    """Per-morphology evaluation."""

    #: deterministic episodes per robot (they differ by reset noise and terrain)
    episodes: int = 3

    def check(self, where: str) -> None:
        """Nothing to check beyond the keys (``where``: the profile)."""


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
    #: (taller, lighter, random designs); ``None``: none
    ood_set: str | None = None
    #: the first N robots of ``ood_set`` (``null``: all)
    ood_robots: int | None = None
    #: episode length limit of every env of the run
    max_episode_steps: int = 1000
    #: what body heights in the robots' proprioception are measured from, in every env of the run
    #: (``gym.make(..., height_reference=...)``): ``world`` (MetaMorph's convention, default) or
    #: ``ground`` (above the ground under the torso: the same statistics on every task, the better
    #: input for a multi-task student); single env backend only
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

    def check(self, where: str) -> None:
        """Check the profile's own values, not its sections' (``where``: the profile); :raises ConfigError: a bad one."""
        from unimal_envs.contract import HEIGHT_REFERENCES

        if self.height_reference not in HEIGHT_REFERENCES:
            _refuse(f"{where}: height_reference must be one of {list(HEIGHT_REFERENCES)}, got {self.height_reference!r}")
        if self.goal_range is not None and not self.goal_range > 0:
            _refuse(f"{where}: goal_range must be null or a distance > 0 (m), got {self.goal_range!r}")


#: The profile's sections by key: each a dataclass whose fields are the section's keys.
SECTIONS: dict[str, type] = {
    "teachers": TeachersConfig,
    "student": StudentConfig,
    "distill": DistillConfig,
    "transfer": TransferConfig,
    "export": ExportConfig,
    "evaluate": EvaluateConfig,
    "grl": GRLConfig,
    "hyperdistill": HyperDistillConfig,
}


def section_keys(cls: type) -> list[str]:
    """The keys of section (or profile) ``cls`` as messages list them: its own in declaration order,
    then those it shares with other sections (:class:`SimulationSettings`)."""
    names = [f.name for f in dataclasses.fields(cls)]
    shared = {f.name for f in dataclasses.fields(SimulationSettings)} if issubclass(cls, SimulationSettings) else set()
    return [n for n in names if n not in shared] + [n for n in names if n in shared]


def _is_mapping(cls: type, name: str) -> bool:
    """Whether field ``name`` of ``cls`` holds a free mapping (``policy_kwargs``, ``overrides``...), whose own keys are not checked here."""
    hint = typing.get_type_hints(cls)[name]
    return typing.get_origin(hint) is dict or any(typing.get_origin(arg) is dict for arg in typing.get_args(hint))


def unknown_override(key: str, removed: Mapping[str, Any] = {}) -> str | None:
    """What is wrong with the dotted ``--set`` key ``key`` (``teachers.n_timesteps``), or ``None``.

    Only the profile's own key names are checked (values, and the keys inside free mappings such as
    ``student.policy_kwargs``, are left to the full validation); a key in ``removed`` is left to it
    too, which names what replaced it.
    """
    if key in removed:
        return None
    parts = key.split(".")
    names = [f.name for f in dataclasses.fields(Profile) if f.name != "name"]
    if parts[0] not in names:
        return f"unknown key(s) {[parts[0]]}; valid keys: {names}"
    section = SECTIONS.get(parts[0])
    if section is None:
        return f"{parts[0]!r} is not a section of the profile" if len(parts) > 1 else None
    if len(parts) == 1:
        return None
    keys = section_keys(section)
    if parts[1] not in keys:
        return f"section {parts[0]!r}: unknown key(s) {[parts[1]]}; valid keys: {keys}"
    if len(parts) > 2 and not _is_mapping(section, parts[1]):
        return f"{parts[0]}.{parts[1]} is not a section of the profile"
    return None


def unknown_tasks(tasks: list[str]) -> str | None:
    """What is wrong with task names that are no task's (with the closest name as a hint), or ``None``."""
    from unimal_envs.contract import TASK_NAMES

    not_tasks = [task for task in tasks if task not in TASK_NAMES]
    if not not_tasks:
        return None
    close = {task: difflib.get_close_matches(task, TASK_NAMES, n=1) for task in not_tasks}
    hints = "; ".join(f"{task!r} (did you mean {match[0]!r}?)" if match else repr(task) for task, match in close.items())
    return f"unknown task(s) {hints}; tasks are {list(TASK_NAMES)}"
