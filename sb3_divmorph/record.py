"""Record a trained model (rl-zoo or divmorph pipeline) acting in a UNIMAL env, as an MP4, headless.

``rl_zoo3.record_video`` cannot import ``--gym-packages``, so it cannot build the Unimal envs;
this is the replacement::

    divmorph record logs/ppo/Unimal-FT-v0_1                 # an rl-zoo run folder (env and algo from its name)
    divmorph record runs/demo/teachers/FT                   # a pipeline stage folder (task from the layout)
    divmorph record runs/demo/student --task Patrol --robot train-003 --episodes 2
    python -m sb3_divmorph.record runs/demo/transfer/Escape/divmorph --out escape.mp4

A model is looked up as ``model.zip`` in a pipeline folder or ``<env id>.zip`` (else
``best_model.zip``) in an rl-zoo folder, with its observation statistics (``vecnormalize.pkl``
next to it, or ``<env id>/vecnormalize.pkl`` for rl-zoo): a run saved with statistics is always
recorded with them, and an rl-zoo run whose ``config.yml`` says it normalised observations but has
no statistics file is refused. Frames come from ``render_mode="rgb_array"`` (``MUJOCO_GL=egl``, no
display needed) and are encoded with imageio/ffmpeg at 50 frames per second (real time).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

NORMALIZER = "vecnormalize.pkl"
#: ``Unimal-FT-v0_3`` (rl-zoo's ``<env id>_<run>`` folder names)
_ZOO_RUN = re.compile(r"^(?P<env>Unimal-[A-Za-z]+-v\d+)_\d+$")
ALGOS = ("ppo", "a2c")


class RecordError(ValueError):
    """The model, its statistics or the requested env cannot be found or do not fit together."""


@dataclass
class SavedModel:
    """Where a trained model and its statistics are, and what they were trained on.

    :param model: the ``.zip`` file.
    :param normalizer: its ``VecNormalize`` statistics (``None``: trained on raw observations).
    :param env_id: the env it was trained on, when the layout tells (``None`` otherwise).
    :param algo: ``ppo`` or ``a2c``, when the layout tells.
    """

    model: Path
    normalizer: Path | None
    env_id: str | None
    algo: str | None


def _zoo_normalizes(config: Path) -> bool:
    """Whether an rl-zoo run's saved ``config.yml`` turned observation normalisation on."""
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    # rl-zoo dumps an OrderedDict of [key, value] pairs; read it without unsafe YAML tags
    Loader.add_constructor(
        "tag:yaml.org,2002:python/object/apply:collections.OrderedDict",
        lambda loader, node: dict(loader.construct_sequence(node.value[0], deep=True) if node.value else []),
    )
    with open(config) as f:
        values = yaml.load(f, Loader=Loader) or {}  # noqa: S506 (a SafeLoader subclass)
    normalize = dict(values).get("normalize", False)
    if isinstance(normalize, str):
        return "norm_obs=False" not in normalize.replace(" ", "")
    return bool(normalize)


