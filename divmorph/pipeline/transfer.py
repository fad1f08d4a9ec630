"""Stage 3 — transfer to a novel task: the arms of :mod:`divmorph.pipeline.arms`, raced on one budget.

Folders: ``transfer/<task>/<arm>/seed-<s>/`` (one resumable run each; with ``transfer.eval_every``
an ``eval.csv`` of deterministic returns on the training and novel robots, see
:mod:`divmorph.pipeline.curves`), and the metrics of every arm in ``transfer/<task>/metrics.csv``.

Every arm trains with the novel task's rl-zoo settings on the training robots (``Unimal-<task>-v0``),
with one optimiser rule for all: Adam's ``eps`` is ``transfer.adam_eps`` in every arm.
Arms that start from a trained model (student, teacher, GRL agent) take its weights and its
observation statistics, which stay *frozen* for the whole run (the weights were trained on inputs
normalised by exactly these; letting them move changes what even a frozen network does); reward statistics start afresh for the new task and learn.
Every arm sees the novel task's inputs: a source without an encoder for one of them (the teacher
of a task without a height map, fine-tuned on Escape) gets the encoder the task's own
architecture has, freshly initialised, next to all its trained weights (:func:`finetuned_model`).
In the DivMorph arm (and the ablations, transferred the same way) the gates see the embedding of
the task's instruction (the built-in one, or ``transfer.instructions[task]`` of the profile,
embedded by the text encoder) and stay fixed; PPO trains the tailors those gates select and,
``learngene_lr_scale`` times slower, the shared knowledge (:func:`sb3_divmorph.algos.finetune.prepare_transfer`).
A part an ablation does not divert has no tailors; it trains at ``transfer.undiverted_lr_scale``
(default: the full rate, as any fine-tuned network).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecNormalize

from sb3_divmorph.algos.adaptive_rate import AdaptiveLearningRate
from sb3_divmorph.algos.device_ppo import DevicePPO
from sb3_divmorph.algos.finetune import (
    CriticWarmup,
    UnitLearningRates,
    UnitSelection,
    critic_rate_scales,
    prepare_transfer,
    rotation_rate_scales,
    set_adam_eps,
)
from divmorph.pipeline.arms import ARMS
from divmorph.pipeline.config import ConfigError, Profile, check_arms, check_seeds, grl_policy_kwargs, load_zoo_entry
from divmorph.pipeline.curves import EVAL_FILE, EvalCurveCallback, evaluate_model, write_metrics
from divmorph.pipeline.folders import (  # noqa: F401 -- transfer_folder, transfer_seeds, transfer_tasks re-exported
    read_learngene,
    student_folder,
    teacher_folder,
    transfer_folder,
    transfer_seeds,
    transfer_tasks,
)
from divmorph.pipeline.grid import GridReport, Job, run_grid
from divmorph.pipeline.envs import (
    inherited_normalizer,
    make_vec_env,
    normalizer_for,
    profile_env_kwargs,
    resolve_device,
    robot_observations,
    task_env_name,
)
from divmorph.pipeline.files import atomic_write_json, is_done
from divmorph.pipeline.robots import profile_robots, transfer_eval_robots
from divmorph.pipeline.training import TrainingRun, stage_model  # robot_observations re-exported
from sb3_divmorph.policies.learngene import inherit
from sb3_divmorph.policies.morphology_transformer import PRESETS, DivMorphPolicy
from unimal_envs.contract import NOVEL_TASKS, TASK_NAMES
from unimal_envs.instructions import INSTRUCTIONS, embed_instruction, shipped_embeddings
from unimal_envs.tasks import TASKS


def gate_selection(policy: DivMorphPolicy, raw_obs: dict[str, np.ndarray], normalizer: VecNormalize | None) -> UnitSelection:
    """The tailors the student's gates select for these robots doing this task."""
    obs = raw_obs if normalizer is None else normalizer.normalize_obs(raw_obs)
    gates = policy.get_gates(obs)
    return UnitSelection.from_gates(gates.morphology.cpu().numpy(), gates.task.cpu().numpy())


