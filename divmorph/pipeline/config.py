"""Pipeline profiles (``zoo_configs/divmorph.yml``), validated (rl-zoo entries: :mod:`sb3_divmorph.zoo`).

A profile is plain YAML; every section maps onto a dataclass below, and a key the dataclass does
not have is an error that names it and lists the valid ones (a typo must never be silently
ignored in a run that takes hours).
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping
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
from divmorph.profile import (  # noqa: F401 -- the sections are declared in divmorph.profile; re-exported here
    DistillConfig,
    EvaluateConfig,
    ExportConfig,
    GRLConfig,
    HyperDistillConfig,
    Profile,
    StudentConfig,
    TeachersConfig,
    TransferConfig,
)
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


def profile_from_dict(name: str, values: dict[str, Any]) -> Profile:
    """The validated :class:`Profile` named ``name`` from its raw mapping (a profile file's entry, a
    recorded ``run.json``): unknown keys name the valid ones, and every value is checked.

    :raises ConfigError: an unknown, removed or missing key, or a bad value.
    """
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
    parsed = {key: _from_dict(section, values.pop(key, None), f"profile {name!r}, section {key!r}") for key, section in sections.items()}
    if values.get("grl") is not None:
        parsed["grl"] = _from_dict(GRLConfig, values.pop("grl"), f"profile {name!r}, section 'grl'")
    else:
        values.pop("grl", None)
    if values.get("hyperdistill") is not None:
        parsed["hyperdistill"] = _from_dict(HyperDistillConfig, values.pop("hyperdistill"), f"profile {name!r}, section 'hyperdistill'")
    profile = _from_dict(Profile, {**values, **parsed, "name": name}, f"profile {name!r}")
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
        raise ConfigError(f"profile {name!r}: height_reference must be one of {list(HEIGHT_REFERENCES)}, got {profile.height_reference!r}")
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
        raise ConfigError(f"profile {name!r}: transfer.action_std must be a positive number or null, got {profile.transfer.action_std!r}")
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
        raise ConfigError(f"profile {name!r}: transfer.instructions for {stray}, which are not in transfer.tasks {profile.transfer.tasks}")
    if not 0 <= profile.distill.beta_start <= 1 or not 0 <= profile.distill.beta_end <= 1:
        raise ConfigError(f"profile {name!r}: distill.beta_start/beta_end must be in [0, 1]")
    if profile.distill.ppo_loss and max(profile.distill.beta_start, profile.distill.beta_end) > 0:
        raise ConfigError(f"profile {name!r}: distill.ppo_loss needs beta_start = beta_end = 0 (mixing is off-policy)")
    return profile


def check_removed_keys(values: dict[str, Any], where: str) -> None:
    """A profile that sets a removed key, or a kept key to its retired value, is an error naming it and
    what replaces it (a run recorded in record format 1 is migrated once: ``divmorph migrate``)."""
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
        return profile_from_dict(name, apply_overrides(profiles[name], overrides or {}))
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
