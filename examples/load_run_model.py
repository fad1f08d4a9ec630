"""Load a trained model with its observation statistics, robots and env settings, and roll it out.

    python examples/load_run_model.py results/cpu100/teachers/FT            # a shipped 100-robot teacher
    python examples/load_run_model.py runs/demo/student --task Patrol        # a student of `make demo`
    python examples/load_run_model.py results/cpu100/teachers/Obstacle --robot mvt-5506-1-12-17-11-10-12 --episodes 3

Any folder holding ``model.zip`` and (when training normalised observations) ``vecnormalize.pkl``
works: the pipeline's ``teachers/<task>``, ``student``, ``transfer/<task>/<arm>/seed-<s>``, the
output of ``examples/distill_dagger.py``, or an rl-zoo run folder. ``load_pretrained`` loads the
statistics *with* the model (a policy fed unnormalised observations acts on inputs it never saw),
and the robots and env settings of its run. Each robot gets an env of its own, so every line
names the robot that ran; a seed gives the same episodes every time.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch as th

from divmorph.pretrained import PretrainedError, load_pretrained
from unimal_envs.contract import TASK_NAMES


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path, help="a run folder with model.zip (+ vecnormalize.pkl), or an rl-zoo run folder")
    parser.add_argument("--task", default=None, choices=TASK_NAMES, help="task to run (default: the one it was trained on)")
    parser.add_argument(
        "--robots", type=int, default=4, help="N of the robots it was trained on, spread over their sorted list (default 4)"
    )
    parser.add_argument("--robot", nargs="+", default=None, help="these robots, by name, instead")
    parser.add_argument("--episodes", type=int, default=1, help="episodes per robot (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the episodes (default 0)")
    parser.add_argument("--steps", type=int, default=1000, help="longest episode (default 1000, the tasks' length)")
    args = parser.parse_args(argv)
    if args.robots < 1 or args.episodes < 1 or args.steps < 1:
        parser.error("--robots, --episodes and --steps must be at least 1")
    th.set_num_threads(1)  # small models: a second thread only contends with the simulation

    try:
        model = load_pretrained(args.folder)
        trained = model.robots
        if args.robot:
            unknown = sorted(set(args.robot) - {r.stem for r in trained})
            if unknown:
                print(f"note: {unknown} are not among the robots it was trained on")
            robots = args.robot
        else:  # spread over the sorted list: its head is one family of robots only
            robots = [trained[i] for i in np.linspace(0, len(trained) - 1, min(args.robots, len(trained))).round().astype(int)]
        rows = model.evaluate(robots, task=args.task, episodes=args.episodes, seed=args.seed, max_episode_steps=args.steps)
    except (PretrainedError, FileNotFoundError) as error:
        parser.error(str(error))
    settings = ", ".join(f"{k}={v!r}" for k, v in model.env_kwargs.items()) or "the env defaults"
    print(f"{model.saved.model} on {args.task or model.env_id} ({settings}), {args.episodes} episode(s) per robot, seed {args.seed}:")
    for row in sorted(rows, key=lambda r: (r["robot"], r["episode"])):
        print(f"  {row['robot']}, episode {row['episode']}: return {row['return']:.1f} over {row['length']} steps")
    print(f"mean return {np.mean([r['return'] for r in rows]):.1f} over {len(rows)} episodes")


if __name__ == "__main__":
    main()
