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
from pathlib import Path
from typing import Any

#: The checkout this module sits in (used when the package is run from a source tree, not installed).
_SOURCE_TREE_CONFIGS = Path(__file__).resolve().parents[1] / "zoo_configs"


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
    :returns: a :class:`~sb3_divmorph.pipeline.config.ZooEntry` (``policy``, ``n_timesteps``,
        ``n_envs``, ``policy_kwargs``, ``normalize``, ``ppo_kwargs``, ``callbacks``).
    """
    from sb3_divmorph.pipeline.config import load_zoo_entry

    return load_zoo_entry(path or config_file("ppo.yml"), env_id, overrides)


def __getattr__(name: str) -> Any:
    # rl-zoo's ``--conf-file sb3_divmorph.zoo`` reads ``hyperparams``: the raw entries of ppo.yml,
    # exactly what rl-zoo gets from ``--conf-file zoo_configs/ppo.yml`` (read when first asked for).
    if name == "hyperparams":
        import yaml

        with open(config_file("ppo.yml")) as f:
            return yaml.safe_load(f)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
