"""The shipped rl-zoo hyperparameters and pipeline profiles (``zoo_configs/``), from anywhere.

``zoo_configs/`` lives at the repository root and is installed as the package
``sb3_divmorph.zoo_configs`` (wheels and editable installs alike), so an installed ``divmorph``
finds its profiles and zoo entries from any working directory. Three ways in:

* rl-zoo reads a Python module's ``hyperparams`` when ``--conf-file`` is not a ``.yml`` path, so
  ``python -m rl_zoo3.train --algo ppo --env Unimal-FT-v0 --gym-packages unimal_envs sb3_divmorph
  --conf-file sb3_divmorph.zoo`` works from any folder (``zoo_configs/ppo.yml`` only from the
  repository root);
* :func:`zoo_hyperparams` gives one entry ready for ``PPO(...)``, with the schedules and the
  ``policy_kwargs`` / ``normalize`` strings evaluated, as rl-zoo would;
* :func:`config_file` / :func:`zoo_configs_dir` locate the files themselves.
"""

from __future__ import annotations

import importlib.resources
import inspect
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from stable_baselines3 import PPO
from stable_baselines3.common.utils import LinearSchedule

#: Where profiles and zoo files are looked up when a relative path is given.
REPO_ROOT = Path(__file__).resolve().parents[1]
#: The checkout this module sits in (used when the package is run from a source tree, not installed).
_SOURCE_TREE_CONFIGS = Path(__file__).resolve().parents[1] / "zoo_configs"


class ConfigError(ValueError):
    """A profile or hyperparameter file is invalid (unknown key, bad value, missing file)."""


def resolve_path(path: str | Path) -> Path:
    """``path`` as given if it exists; else a ``zoo_configs/...`` path among the shipped
    configuration files (found from any working directory, installed or not); else relative to
    the repository root."""
    path = Path(path)
    if path.exists() or path.is_absolute():
        return path
    if path.parts and path.parts[0] == "zoo_configs":
        shipped = zoo_configs_dir().joinpath(*path.parts[1:])
        if shipped.exists():
            return shipped
    candidate = REPO_ROOT / path
    return candidate if candidate.exists() else path


def zoo_configs_dir() -> Path:
    """The folder holding ``ppo.yml`` and ``divmorph.yml``: the installed package data
    (``sb3_divmorph/zoo_configs`` in a wheel, the repository's ``zoo_configs/`` in an editable
    install), else the ``zoo_configs/`` of the source tree this module was imported from."""
    try:
        packaged = importlib.resources.files("sb3_divmorph.zoo_configs")
    except ModuleNotFoundError:  # imported from a source tree that is not installed (PYTHONPATH)
        return _SOURCE_TREE_CONFIGS
    # an installed package lies in the file system (zip imports of this package are not supported)
    return Path(str(packaged))


def config_file(name: str) -> Path:
    """A shipped configuration file by name (``"ppo.yml"``, ``"divmorph.yml"``).

    :raises FileNotFoundError: no such file among the shipped ones (the message lists them).
    """
    folder = zoo_configs_dir()
    path = folder / name
    if not path.is_file():
        shipped = sorted(p.name for p in folder.glob("*.yml"))
        raise FileNotFoundError(f"no shipped configuration file {name!r} in {folder}; shipped: {shipped}")
    return path


def zoo_hyperparams(env_id: str, overrides: dict[str, Any] | None = None, path: str | Path | None = None):
    """One rl-zoo entry ready for Stable-Baselines3, for your own ``PPO`` runs::

        hp = zoo_hyperparams("Unimal-FT-v0")
        venv = VecNormalize(make_vec_env("Unimal-FT-v0", n_envs=hp.n_envs), gamma=hp.ppo_kwargs["gamma"], **hp.normalize)
        model = PPO(hp.policy, venv, policy_kwargs=hp.policy_kwargs, **hp.ppo_kwargs)

    :param env_id: the entry, e.g. ``"Unimal-FT-v0"`` or ``"Unimal-FT-v0-metamorph"``.
    :param overrides: keys replacing the entry's (validated: unknown keys are an error).
    :param path: another rl-zoo YAML file (default: the shipped ``ppo.yml``).
    :returns: a :class:`ZooEntry` (``policy``, ``n_timesteps``,
        ``n_envs``, ``policy_kwargs``, ``normalize``, ``ppo_kwargs``, ``callbacks``).
    """
    return load_zoo_entry(path or config_file("ppo.yml"), env_id, overrides)