class UpdateRatioLogger(BaseCallback):
    """Logs ``transfer/update_ratio``: the learngene / selected-tailor mean absolute update of the
    last rollout's optimiser steps, as applied (the configured ``learngene_lr_scale`` is the target).

    :param rates: returns the installed :class:`~sb3_divmorph.algos.finetune.UnitLearningRates`.
    """

    def __init__(self, rates: Callable[[], UnitLearningRates | None]):
        super().__init__()
        self.rates = rates

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        # the optimiser steps between two rollouts are the previous rollout's update
        rates = self.rates()
        if rates is not None and self.model.num_timesteps > 0:
            means = rates.mean_updates(reset=True)
            if means["selected_tailor"] > 0:
                self.logger.record("transfer/update_ratio", means["learngene"] / means["selected_tailor"])
                self.logger.record("transfer/update_selected_tailor", means["selected_tailor"])
            if np.isfinite(means.get("undiverted", np.nan)):
                self.logger.record("transfer/update_undiverted", means["undiverted"])


def closest_file(out: Path, task: str, by: str) -> Path:
    return Path(out) / "transfer" / task / f"closest-by-{by}.json"


def closest_task(profile: Profile, out: Path, task: str, by: str | None = None) -> dict[str, Any]:
    """The training task whose teacher the ``closest`` arm (MetaMorph→) starts from, and why.

    ``by="embedding"``: the largest cosine between the novel task's instruction embedding (its
    ``transfer.instructions`` text if given) and each training task's; ``by="return"``: the
    teacher with the best zero-shot return on the novel task (deterministic, training robots,
    ``transfer.eval_episodes`` episodes). The choice is written to ``transfer/<task>/closest-by-<by>.json``
    once, so every seed and every later call uses the same teacher.

    :param task: the novel task.
    :param by: ``embedding`` or ``return`` (default: ``transfer.closest_by``).
    :return: ``{"task", "closest", "by", "criterion", "scores": {training task: score}}``.
    """
    by = by or profile.transfer.closest_by
    path = closest_file(out, task, by)
    if path.is_file():
        return json.loads(path.read_text())
    teachers = list(profile.teachers.tasks)
    if by == "embedding":
        target = embed_instruction(profile.transfer.instructions.get(task, INSTRUCTIONS[task]))
        embeddings = shipped_embeddings()
        scores = {t: float(np.dot(target, embeddings[t]) / (np.linalg.norm(target) * np.linalg.norm(embeddings[t]))) for t in teachers}
        what = "cosine of the instruction embeddings"
    elif by == "return":
        robots = transfer_eval_robots(profile, "train")
        scores = {}
        for t in teachers:
            rows = evaluate_model(
                teacher_folder(out, t),
                task,
                robots,
                profile.transfer.eval_episodes,
                profile.max_episode_steps,
                profile.seed,
                instruction=profile.transfer.instructions.get(task),
                env_kwargs=profile_env_kwargs(profile),
            )
            scores[t] = float(np.mean([r["return"] for r in rows]))
        what = "zero-shot return of the teacher on the novel task"
    else:
        raise ConfigError(f"closest_by must be 'embedding' or 'return', got {by!r}")
    chosen = max(teachers, key=lambda t: scores[t])
    choice = {"task": task, "closest": chosen, "by": by, "criterion": what, "scores": scores}
    atomic_write_json(path, choice)
    return choice


def gate_instruction(profile: Profile, out: Path, task: str, arm: str) -> str | None:
    """The closest training task's instruction when ``transfer.task_gates: closest`` gives it to this
    arm (an arm that starts from a DivMorph student, whose router -- the only reader of the task
    embedding -- then selects that task's tailors), else ``None``.

    :raises ConfigError: an unknown ``task_gates``.
    """
    cfg = profile.transfer
    if cfg.task_gates not in ("instruction", "closest"):
        raise ConfigError(f"transfer.task_gates must be 'instruction' or 'closest', got {cfg.task_gates!r}")
    if cfg.task_gates == "closest" and ARMS[arm].gated:
        return INSTRUCTIONS[closest_task(profile, out, task)["closest"]]
    return None


def describe_closest(choice: dict[str, Any]) -> str:
    """Which teacher the ``closest`` arm starts from, and why, in one line."""
    scores = choice["scores"]
    ranked = ", ".join(f"{t} {scores[t]:.3f}" for t in sorted(scores, key=scores.get, reverse=True))
    return f"{choice['task']}: closest training task {choice['closest']} by {choice['criterion']} ({ranked})"


