"""Load a trained model with its observation statistics and roll it out.

    python examples/load_run_model.py runs/demo/teachers/FT          # a teacher of `make demo`
    python examples/load_run_model.py runs/demo/student --task Patrol
    python examples/load_run_model.py results/cpu100/teachers/Obstacle --robot mvt-5506-1-12-17-11-10-12 --seed 1 --steps 1000

Any folder holding ``model.zip`` and (when training normalised observations) ``vecnormalize.pkl``
works: the pipeline's ``teachers/<task>``, ``student``, ``transfer/<task>/<arm>/seed-<s>``, or the output of
``examples/distill_dagger.py``. The statistics must be loaded *with* the model: a policy fed
unnormalised observations acts on inputs it never saw. ``VecNormalize.load`` wraps the env;
``training = False`` freezes the statistics and ``norm_reward = False`` reports true returns.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.env_util import make_vec_env
from stable_baselines3.common.vec_env import VecNormalize

import sb3_divmorph  # noqa: F401  (policy aliases)
from sb3_divmorph.pipeline.runs import stage_model, stage_normalizer, trained_env_kwargs, trained_robots
import unimal_envs  # noqa: F401  (registers the Unimal-* ids)
from unimal_envs.contract import TASK_NAMES


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path, help="a run folder with model.zip (+ vecnormalize.pkl)")
    parser.add_argument("--task", default=None, help="task to run (default: the folder's name when it is a task, e.g. teachers/FT)")
    parser.add_argument(
        "--robots",
        type=int,
        default=2,
        help="first N robots the model was trained on (its run's robot_sets.json; else the train set), one episode each",
    )
    parser.add_argument("--robot", nargs="+", default=None, help="these robots of its training set, by name, instead of the first N")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first env (env i: seed + i; it lays out terrain and blocks)")
    parser.add_argument("--steps", type=int, default=200, help="longest episode")
    args = parser.parse_args(argv)
    th.set_num_threads(1)  # small models: a second thread only contends with the simulation

    task = args.task or args.folder.name
    if task not in TASK_NAMES:
        parser.error(f"cannot tell the task from {args.folder}; pass --task (one of {list(TASK_NAMES)})")
    try:  # a recorded run's model may have left the tree: the message says how to get it back
        model_file = stage_model(args.folder)
    except FileNotFoundError as error:
        parser.error(str(error))
    stats_file = stage_normalizer(args.folder)  # None: the model trained on raw observations

    # The robots the model was trained on, by default: a pipeline run records them (robot_sets.json);
    # a teacher run on other robots would look untrained.
    trained = trained_robots(args.folder)
    robots = trained if trained is not None else unimal_envs.morphology.loader.morphology_files("train")
    if args.robot:
        unknown = sorted(set(args.robot) - {r.stem for r in robots})
        if unknown:
            parser.error(f"not among the robots it was trained on: {unknown}")
        robots = [r for name in args.robot for r in robots if r.stem == name]
    else:
        robots = robots[: args.robots]
    print(f"robots: {[r.stem for r in robots]} ({'the ones it was trained on' if trained else 'the shipped train set'})")
    # and the observations it learnt on (a run may measure body heights above the ground, not the world)
    env_kwargs = dict(morphologies=robots, max_episode_steps=args.steps, **trained_env_kwargs(args.folder))
    venv = make_vec_env(f"Unimal-{task}-v0", n_envs=len(robots), seed=args.seed, env_kwargs=env_kwargs)
    if stats_file is not None:
        venv = VecNormalize.load(str(stats_file), venv)
        venv.training, venv.norm_reward = False, False
    else:
        print(f"{args.folder} has no vecnormalize.pkl: the model was trained on raw observations")
    model = PPO.load(model_file, env=venv, device="cpu")

    # one episode per env (each env holds one robot); VecMonitor-free bookkeeping of the returns
    obs = venv.reset()
    returns, lengths, finished = [0.0] * len(robots), [0] * len(robots), [False] * len(robots)
    while not all(finished):
        actions, _ = model.predict(obs, deterministic=True)
        obs, rewards, dones, _ = venv.step(actions)
        for i, (reward, done) in enumerate(zip(rewards, dones)):
            if not finished[i]:
                returns[i] += float(reward)
                lengths[i] += 1
                finished[i] = bool(done)
    for robot, total, length in zip(robots, returns, lengths):
        print(f"{model_file} on {task}, {robot.stem}: return {total:.1f} over {length} steps")


if __name__ == "__main__":
    main()
