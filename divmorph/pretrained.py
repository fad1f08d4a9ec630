"""A trained model in one call: the model, its observation statistics, its robots and env settings.

A model is only as good as the observations it is fed: the statistics it was normalised with, the
robots it learnt on and the env settings of its run (a model trained with heights above the ground,
``height_reference="ground"``, fed the default sees heights it never learnt on and does far worse).
:func:`load_pretrained` reads all of it from where the project and rl-zoo save it::

    from divmorph.pretrained import load_pretrained

    teacher = load_pretrained("results/cpu100/teachers/FT")
    for row in teacher.evaluate(robots=teacher.robots[:3]):          # one env per robot, in order
        print(row["robot"], row["return"], row["length"])
    env = teacher.make_env("floor-1409-0-12-01-12-30-07")            # a Gymnasium env with its settings
    obs, _ = env.reset(seed=0)
    action = teacher.predict(obs)                                     # statistics applied

Where things are looked up (:func:`find_model`): ``model.zip`` in a pipeline stage folder (its
statistics ``vecnormalize.pkl`` and its env settings and robots ``env.json`` beside it, written from
its envs when it was saved; for models saved before, the run's ``robot_sets.json`` / ``run.json``), or ``<env id>.zip`` (else ``best_model.zip``) in an rl-zoo run
folder ``logs/<algo>/<env id>_<n>`` (statistics in ``<env id>/vecnormalize.pkl``, env settings from
``<env id>/args.yml``'s ``env_kwargs``). Giving an env setting other than the one the model
trained with warns, naming the setting: it is allowed (a study may want it), never silent.
"""

from __future__ import annotations

import json
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

NORMALIZER = "vecnormalize.pkl"
#: ``Unimal-FT-v0_3`` (rl-zoo's ``<env id>_<run>`` folder names)
_ZOO_RUN = re.compile(r"^(?P<env>Unimal-[A-Za-z]+-v\d+)_\d+$")
ALGOS = ("ppo", "a2c")


class PretrainedError(ValueError):
    """The model, its statistics or the requested env cannot be found or do not fit together."""


@dataclass
class SavedModel:
    """Where a trained model and its statistics are, and what they were trained on.

    :param model: the ``.zip`` file.
    :param normalizer: its ``VecNormalize`` statistics (``None``: trained on raw observations).
    :param env_id: the env it was trained on, when the layout tells (``None`` otherwise).
    :param algo: ``ppo`` or ``a2c``, when the layout tells.
    :param env_kwargs: the env arguments its run made its envs with (rl-zoo's ``env_kwargs``, the
        pipeline's env settings); its robots are under ``morphologies`` when the run records them,
        and the instruction a transfer run gave it (another task's, or its own in other words) under
        ``instruction``.
    """

    model: Path
    normalizer: Path | None
    env_id: str | None
    algo: str | None
    env_kwargs: dict[str, Any] = field(default_factory=dict)

    def env_settings(self, env_id: str) -> dict[str, Any]:
        """``env_kwargs`` for running the model on ``env_id``: its recorded instruction belongs to the
        task it trained on, so on another task that task's own instruction is used."""
        if env_id == self.env_id:
            return dict(self.env_kwargs)
        return {key: value for key, value in self.env_kwargs.items() if key != "instruction"}


def _read_zoo_yaml(path: Path) -> dict[str, Any]:
    """An rl-zoo ``config.yml`` / ``args.yml`` (an OrderedDict dumped as YAML), read without unsafe tags."""
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    Loader.add_constructor(
        "tag:yaml.org,2002:python/object/apply:collections.OrderedDict",
        lambda loader, node: dict(loader.construct_sequence(node.value[0], deep=True) if node.value else []),
    )
    with open(path) as f:
        values = yaml.load(f, Loader=Loader) or {}  # noqa: S506 (a SafeLoader subclass)
    return dict(values)


def _zoo_normalizes(config: Path) -> bool:
    """Whether an rl-zoo run's saved ``config.yml`` turned observation normalisation on."""
    normalize = _read_zoo_yaml(config).get("normalize", False)
    if isinstance(normalize, str):
        return "norm_obs=False" not in normalize.replace(" ", "")
    return bool(normalize)