# -- rl-zoo hyperparameter entries -----------------------------------------------------------
#: The shipped entries' ``vec_env_wrapper``: rl-zoo steps their envs with a ``UnimalVecEnv``, as the pipeline does.
LEAN_VEC_ENV = "unimal_envs.vector.lean_vec_env"
#: Keys of an rl-zoo entry that are not PPO constructor arguments.
_ZOO_ONLY = {"n_timesteps", "policy", "n_envs", "normalize", "env_wrapper", "frame_stack", "callback", "vec_env_wrapper"}
_PPO_ARGS = set(inspect.signature(PPO.__init__).parameters) - {"self", "env", "policy"}
#: PPO arguments the pipeline sets itself (from the profile's ``seed`` and ``device``, or not at all)
_SET_BY_PIPELINE = {"seed", "device", "verbose", "tensorboard_log", "_init_setup_model"}
#: What an entry or a profile's ``overrides`` may hold: PPO's hyperparameters and the rl-zoo keys
#: the pipeline reads.
PPO_HYPERPARAMETERS = sorted(_PPO_ARGS - _SET_BY_PIPELINE)
ZOO_KEYS = sorted(_ZOO_ONLY - {"env_wrapper", "frame_stack", "vec_env_wrapper"})


def check_ppo_keys(keys, where: str) -> None:
    """Refuse keys that are neither PPO hyperparameters nor rl-zoo keys the pipeline reads.

    :param keys: the keys of a zoo entry or of a profile's ``overrides``.
    :param where: what holds them, for the message (file, profile, section).
    :raises ConfigError: naming the unknown keys and listing only the valid ones.
    """
    managed = sorted(set(keys) & _SET_BY_PIPELINE)
    if managed:
        raise ConfigError(f"{where}: {managed} are set by the pipeline (the profile's seed and device), not by a zoo entry or overrides")
    unknown = sorted(set(keys) - set(PPO_HYPERPARAMETERS) - _ZOO_ONLY)
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; PPO hyperparameters: {PPO_HYPERPARAMETERS}; rl-zoo keys: {ZOO_KEYS}")


@dataclass
class ZooEntry:
    """One env's PPO setup from an rl-zoo YAML, with strings turned into values."""

    policy: str
    n_timesteps: int
    n_envs: int
    policy_kwargs: dict[str, Any]
    normalize: dict[str, Any] | None
    ppo_kwargs: dict[str, Any]
    #: ``(class path, kwargs)`` of rl-zoo callbacks (only MetaMorph's balanced robot sampler)
    callbacks: list[tuple[str, dict[str, Any]]] = field(default_factory=list)


def _zoo_eval(text: str, where: str) -> Any:
    try:
        return eval(text, {"__builtins__": {}}, {"dict": dict, "list": list, "True": True, "False": False, "None": None})  # noqa: S307
    except Exception as error:  # noqa: BLE001
        raise ConfigError(f"{where}: cannot evaluate {text!r}: {error}") from None


def _schedule(value: Any, where: str) -> Any:
    if isinstance(value, str) and value.startswith("lin_"):
        start = float(value[4:])
        return LinearSchedule(start, 0.0, 1.0)
    if isinstance(value, str) and value.startswith("cosine_"):
        # MetaMorph's recipe: cosine decay to 0 with a short linear warm-up (sb3_divmorph.algos.recipe).
        from sb3_divmorph.algos.recipe import CosineWarmupSchedule

        try:
            return CosineWarmupSchedule(float(value[7:]))
        except ValueError as error:
            raise ConfigError(f"{where}: bad cosine schedule {value!r}: {error}") from None
    if isinstance(value, str):
        raise ConfigError(f"{where}: only numbers, 'lin_<value>' and 'cosine_<value>' schedules are supported, got {value!r}")
    return value