def arm_source(profile: Profile, out: Path, task: str, arm: str) -> Path | None:
    """The folder an arm starts from (``None``: random init), checked to exist.

    :raises FileNotFoundError: its prerequisite stage has not run; the message names the command.
    """
    spec = ARMS[arm]
    out = Path(out)
    if spec.student is not None:
        folder = student_folder(out, spec.student)
        if not is_done(folder):
            raise FileNotFoundError(
                f"no distilled student for arm {arm!r} in {folder}; run `divmorph distill --out {out} --arms {arm}` first"
            )
        return folder
    if arm == "closest":
        missing = [t for t in profile.teachers.tasks if not is_done(teacher_folder(out, t))]
        if missing:
            raise FileNotFoundError(
                f"arm 'closest' needs the teachers; {missing} not found in {out / 'teachers'}: run `divmorph teachers --out {out}` first"
            )
        return teacher_folder(out, closest_task(profile, out, task)["closest"])
    if arm == "grl":
        return out / read_learngene(out)["folder"]
    return None


def check_arm_prerequisites(profile: Profile, out: Path, tasks: list[str], arms: list[str], seeds: list[int] = (0,)) -> None:
    """Before any run starts: every arm's prerequisite exists, the ``closest`` choices are made (and
    printed), and no existing run folder was begun from another source."""
    for task in tasks:
        if task not in NOVEL_TASKS:
            raise ConfigError(f"transfer targets a novel task; {task!r} is not one of {list(NOVEL_TASKS)}")
        for arm in arms:
            source = arm_source(profile, out, task, arm)
            if arm == "closest":
                print(f"[transfer] {describe_closest(closest_task(profile, out, task))}")
            for seed in seeds:
                record = _source_record(out, arm, seed, source, gate_instruction(profile, out, task, arm))
                _check_source(transfer_folder(out, task, arm, seed), record, write=False)


def _source_record(out: Path, arm: str, seed: int, source: Path | None, instruction: str | None = None) -> dict[str, Any]:
    """What a run started from; ``instruction``: the one ``task_gates: closest`` gave it (recorded only
    then: under the default rule the record is the same as without the setting; the evaluation stage
    reads it back)."""
    record = {"arm": arm, "seed": seed, "source": None if source is None else str(Path(source).relative_to(out))}
    if instruction is not None:
        record["instruction"] = instruction
    return record


def _check_source(folder: Path, source: dict[str, Any], write: bool = True) -> None:
    """Remember what a run started from; a run folder begun from something else is refused (not overwritten)."""
    path = folder / "source.json"
    if path.is_file():
        recorded = json.loads(path.read_text())
        if recorded != source:
            raise ConfigError(
                f"{folder} was started from {recorded['source']} ({recorded.get('instruction', 'the built-in instruction')}), "
                f"not {source['source']} ({source.get('instruction', 'the built-in instruction')}); "
                "use another --out (or delete that folder) to start it again"
            )
    elif write:
        atomic_write_json(path, source)


def resolved_exteroception(policy_kwargs: dict[str, Any]) -> dict[str, list[int]]:
    """The exteroception encoders (``{key: widths}``) a MetaMorph built with ``policy_kwargs`` has:
    its ``exteroception`` keyword, or its preset's."""
    extero = policy_kwargs.get("exteroception")
    if extero is None:
        extero = PRESETS[policy_kwargs.get("preset", "small")]["exteroception"]
    return {key: list(dims) for key, dims in extero.items() if len(dims) > 0}


def _feature_layout(policy: th.nn.Module) -> list[tuple[str, int]]:
    """``[(part, width)]`` of the token features the decoders read: the Transformer's ``d_model``
    columns, then each exteroception encoder's output in the extractor's order."""
    extractor = policy.features_extractor if policy.share_features_extractor else policy.pi_features_extractor
    return [("tokens", extractor.d_model), *((key, encoder.out_dim) for key, encoder in extractor.exteroception.items())]