def find_model(source: str | Path) -> SavedModel:
    """Locate the model, its statistics, env, algorithm and env settings from a file or folder.

    :param source: a ``.zip`` model, a pipeline stage folder (``model.zip``) or an rl-zoo run
        folder (``logs/<algo>/<env id>_<n>``).
    :raises PretrainedError: nothing loadable there, or statistics announced but missing.
    """
    from unimal_envs.contract import TASK_NAMES

    from divmorph.shipped import cached_path, fetch_command, shipped_run_of

    source = Path(source)
    if not source.exists():
        # a shipped run's path where there is no checkout (a pip install): its fetched copy
        fetched = cached_path(source)
        if fetched is None:
            run = shipped_run_of(source)
            hint = f"; the shipped models of {run} are not in this install: fetch them once with `{fetch_command(run)}`" if run else ""
            raise PretrainedError(f"no such file or directory: {source}{hint}")
        source = fetched
    if source.is_dir():
        zoo = _ZOO_RUN.match(source.name)
        if (source / "model.zip").is_file():  # divmorph pipeline layout
            model = source / "model.zip"
        elif zoo and (source / f"{zoo['env']}.zip").is_file():
            model = source / f"{zoo['env']}.zip"
        elif zoo and (source / "best_model.zip").is_file():
            model = source / "best_model.zip"
        else:
            raise PretrainedError(
                f"{source} holds no model.zip (divmorph run) nor <env id>.zip (rl-zoo run folder such as logs/ppo/Unimal-FT-v0_1)"
            )
    elif source.suffix == ".zip":
        model = source
    else:
        raise PretrainedError(f"{source} is neither a .zip model nor a run folder")

    folder = model.parent
    zoo = _ZOO_RUN.match(folder.name)
    if zoo:
        env_id = zoo["env"]
        stats: Path | None = folder / env_id / NORMALIZER
        config = folder / env_id / "config.yml"
        args = folder / env_id / "args.yml"
        algo = folder.parent.name if folder.parent.name in ALGOS else None
        if not stats.is_file():  # type: ignore[union-attr]
            if config.is_file() and _zoo_normalizes(config):
                raise PretrainedError(f"{config} says the model was trained with normalised observations, but {stats} is missing")
            stats = None
        env_kwargs = (_read_zoo_yaml(args).get("env_kwargs") or {}) if args.is_file() else {}
        return SavedModel(model, stats, env_id, algo, dict(env_kwargs))

    # divmorph pipeline: teachers/<task>, transfer/<task>/<arm>, student (multi-task: no single task)
    from divmorph.pipeline.files import ENV_SETTINGS
    from divmorph.pipeline.robots import trained_env_kwargs, trained_instruction, trained_robots
    from unimal_envs import env_id as unimal_env_id

    # teachers/<task>, transfer/<task>/<arm>, transfer/<task>/<arm>/seed-<n>
    names = (folder.name, folder.parent.name, *((folder.parent.parent.name,) if folder.name.startswith("seed-") else ()))
    task = next((name for name in names if name in TASK_NAMES), None)
    normalizer = folder / NORMALIZER
    env_kwargs = dict(trained_env_kwargs(folder))
    robots = trained_robots(folder)
    saved = json.loads((folder / ENV_SETTINGS).read_text()) if (folder / ENV_SETTINGS).is_file() else {}
    if saved:  # the settings saved beside the model win over its run's records, which must agree
        if robots is not None and [r.stem for r in robots] != saved["robots"]:
            warnings.warn(f"{folder}: its run's robot_sets.json names other robots than {ENV_SETTINGS}; using {ENV_SETTINGS}", stacklevel=2)
            robots = None
        if saved["height_reference"] != env_kwargs.get("height_reference", "world"):
            warnings.warn(
                f"{folder}: its run's run.json and {ENV_SETTINGS} disagree on height_reference; using {ENV_SETTINGS}", stacklevel=2
            )
        env_kwargs.pop("height_reference", None)
        if saved["height_reference"] != "world":
            env_kwargs["height_reference"] = saved["height_reference"]
        if robots is None:
            robots = saved["robots"]  # by name: the shipped and official sets on this machine
    if robots is not None:
        env_kwargs["morphologies"] = robots
    instruction = trained_instruction(folder, task)
    if instruction is not None:  # a transfer run told another task's instruction, or one in other words
        env_kwargs["instruction"] = instruction
    return SavedModel(model, normalizer if normalizer.is_file() else None, unimal_env_id(task) if task else None, None, env_kwargs)