#: The one rl-zoo ``callback`` the pipeline understands: MetaMorph's balanced robot sampler.
BALANCED_SAMPLER = "sb3_divmorph.algos.recipe.BalancedRobotSampler"


def _callbacks(value: Any, where: str) -> list[tuple[str, dict[str, Any]]]:
    """rl-zoo's ``callback`` value (a class path, a ``{path: kwargs}`` dict, or a list of them)."""
    items = value if isinstance(value, list) else [value]
    parsed = []
    for item in items:
        path, kwargs = next(iter(item.items())) if isinstance(item, dict) and len(item) == 1 else (item, {})
        if path != BALANCED_SAMPLER:
            raise ConfigError(f"{where}: the divmorph pipeline supports only callback {BALANCED_SAMPLER!r}, got {item!r}")
        parsed.append((path, dict(kwargs or {})))
    return parsed


def load_zoo_entry(path: str | Path, env_id: str, overrides: dict[str, Any] | None = None) -> ZooEntry:
    """Read ``env_id``'s entry of an rl-zoo hyperparameter file and apply ``overrides``.

    :raises ConfigError: missing file or entry, unknown keys (neither rl-zoo nor PPO arguments).
    """
    resolved = resolve_path(path)
    if not resolved.is_file():
        raise ConfigError(f"rl-zoo hyperparameter file {path} not found")
    with open(resolved) as f:
        data = yaml.safe_load(f) or {}
    if env_id not in data:
        raise ConfigError(f"{resolved} has no entry for {env_id}; entries: {sorted(data)}")
    entry = {**data[env_id], **(overrides or {})}
    where = f"{resolved} [{env_id}]"
    check_ppo_keys(data[env_id], where)
    check_ppo_keys(overrides or {}, f"overrides of {where}")
    callbacks = _callbacks(entry.pop("callback"), where) if "callback" in entry else []
    # the shipped entries' rl-zoo VecEnv is the pipeline's own (unimal_envs.vector): nothing to apply here
    if entry.get("vec_env_wrapper") == LEAN_VEC_ENV:
        del entry["vec_env_wrapper"]
    for key in ("env_wrapper", "frame_stack", "vec_env_wrapper"):
        if key in entry:
            raise ConfigError(f"{where}: {key!r} is not supported by the divmorph pipeline")
    policy_kwargs = entry.pop("policy_kwargs", {}) or {}
    if isinstance(policy_kwargs, str):
        policy_kwargs = _zoo_eval(policy_kwargs, where)
    normalize = entry.pop("normalize", None)
    if isinstance(normalize, str):
        normalize = _zoo_eval(normalize, where)
    elif normalize is True:
        normalize = {}
    elif normalize is False:
        normalize = None
    if "n_timesteps" not in entry:
        raise ConfigError(f"{where}: n_timesteps is required")
    ppo_kwargs = {k: v for k, v in entry.items() if k in _PPO_ARGS}
    for key in ("learning_rate", "clip_range"):
        if key in ppo_kwargs:
            ppo_kwargs[key] = _schedule(ppo_kwargs[key], f"{where} {key}")
    return ZooEntry(
        policy=str(entry.get("policy", "MetaMorphPolicy")),
        n_timesteps=int(float(entry["n_timesteps"])),
        n_envs=int(entry.get("n_envs", 1)),
        policy_kwargs=dict(policy_kwargs),
        normalize=normalize,
        ppo_kwargs=ppo_kwargs,
        callbacks=callbacks,
    )


def __getattr__(name: str) -> Any:
    # rl-zoo's ``--conf-file sb3_divmorph.zoo`` reads ``hyperparams``: the raw entries of ppo.yml,
    # exactly what rl-zoo gets from ``--conf-file zoo_configs/ppo.yml`` (read when first asked for).
    if name == "hyperparams":
        import yaml

        with open(config_file("ppo.yml")) as f:
            return yaml.safe_load(f)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