@th.no_grad()
def load_widened(policy: th.nn.Module, source: th.nn.Module) -> list[str]:
    """Load ``source``'s weights into ``policy``, a copy of its architecture with more exteroception
    encoders; returns the names of the tensors left at ``policy``'s fresh initialisation.

    Tensors of the same name and shape are copied. The layers that read the token features (the
    first layer of each decoder) are wider by the new encoders' outputs: their columns for the
    Transformer's output and for the encoders ``source`` has are copied, the new encoders' columns
    and the new encoders themselves keep their fresh initialisation (so the policy reads the new
    inputs from the first step).

    :param policy: the widened policy (freshly initialised).
    :param source: the trained policy.
    :raises ValueError: a tensor differs in a way other than these columns (the architectures differ).
    """
    old_layout, new_layout = _feature_layout(source), _feature_layout(policy)
    missing = [part for part, _ in old_layout if part not in dict(new_layout)]
    if missing:
        raise ValueError(f"cannot widen: the new policy lacks the source's encoder(s) {missing}")

    def offsets(layout):
        result, start = {}, 0
        for part, width in layout:
            result[part] = slice(start, start + width)
            start += width
        return result, start

    old_cols, old_width = offsets(old_layout)
    new_cols, new_width = offsets(new_layout)
    theirs = source.state_dict()
    fresh = []
    for name, tensor in policy.state_dict().items():
        if name not in theirs:
            fresh.append(name)
            continue
        value = theirs[name]
        if value.shape == tensor.shape:
            tensor.copy_(value)
        elif value.dim() == 2 and value.shape[0] == tensor.shape[0] and (value.shape[1], tensor.shape[1]) == (old_width, new_width):
            for part, columns in old_cols.items():
                tensor[:, new_cols[part]] = value[:, columns]
            fresh.append(f"{name} (the new encoders' columns)")
        else:
            raise ValueError(f"cannot widen: {name} is {tuple(value.shape)} in the source and {tuple(tensor.shape)} here")
    return fresh


def finetuned_model(
    saved: PPO,
    venv,
    task: str,
    task_policy_kwargs: dict[str, Any],
    seed: int,
    device: str,
    ppo_kwargs: dict[str, Any],
    algo: type[PPO] = PPO,
    action_std: float | None = None,
    adapter_rank: int = 0,
) -> PPO:
    """A PPO model on ``venv`` that starts from ``saved``'s policy and sees ``task``'s inputs.

    A policy without an encoder for one of the task's observations (a teacher of a task without a
    height map, fine-tuned on Escape) gets the encoder the task's own architecture
    (``task_policy_kwargs``, what the ``scratch`` arm is built with) has, freshly initialised, and
    keeps every weight it has (:func:`load_widened`); otherwise its architecture and weights are
    taken as they are.

    :param saved: the trained model.
    :param venv: the novel task's envs (normalised).
    :param task: the novel task.
    :param task_policy_kwargs: the novel task's MetaMorph kwargs.
    :param algo: ``PPO``, or ``DevicePPO`` on the batched backend (rollouts on the device).
    :param action_std: the std the fine-tuned policy samples from (``None``: ``saved``'s); its mean
        action, every weight, stays ``saved``'s.
    :param adapter_rank: give every factorized layer a zero-initialised adapter of this width (the
        ``adapter`` recipe); the policy computes what ``saved``'s does until the adapters train.
    """
    kwargs = dict(saved.policy_kwargs)
    if action_std is not None:
        kwargs["action_std"] = action_std
    if adapter_rank:
        kwargs["adapter_rank"] = adapter_rank
    extractor = saved.policy.features_extractor if saved.policy.share_features_extractor else saved.policy.pi_features_extractor
    has = set(extractor.exteroception.keys()) if hasattr(extractor, "exteroception") else None
    needed = [key for key in TASKS[task].observation_keys if has is not None and key not in has]
    if needed:
        wanted = resolved_exteroception(task_policy_kwargs)
        lacking = [key for key in needed if key not in wanted]
        if lacking:
            raise ConfigError(
                f"{task} observes {lacking}, but neither the source policy nor {task}'s own architecture "
                f"(policy_kwargs {task_policy_kwargs}) has an encoder for it"
            )
        kwargs["exteroception"] = {**{key: wanted[key] for key in needed}, **saved.policy.config["exteroception"]}
    model = algo(type(saved.policy), venv, policy_kwargs=kwargs, seed=seed, device=device, **ppo_kwargs)
    if needed:
        load_widened(model.policy, saved.policy)
    else:
        missing, unexpected = model.policy.load_state_dict(saved.policy.state_dict(), strict=False)
        fresh = [key for key in missing if not key.endswith(("adapter_down", "adapter_up"))]
        if fresh or unexpected:
            raise RuntimeError(f"the source policy does not fit: missing {fresh}, unexpected {unexpected}")
    if action_std is not None:
        set_action_std(model.policy, action_std)
    return model


