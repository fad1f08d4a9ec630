"""Record a trained model (rl-zoo or divmorph pipeline) acting in a UNIMAL env, as an MP4, headless.

``rl_zoo3.record_video`` cannot import ``--gym-packages``, so it cannot build the Unimal envs;
this is the replacement::

    divmorph record logs/ppo/Unimal-FT-v0_1                 # an rl-zoo run folder (env and algo from its name)
    divmorph record runs/demo/teachers/FT                   # a pipeline stage folder (task from the layout)
    divmorph record runs/demo/student --task Patrol --robot train-003 --episodes 2
    python -m divmorph.record runs/demo/transfer/Escape/divmorph --out escape.mp4

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
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

# Where a model and its statistics are, and what it was trained on: shared with load_pretrained.
from divmorph.pretrained import (  # noqa: E402, F401 -- re-exported (find_model, SavedModel were defined here)
    ALGOS,
    NORMALIZER,
    PretrainedError,
    SavedModel,
    best_robots,
    check_archive,
    find_model,
)

#: The errors of ``record`` (a model that cannot be found, an unknown task...): those of :mod:`divmorph.pretrained`.
RecordError = PretrainedError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``record`` arguments (shared by ``divmorph record`` and ``python -m divmorph.record``)."""
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
    parser.add_argument(
        "--robot",
        action="append",
        help="robot name in that set (repeatable, one per episode in turn; default: the robot the model does best on by "
        "its run's evaluation, else the first, said on stderr); 'best': that robot, or an error where there is no evaluation",
    )
    parser.add_argument("--episodes", type=int, default=1, help="episodes to record, one after the other (default: 1)")
    parser.add_argument("--steps", type=int, default=1000, help="longest episode, in steps of 0.02 s (default: 1000)")
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of taking the mean")
    parser.add_argument(
        "--seed",
        type=int,
        default=0,
        help="episode e of a robot is reset with episode_seed(SEED, robot, e): the episode `divmorph evaluate` plays under the same seed",
    )
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
    from unimal_envs import env_id as unimal_env_id  # (importing unimal_envs registers the Unimal-* ids)
    from sb3_divmorph.algos.distillation import check_spaces, load_normalizer
    from divmorph.pipeline.curves import episode_seed
    from unimal_envs.contract import TASK_NAMES
    from unimal_envs.rendering import GIF_FPS, episode_frames, frames_kept, write_video

    if args.episodes < 1 or args.steps < 1:
        raise RecordError(f"--episodes and --steps must be at least 1, got {args.episodes} and {args.steps}")
    if args.out and Path(args.out).suffix.lower() not in (".mp4", ".gif"):
        raise RecordError(f"--out {args.out}: the video's file name must end in .mp4 or .gif")
    saved = find_model(args.source)
    check_archive(saved.model)
    if args.task is not None:
        if args.task not in TASK_NAMES:
            raise RecordError(f"unknown task {args.task!r}; choose from {list(TASK_NAMES)}")
        env_id = unimal_env_id(args.task)
    elif saved.env_id is not None:
        env_id = saved.env_id
    else:
        raise RecordError(f"cannot tell which task {saved.model} was trained on; pass --task (one of {list(TASK_NAMES)})")
    normalizer_file = Path(args.normalizer) if args.normalizer else saved.normalizer
    if normalizer_file is not None and not normalizer_file.is_file():
        raise RecordError(f"no such statistics file: {normalizer_file}")

    if args.robot == ["best"]:  # chosen on the training robots, by the run's recorded evaluation
        (best, mean), *_ = best_robots(saved, env_id, n=1)
        print(f"[record] best training robot of {saved.model.parent} on {env_id} by its run's evaluation: {best} (mean return {mean:.1f})")
        args.robot = [best]

    # the model's own robots and env settings (a pipeline run's records, an rl-zoo run's env_kwargs):
    # a teacher filmed on other robots, or fed other observations, would look untrained
    settings = saved.env_settings(env_id)
    trained_on = settings.pop("morphologies", None)
    morphologies = args.morphologies if args.morphologies is not None else (trained_on or "train")
    for key in ("render_mode", "width", "height", "max_episode_steps"):
        settings.pop(key, None)  # the recording's own
    env = gym.make(
        env_id,
        morphologies=morphologies,
        render_mode="rgb_array",
        width=args.width,
        height=args.height,
        max_episode_steps=args.steps,
        **settings,
    )
    robots = [m.name for m in env.unwrapped.morphologies]  # type: ignore[attr-defined]  # a UnimalEnv
    unknown = sorted(set(args.robot or []) - set(robots))
    if unknown:
        env.close()
        raise RecordError(f"robot(s) {unknown} not among the robots recorded from (e.g. {robots[:3]})")
    chosen = args.robot or [default_robot(saved, env_id, robots, args.morphologies is None)]

    algo = A2C if (args.algo or saved.algo) == "a2c" else PPO
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
            # the project's seeding rule (episode_seed): this robot's e-th episode is the one
            # `divmorph evaluate` and load_pretrained(...).evaluate play under the same seed
            reset_seed = episode_seed(args.seed, robot, episode // len(chosen))
            for frame in episode_frames(env, policy, steps=args.steps, seed=reset_seed, options={"morphology": robot}, outcome=outcome):
                count += 1
                yield frame
            print(f"[record] episode {episode}: {robot}, {outcome['steps']} steps, return {outcome['return']:.1f}")

    fps = env.metadata.get("render_fps", 50)
    try:
        write_video(frames(), out, fps=fps)
    finally:
        env.close()
    kept = frames_kept(count, out, fps)
    held = f"{kept} frames" if kept == count else f"{kept} frames (of {count} simulated: a GIF plays {GIF_FPS} per second, still real time)"
    print(f"[record] {held} of {env_id} -> {out}")
    return out


def default_robot(saved: SavedModel, env_id: str, robots: list[str], own_robots: bool) -> str:
    """The robot filmed when none is asked for: among the model's own robots, the one it does best on
    by its run's evaluation; otherwise the first, said loudly (an unchosen robot may simply fall)."""
    if own_robots:
        try:
            (best, mean), *_ = best_robots(saved, env_id, n=1)
        except PretrainedError as error:
            reason = str(error)
        else:
            if best in robots:
                print(
                    f"[record] no --robot: filming {best}, the robot {saved.model.parent} does best on {env_id} by its run's evaluation (mean return {mean:.1f})"
                )
                return best
            reason = f"its best robot {best} is not among the robots recorded from"
    else:
        reason = "--morphologies names other robots than the model's evaluation"
    print(
        f"[record] no --robot: filming the first robot, {robots[0]}, which need not be one the model does well on ({reason}); "
        "pass --robot NAME or --robot best",
        file=sys.stderr,
    )
    return robots[0]


def main(argv: list[str] | None = None) -> int:
    """``python -m divmorph.record``: same arguments as ``divmorph record``."""
    parser = argparse.ArgumentParser(
        prog="python -m divmorph.record", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
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
