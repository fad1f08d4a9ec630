"""Pipeline profiles (``zoo_configs/divmorph.yml``), validated (rl-zoo entries: :mod:`sb3_divmorph.zoo`).

A profile is plain YAML; every section maps onto a dataclass of :mod:`divmorph.profile`, which
checks its values (``check``), and a key the dataclass does not have is an error that names it and
lists the valid ones (a typo must never be silently ignored in a run that takes hours).
"""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

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
from divmorph.profile import (  # noqa: F401 -- the sections and their checks live in divmorph.profile; re-exported here
    ENV_BACKENDS,
    SECTIONS,
    TEACHER_POLICIES,
    DistillConfig,
    EvaluateConfig,
    ExportConfig,
    GRLConfig,
    HyperDistillConfig,
    Profile,
    SimulationSettings,
    StudentConfig,
    TeachersConfig,
    TransferConfig,
    check_arms,
    check_seeds,
    section_keys,
)
from unimal_envs import env_id

DEFAULT_PROFILES = Path("zoo_configs") / "divmorph.yml"


def _from_dict(cls: type, values: dict[str, Any] | None, where: str):
    values = dict(values or {})
    names = section_keys(cls)
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


def profile_from_dict(name: str, values: dict[str, Any]) -> Profile:
    """The validated :class:`Profile` named ``name`` from its raw mapping (a profile file's entry, a
    recorded ``run.json``): unknown keys name the valid ones, and every value is checked.

    :raises ConfigError: an unknown, removed or missing key, or a bad value.
    """
    # the sections every profile has (grl and hyperdistill are optional, read below)
    sections = {key: section for key, section in SECTIONS.items() if key not in ("grl", "hyperdistill")}
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
    # each section checks its own values (divmorph.profile), then the profile its top-level ones
    for key in SECTIONS:
        section = getattr(profile, key)
        if section is not None:
            section.check(f"profile {name!r}")
    profile.check(f"profile {name!r}")
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
    """The rl-zoo entry of ``task``'s teacher: ``Unimal-<task>-v<N>``, or its ``-<recipe>`` variant."""
    env_name = env_id(task)
    return f"{env_name}-{profile.teachers.recipe}" if profile.teachers.recipe else env_name


def teacher_policy(profile: Profile, task: str) -> str:
    """The policy of the run's teacher of ``task``: ``teachers.policy``, else the zoo entry's."""
    cfg = profile.teachers
    return cfg.policy or load_zoo_entry(cfg.hyperparams, zoo_entry_id(profile, task), cfg.overrides).policy