def set_action_std(policy, action_std: float) -> None:
    """Sample ``policy``'s actions with std ``action_std`` from now on (a fixed std or a learned log-std's start).

    The std lives in the policy's ``log_std`` (a buffer when fixed, a parameter when learned), which
    a loaded state dict overwrites: this sets it after the weights are in.

    :raises ConfigError: ``action_std`` is not positive, or the policy has no such std.
    """
    if not action_std > 0:
        raise ConfigError(f"transfer.action_std must be positive, got {action_std!r}")
    if not hasattr(policy, "log_std") or not hasattr(policy, "action_std"):
        raise ConfigError(f"{type(policy).__name__} has no state-independent std to set (transfer.action_std)")
    with th.no_grad():
        policy.log_std.fill_(math.log(action_std))
    policy.action_std = float(action_std)


def transfer_seed(profile: Profile, task: str, seed: int) -> int:
    """PPO seed of one run: the run's seed, a fixed offset, the task's index and 100 per ``seed``."""
    return profile.seed + 7000 + TASK_NAMES.index(task) + 100 * seed


def recipe_for(recipe: str, num_timesteps: int) -> str:
    """The recipe ``prepare_transfer`` applies to a model built or loaded at ``num_timesteps``: ``kind``
    restarts the selected task tailors once, on the fresh model (step 0); a checkpoint or a finished run of
    it was restarted already and trains, or is evaluated, as ``fixed-gates``."""
    return "fixed-gates" if recipe == "kind" and num_timesteps > 0 else recipe