@dataclass
class Pretrained:
    """A loaded model with everything it needs to act as it learnt to (see the module docstring).

    :param saved: where it came from (:class:`SavedModel`).
    :param model: the SB3 algorithm (``model.policy`` is the network).
    :param normalizer: its frozen observation statistics (a ``VecNormalize``), or ``None``.
    """

    saved: SavedModel
    model: Any
    normalizer: Any = None

    @property
    def env_id(self) -> str | None:
        """The env it was trained on (``None`` for a multi-task student: pass ``task``)."""
        return self.saved.env_id

    @property
    def robots(self) -> list[Path]:
        """The robots it was trained on (the shipped ``train`` set when its run does not say)."""
        from unimal_envs.morphology.loader import morphology_files

        return morphology_files(self.saved.env_kwargs.get("morphologies", "train"))

    @property
    def env_kwargs(self) -> dict[str, Any]:
        """The env settings it was trained with, its robots aside."""
        return {k: v for k, v in self.saved.env_kwargs.items() if k != "morphologies"}

    def _env_id(self, task: str | None) -> str:
        from unimal_envs.contract import TASK_NAMES

        if task is not None:
            if task not in TASK_NAMES:
                raise PretrainedError(f"unknown task {task!r}; choose from {list(TASK_NAMES)}")
            from unimal_envs import env_id as unimal_env_id

            return unimal_env_id(task)
        if self.env_id is None:
            raise PretrainedError(f"cannot tell which task {self.saved.model} was trained on; pass task= (one of {list(TASK_NAMES)})")
        return self.env_id

    def _settings(self, overrides: dict[str, Any], env_id: str) -> dict[str, Any]:
        settings = {key: value for key, value in self.saved.env_settings(env_id).items() if key != "morphologies"}
        for key, value in overrides.items():
            if key in settings and settings[key] != value:
                warnings.warn(
                    f"{self.saved.model} was trained with {key}={settings[key]!r}; running it with {key}={value!r} "
                    "feeds it observations it did not learn on",
                    stacklevel=3,
                )
            settings[key] = value
        return settings

    def _robot_files(self, robots: Any) -> list[Path]:
        from unimal_envs.morphology.loader import is_set_name, morphology_files

        if robots is None:
            return self.robots
        if isinstance(robots, (str, Path)) and not is_set_name(robots) and not Path(robots).is_dir():
            robots = [robots]  # one robot, by name or file
        return morphology_files(robots)

    def best_robots(self, task: str | None = None, n: int = 5, split: str = "train") -> list[tuple[str, float]]:
        """The robots this model does best on by its run's evaluation (see :func:`best_robots`)."""
        return best_robots(self.saved, self._env_id(task), n, split)

    def make_env(self, robots: Any = None, task: str | None = None, **env_kwargs: Any) -> gym.Env:
        """A Gymnasium env with the model's settings (warns on an override of one of them).

        :param robots: a robot name, file, set or list (default: the robots it was trained on).
        :param task: the task (default: the one it was trained on).
        :param env_kwargs: further ``gym.make`` arguments (``max_episode_steps``, ``render_mode``...).
        """
        import unimal_envs  # noqa: F401  (registers the Unimal-* ids)

        env_id = self._env_id(task)
        return gym.make(env_id, morphologies=self._robot_files(robots), **self._settings(env_kwargs, env_id))

    def predict(self, obs: dict[str, np.ndarray], deterministic: bool = True) -> np.ndarray:
        """The model's action for a (single or batched) observation, its statistics applied."""
        if self.normalizer is not None:
            obs = self.normalizer.normalize_obs(obs)
        action, _ = self.model.predict(obs, deterministic=deterministic)
        return action

    def evaluate(
        self,
        robots: Any = None,
        task: str | None = None,
        episodes: int = 1,
        seed: int = 0,
        max_episode_steps: int = 1000,
        deterministic: bool = True,
        **env_kwargs: Any,
    ) -> list[dict[str, Any]]:
        """Episode returns on each robot, named by the robot that ran: one env per robot, stepped
        together, ``episodes`` each (a seed gives the same episodes on every call).

        :returns: ``[{"robot", "episode", "return", "length"}]`` in the order asked: robot by robot as
            given, each robot's episodes in order.
        :raises PretrainedError: ``episodes`` < 1, an unknown task, or no task to tell.
        """
        from divmorph.pipeline.curves import robot_venv, rollout_returns

        if episodes < 1:
            raise PretrainedError(f"episodes must be at least 1, got {episodes}")
        files = self._robot_files(robots)
        env_id = self._env_id(task)
        venv = robot_venv(env_id, files, max_episode_steps, seed, **self._settings(env_kwargs, env_id))
        try:
            normalize = self.normalizer.normalize_obs if self.normalizer is not None else None
            return rollout_returns(self.model, venv, files, episodes, normalize, deterministic=deterministic)
        finally:
            venv.close()