def find_model(source: str | Path) -> SavedModel:
    """Locate the model, its statistics, env and algorithm from a file or folder.

    :param source: a ``.zip`` model, a pipeline stage folder (``model.zip``) or an rl-zoo run
        folder (``logs/<algo>/<env id>_<n>``).
    :raises RecordError: nothing recordable there, or statistics announced but missing.
    """
    from unimal_envs.contract import TASK_NAMES

    source = Path(source)
    if not source.exists():
        raise RecordError(f"no such file or directory: {source}")
    if source.is_dir():
        zoo = _ZOO_RUN.match(source.name)
        if (source / "model.zip").is_file():  # divmorph pipeline layout
            model = source / "model.zip"
        elif zoo and (source / f"{zoo['env']}.zip").is_file():
            model = source / f"{zoo['env']}.zip"
        elif zoo and (source / "best_model.zip").is_file():
            model = source / "best_model.zip"
        else:
            raise RecordError(
                f"{source} holds no model.zip (divmorph run) nor <env id>.zip (rl-zoo run folder such as logs/ppo/Unimal-FT-v0_1)"
            )
    elif source.suffix == ".zip":
        model = source
    else:
        raise RecordError(f"{source} is neither a .zip model nor a run folder")

    folder = model.parent
    zoo = _ZOO_RUN.match(folder.name)
    if zoo:
        env_id = zoo["env"]
        stats = folder / env_id / NORMALIZER
        config = folder / env_id / "config.yml"
        algo = folder.parent.name if folder.parent.name in ALGOS else None
        if not stats.is_file():
            if config.is_file() and _zoo_normalizes(config):
                raise RecordError(f"{config} says the model was trained with normalised observations, but {stats} is missing")
            stats = None
        return SavedModel(model, stats, env_id, algo)

    # divmorph pipeline: teachers/<task>, transfer/<task>/<arm>, student (multi-task: no single task)
    task = next((name for name in (folder.name, folder.parent.name) if name in TASK_NAMES), None)
    stats = folder / NORMALIZER
    return SavedModel(model, stats if stats.is_file() else None, f"Unimal-{task}-v0" if task else None, None)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``record`` arguments (shared by ``divmorph record`` and ``python -m sb3_divmorph.record``)."""
    parser.add_argument(
        "source", help="model .zip, divmorph stage folder (runs/demo/teachers/FT) or rl-zoo run folder (logs/ppo/Unimal-FT-v0_1)"
    )
    parser.add_argument("--task", help="task to record (default: the one the model was trained on, when its folder tells)")
    parser.add_argument("--algo", choices=ALGOS, help="algorithm the model was saved by (default: from the rl-zoo folder, else ppo)")
    parser.add_argument("--normalizer", help="VecNormalize statistics (default: the ones saved with the model)")
    parser.add_argument(
        "--morphologies",
        default=None,
        help="robot set, directory or .xml file (default: the robots the model was trained on, from its run's robot_sets.json; else train)",
    )
    parser.add_argument("--robot", action="append", help="robot name in that set (repeatable; default: the first ones, one per episode)")
    parser.add_argument("--episodes", type=int, default=1, help="episodes to record, one after the other (default: 1)")
    parser.add_argument("--steps", type=int, default=1000, help="longest episode, in steps of 0.02 s (default: 1000)")
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of taking the mean")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument(
        "--out",
        help="MP4 file, or GIF when it ends in .gif (default: videos/<model folder>-<env id>.mp4 in "
        "the current folder, never inside the model's folder)",
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def record(args: argparse.Namespace) -> Path:
    """Record ``args.episodes`` episodes of the model named by ``args.source``; returns the MP4 path.

    :raises RecordError: see :func:`find_model`; also an unknown task or a model whose observation
        space is not the env's.
    """
    import gymnasium as gym
    from stable_baselines3 import A2C, PPO
    from tqdm import tqdm

    import sb3_divmorph  # noqa: F401  (the policy aliases, for models saved with them)
    import unimal_envs  # noqa: F401  (registers the Unimal-* ids)
    from sb3_divmorph.distillation import check_spaces, load_normalizer
    from unimal_envs.contract import TASK_NAMES
    from unimal_envs.rendering import episode_frames, write_video

    if args.episodes < 1 or args.steps < 1:
        raise RecordError(f"--episodes and --steps must be at least 1, got {args.episodes} and {args.steps}")
    if args.out and Path(args.out).suffix.lower() not in (".mp4", ".gif"):
        raise RecordError(f"--out {args.out}: the video's file name must end in .mp4 or .gif")
    saved = find_model(args.source)
    if args.task is not None:
        if args.task not in TASK_NAMES:
            raise RecordError(f"unknown task {args.task!r}; choose from {list(TASK_NAMES)}")
        env_id = f"Unimal-{args.task}-v0"
    elif saved.env_id is not None:
        env_id = saved.env_id
    else:
        raise RecordError(f"cannot tell which task {saved.model} was trained on; pass --task (one of {list(TASK_NAMES)})")
    normalizer_file = Path(args.normalizer) if args.normalizer else saved.normalizer
    if normalizer_file is not None and not normalizer_file.is_file():
        raise RecordError(f"no such statistics file: {normalizer_file}")

    morphologies = args.morphologies
    if morphologies is None:  # the model's own robots: a teacher run on other robots would look untrained
        from sb3_divmorph.pipeline.runs import trained_robots

        morphologies = trained_robots(saved.model) or "train"
    from sb3_divmorph.pipeline.runs import trained_env_kwargs

    env = gym.make(
        env_id,
        morphologies=morphologies,
        render_mode="rgb_array",
        width=args.width,
        height=args.height,
        max_episode_steps=args.steps,
        **trained_env_kwargs(saved.model),
    )
    robots = [m.name for m in env.unwrapped.morphologies]
    unknown = sorted(set(args.robot or []) - set(robots))
    if unknown:
        env.close()
        raise RecordError(f"robot(s) {unknown} not among the robots recorded from (e.g. {robots[:3]})")
    chosen = args.robot or robots

    algo = {"ppo": PPO, "a2c": A2C}[args.algo or saved.algo or "ppo"]
    model = algo.load(saved.model, device="cpu")
    check_spaces(f"model {saved.model}", model.observation_space, env.observation_space)
    normalizer = load_normalizer(normalizer_file) if normalizer_file is not None else None
    if normalizer is None:
        print(f"[record] {saved.model}: no statistics saved with it, observations go to the model unnormalised")

    def policy(obs):
        action, _ = model.predict(obs if normalizer is None else normalizer.normalize_obs(obs), deterministic=not args.stochastic)
        return action

    out = Path(args.out) if args.out else Path("videos") / f"{saved.model.parent.name}-{env_id}.mp4"
    count = 0

    def frames():  # streamed to the encoder: memory stays flat however long the video
        nonlocal count
        for episode in tqdm(range(args.episodes), desc="[record]", unit="episode", disable=args.no_progress):
            robot = chosen[episode % len(chosen)]
            outcome: dict = {}
            for frame in episode_frames(
                env, policy, steps=args.steps, seed=args.seed + episode, options={"morphology": robot}, outcome=outcome
            ):
                count += 1
                yield frame
            print(f"[record] episode {episode}: {robot}, {outcome['steps']} steps, return {outcome['return']:.1f}")

    try:
        write_video(frames(), out, fps=env.metadata.get("render_fps", 50))
    finally:
        env.close()
    print(f"[record] {count} frames of {env_id} -> {out}")
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m sb3_divmorph.record``: same arguments as ``divmorph record``."""
    parser = argparse.ArgumentParser(
        prog="python -m sb3_divmorph.record", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add_arguments(parser)
    return run(parser.parse_args(argv))


def run(args: argparse.Namespace) -> int:
    """:func:`record` with errors printed as one line on stderr; returns the exit code (0 or 2)."""
    try:
        record(args)
    except (ValueError, FileNotFoundError) as error:  # RecordError, a space mismatch, a bad robot set
        print(f"record: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