def transfer_run(
    profile: Profile, out: Path, task: str, arm: str, seed: int = 0, progress_bar: bool = True, calibration: bool = False
) -> TrainingRun:
    """The (resumable) PPO run of one arm and seed on a novel task (see :mod:`divmorph.pipeline.arms`).

    :param task: a novel task.
    :param arm: a name of :data:`~divmorph.pipeline.arms.ARMS`.
    :param seed: offsets the PPO seed (the robots, budget and evaluation are the same for every seed).
    :param calibration: also accept a *training* task: a setting of the race (a learning rate, the
        critic's treatment) is chosen by running the arms on a training task, never on the novel ones.
    :raises ConfigError: not a novel task, unknown arm, or the run folder was begun from another source.
    :raises FileNotFoundError: the arm's prerequisite stage has not run.
    """
    if task not in NOVEL_TASKS and not (calibration and task in TASK_NAMES):
        raise ConfigError(f"transfer targets a novel task; {task!r} is not one of {list(NOVEL_TASKS)}")
    check_arms([arm], "transfer")
    cfg = profile.transfer
    out = Path(out)
    env_name = task_env_name(task)
    folder = transfer_folder(out, task, arm, seed)
    spec = ARMS[arm]
    source = arm_source(profile, out, task, arm)
    # arms that start from trained weights (a source, or GRL's inherited layers) are fine-tuned
    overrides = cfg.overrides if source is None else {**cfg.overrides, **cfg.finetune_overrides}
    entry = load_zoo_entry(profile.teachers.hyperparams, env_name, overrides)
    robots = transfer_eval_robots(profile, "train") if cfg.train_robots == "eval" else profile_robots(profile, "train")
    device = resolve_device(profile.device)
    run_seed = transfer_seed(profile, task, seed)
    gamma = entry.ppo_kwargs.get("gamma", 0.99)
    env_kwargs = {"morphologies": robots, **profile_env_kwargs(profile)}
    gated = gate_instruction(profile, out, task, arm)
    instruction = gated or cfg.instructions.get(task)
    if instruction is not None:
        env_kwargs["instruction"] = instruction

    def make_env():
        return make_vec_env(
            env_name,
            entry.n_envs,
            run_seed,
            profile.max_episode_steps,
            cfg.env_backend,
            cfg.worlds_per_robot,
            device,
            cfg.terrain_variants,
            **env_kwargs,
        )

    # On the batched backend, rollouts stay on the device (DevicePPO; SB3's PPO otherwise); the
    # arms' optimiser rules (per-unit rates, critic scale, Adam eps) live on the optimiser, which
    # DevicePPO's update (SB3's own) steps as PPO's does, and no callback here reads per-world infos.
    algo = DevicePPO if cfg.env_backend == "batched" else PPO
    callbacks: list[BaseCallback] = []
    if source is not None and cfg.critic_warmup > 0:
        callbacks.append(CriticWarmup(cfg.critic_warmup))
    if cfg.desired_kl is not None:
        callbacks.append(AdaptiveLearningRate(cfg.desired_kl))
    if cfg.eval_every > 0:
        splits = {split: transfer_eval_robots(profile, split) for split in cfg.eval_splits}
        callbacks.append(
            EvalCurveCallback(
                folder / EVAL_FILE,
                env_name,
                splits,
                cfg.eval_every,
                cfg.eval_episodes,
                profile.max_episode_steps,
                profile.seed,
                backend=cfg.eval_backend,
                device=device,
                terrain_variants=cfg.terrain_variants,
                **profile_env_kwargs(profile),
                **({"instruction": instruction} if instruction is not None else {}),
            )
        )
    if source is None:
        # scratch and modumorph: the policy from random init, sized like the teachers
        policy = "ModuMorphPolicy" if arm == "modumorph" else "MetaMorphPolicy"
        policy_kwargs = {**entry.policy_kwargs, **profile.teachers.policy_kwargs}

        def make_model():
            venv = normalizer_for(make_env(), entry.normalize, gamma)
            return algo(policy, venv, policy_kwargs=policy_kwargs, seed=run_seed, device=device, **entry.ppo_kwargs)

    elif arm == "grl":
        learngene = read_learngene(out)

        def make_model():
            # a new MetaMorph; only the learngene's layers (and the observation statistics they were trained with) inherited
            venv = inherited_normalizer(source, make_env(), gamma, freeze_observations=True)
            policy_kwargs = {**grl_policy_kwargs(profile), **({"action_std": cfg.action_std} if cfg.action_std is not None else {})}
            model = algo("MetaMorphPolicy", venv, policy_kwargs=policy_kwargs, seed=run_seed, device=device, **entry.ppo_kwargs)
            inherit(model.policy, PPO.load(stage_model(source), device=device).policy, learngene["units"])
            return model

    else:
        task_policy_kwargs = {**entry.policy_kwargs, **profile.teachers.policy_kwargs}

        def make_model():
            # the source's weights and observation statistics (frozen unless told otherwise); reward statistics
            # start afresh for the new task; an encoder for a task input the source never had is added
            saved = PPO.load(stage_model(source), device=device)
            venv = inherited_normalizer(source, make_env(), gamma, freeze_observations=cfg.freeze_statistics)
            adapter_rank = cfg.adapter_rank if spec.divmorph_transfer and cfg.recipe == "adapter" else 0
            return finetuned_model(
                saved, venv, task, task_policy_kwargs, run_seed, device, entry.ppo_kwargs, algo, cfg.action_std, adapter_rank
            )

    installed: dict[str, UnitLearningRates] = {}
    if spec.divmorph_transfer:
        selection_obs = robot_observations(env_name, robots, run_seed, env_kwargs.get("instruction"), **profile_env_kwargs(profile))

        def prepare(model):
            with th.no_grad():
                selection = gate_selection(model.policy, selection_obs, model.get_vec_normalize_env())
            # the hooks live on the optimiser; they are installed again whenever the run is loaded
            installed["rates"] = prepare_transfer(
                model.policy,
                selection,
                cfg.learngene_lr_scale,
                adam_eps=cfg.adam_eps,
                undiverted_scale=cfg.undiverted_lr_scale,
                critic_scale=cfg.critic_lr_scale if source is not None else 1.0,
                rotation_scale=cfg.rotation_lr_scale,
                recipe=recipe_for(cfg.recipe, model.num_timesteps),
            )

        callbacks.append(UpdateRatioLogger(lambda: installed.get("rates")))
    else:

        def prepare(model):
            # one optimiser rule for every arm (set again whenever the run is loaded)
            set_adam_eps(model.policy.optimizer, cfg.adam_eps)
            scales = critic_rate_scales(model.policy, cfg.critic_lr_scale) if source is not None and cfg.critic_lr_scale != 1 else {}
            if spec.gated and cfg.rotation_lr_scale != 1:
                # a DivMorph student fine-tuned freely: its Cayley generators at rotation_lr_scale of the rate
                scales.update(rotation_rate_scales(model.policy, cfg.rotation_lr_scale))
            if scales:
                # the fine-tuned actor's rate for the actor, multiples of it for the critic and the rotations (hooks on the optimiser)
                installed["critic"] = UnitLearningRates(model.policy.optimizer, scales)

    _check_source(folder, _source_record(out, arm, seed, source, gated))
    return TrainingRun(
        folder,
        cfg.n_timesteps,
        cfg.checkpoint_every,
        make_model,
        make_env,
        algo=algo,
        prepare=prepare,
        callbacks=callbacks,
        device=device,
        progress_bar=progress_bar,
    )