def best_robots(saved: SavedModel, env_id: str, n: int = 5, split: str = "train") -> list[tuple[str, float]]:
    """The robots a model does best on, by its run's evaluation (``evaluate/returns.csv``):
    ``[(robot, mean return over its episodes)]``, best first.

    Chosen on the training robots by default: a showcase picked on held-out robots would be a
    choice made on the test set.

    :param env_id: the task's env id (``Unimal-FT-v0``).
    :param split: ``train``, ``novel`` or ``ood``.
    :raises PretrainedError: the model is not a stage of an evaluated run, or the evaluation has no rows for it.
    """
    from divmorph.pipeline.files import log_file, read_csv_rows
    from divmorph.pipeline.folders import evaluation_label

    task = env_id.split("-")[1]
    found = evaluation_label(saved.model.parent)
    if found is None:
        raise PretrainedError(f"{saved.model.parent} is not a stage of a pipeline run: no evaluation to choose robots from")
    run, label, seed = found
    path = run / "evaluate" / "returns.csv"
    recorded = log_file(path)
    if recorded is None:
        raise PretrainedError(f"{run} has no evaluation ({path}); run `divmorph evaluate --run {run}` first")
    means = robot_means(read_csv_rows(recorded), label, task, split, seed)
    if not means:
        raise PretrainedError(f"{recorded} has no {split} rows of {label} on {task}")
    return means[:n]


def robot_means(
    rows: list[dict[str, str]], model: str, task: str, split: str = "train", seed: int | None = None
) -> list[tuple[str, float]]:
    """Each robot's mean return of one model on one task and split, from the rows of an evaluation's
    ``returns.csv`` (:func:`divmorph.pipeline.files.read_csv_rows`): ``[(robot, mean)]``, best first
    (``seed``: one transfer run's rows only; a robot's ties keep the file's order)."""
    returns: dict[str, list[float]] = {}
    for row in rows:
        if row["model"] != model or row["task"] != task or row["split"] != split:
            continue
        if seed is not None and "seed" in row and (row["seed"] == "" or int(float(row["seed"])) != seed):
            continue
        returns.setdefault(row["morphology"], []).append(float(row["return"]))
    means = [(robot, float(np.mean(values))) for robot, values in returns.items()]
    return sorted(means, key=lambda pair: -pair[1])


def check_archive(model: Path) -> None:
    """Refuse, by name, a model file that is not a whole SB3 archive (see :func:`sb3_divmorph.saved_model.check_archive`).

    :raises PretrainedError: not a readable zip, or a zip without SB3's ``data`` entry.
    """
    from sb3_divmorph.saved_model import SavedModelError
    from sb3_divmorph.saved_model import check_archive as check

    try:
        check(model)
    except SavedModelError as error:
        raise PretrainedError(str(error)) from None


def load_pretrained(source: str | Path, device: str = "cpu", algo: str | None = None) -> Pretrained:
    """Load a trained model with its statistics, robots and env settings (see the module docstring).

    :param source: a pipeline stage folder (``results/cpu100/teachers/FT``), an rl-zoo run folder,
        or a ``.zip``.
    :param device: where the network runs.
    :param algo: ``ppo`` or ``a2c`` (default: from the rl-zoo folder, else ppo).
    :raises PretrainedError: see :func:`find_model`; also a truncated or corrupt model file.
    """
    from sb3_divmorph.saved_model import SavedModelError, load_model

    saved = find_model(source)
    name = algo or saved.algo or "ppo"
    if name not in ALGOS:
        raise PretrainedError(f"unknown algorithm {name!r}; choose from {list(ALGOS)}")
    try:  # load_model checks the archive once, before SB3 reads it
        loaded = load_model(saved.model, saved.normalizer, device=device, algo=name)
    except SavedModelError as error:
        raise PretrainedError(str(error)) from None
    return Pretrained(saved, loaded.model, loaded.normalizer)