def transfer_jobs(profile: Profile, out: Path, tasks: list[str], arms: list[str], seeds: list[int]) -> list[Job]:
    """Arms x tasks x seeds as grid jobs."""
    return [
        Job(f"{__name__}:transfer_run", (task, arm, seed), transfer_folder(out, task, arm, seed), f"transfer {task} {arm} seed {seed}")
        for task in tasks
        for arm in arms
        for seed in seeds
    ]


def transfer(
    profile: Profile,
    out: Path,
    tasks: list[str] | None = None,
    progress_bar: bool = True,
    arms: list[str] | None = None,
    seeds: list[int] | None = None,
    backend=None,
    closest_by: str | None = None,
) -> GridReport:
    """Race the arms on the novel tasks: every arm x task x seed is one resumable run (finished ones are skipped).

    :param tasks: novel tasks (default: the profile's).
    :param arms: arms to run (default: ``transfer.arms``); see :data:`~divmorph.pipeline.arms.ARMS`.
    :param seeds: seeds (default: ``transfer.seeds``).
    :param backend: a :mod:`~divmorph.pipeline.grid` backend (default: local, in this process).
    :param closest_by: ``embedding`` or ``return`` for the ``closest`` arm (default: ``transfer.closest_by``).
    :raises ConfigError: unknown arm or task, seeds given twice.
    :raises FileNotFoundError: an arm's prerequisite stage has not run.
    :raises GridError: some runs failed (the others finished).
    """
    cfg = profile.transfer
    if closest_by is not None:
        profile = dataclasses.replace(profile, transfer=dataclasses.replace(cfg, closest_by=closest_by))
        cfg = profile.transfer
    tasks = list(tasks or cfg.tasks)
    arms = cfg.arm_list() if arms is None else list(arms)
    seeds = list(cfg.seeds if seeds is None else seeds)
    # every name is checked before the first one is announced and trained
    unknown = [task for task in tasks if task not in NOVEL_TASKS]
    if unknown:
        raise ConfigError(f"transfer targets a novel task; {unknown} not one of {list(NOVEL_TASKS)}")
    check_arms(list(arms), "--arms")
    check_seeds(seeds, "--seeds")
    check_arm_prerequisites(profile, out, tasks, arms, seeds)
    jobs = transfer_jobs(profile, out, tasks, arms, seeds)
    for job in jobs:
        task, arm, seed = job.args
        if is_done(job.folder):
            print(f"[transfer] {task} ({arm}) seed {seed}: skipped, already trained in {job.folder}")
        else:
            print(f"[transfer] {task} ({arm}) seed {seed}: PPO for {cfg.n_timesteps} steps -> {job.folder}")
    report = run_grid(profile, out, jobs, backend, progress_bar)
    report.raise_on_failure()
    if cfg.eval_every > 0:
        for task in tasks:
            write_metrics(profile, out, task)
    return report
