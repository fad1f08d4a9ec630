"""Export a student as a pruned compact actor for one robot and task (ONNX and TorchScript).

    python examples/export_actor.py runs/demo/student --task FT --out exported   # first robot it was trained on

``CompactActor.from_policy`` evaluates the gates once for this robot and task, prunes the tailors
they switch off, merges the rest of every layer, folds what is constant for the robot (context,
position embedding, padded tokens, encoders of observations the task lacks) and bakes in the
observation statistics, so the exported actor takes the env's *raw* observations. The example
checks the ONNX file, run by ``OnnxActor`` (onnxruntime + numpy only), against the student.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch as th

import unimal_envs
from sb3_divmorph import CompactActor, OnnxActor, export_onnx, export_torchscript, load_model
from divmorph.pipeline.robots import trained_robot_set, trained_robots
from unimal_envs.contract import TASK_NAMES
from unimal_envs.morphology.loader import morphology_files
from unimal_envs.tasks import TASKS


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("student", type=Path, help="folder with the student's model.zip and vecnormalize.pkl")
    parser.add_argument("--task", default="FT", choices=TASK_NAMES)
    parser.add_argument(
        "--robot",
        default=None,
        help="robot name (default: the first robot the student was trained on, from its run's robot_sets.json; else train-000)",
    )
    parser.add_argument("--out", type=Path, default=Path("exported"))
    args = parser.parse_args(argv)
    th.set_num_threads(1)  # batch-1 inference of a small model: one thread is fastest

    trained = trained_robots(args.student)
    candidates = trained if trained is not None else morphology_files("train")
    robot = candidates[0] if args.robot is None else next((f for f in candidates if f.stem == args.robot), None)
    if robot is None:
        parser.error(f"no robot {args.robot!r} among {'the robots the student was trained on' if trained else 'the train set'}")
    student = load_model(args.student / "model.zip", args.student / "vecnormalize.pkl")
    policy, normalizer = student.model.policy.eval(), student.normalizer

    env = gym.make(unimal_envs.env_id(args.task), morphologies=[robot])
    obs, _ = env.reset(seed=0)
    actor = CompactActor.from_policy(policy, obs, TASKS[args.task].observation_keys, normalizer)
    args.out.mkdir(parents=True, exist_ok=True)
    robot_set = trained_robot_set(args.student) or "train"
    metadata = {"robot": robot.stem, "robot_set": robot_set, "task": args.task, "source": str(args.student / "model.zip")}
    onnx_file = export_onnx(actor, obs, args.out / "actor.onnx", metadata)
    script_file = export_torchscript(actor, obs, args.out / "actor.pt", metadata)

    # the deployed file against the full student, on a few steps of the robot's own actions
    onnx_actor, worst = OnnxActor(onnx_file), 0.0
    for _ in range(20):
        with th.no_grad():
            student_obs, _ = policy.obs_to_tensor(normalizer.normalize_obs({k: v[None] for k, v in obs.items()}))
            reference = policy.get_distribution(student_obs).distribution.mean[0].numpy()
        action = onnx_actor(obs)
        worst = max(worst, float(np.abs(action - reference).max()))
        obs, _, terminated, truncated, _ = env.step(np.clip(action, -1, 1))
        if terminated or truncated:
            obs, _ = env.reset()
    env.close()
    print(
        f"{robot.stem} x {args.task}: {actor.stored_numbers()['weights']:,} weights "
        f"(the whole student, critic and router included: {sum(p.numel() for p in policy.parameters()):,}); "
        f"max |ONNX - student| over 20 steps {worst:.1e}"
    )
    print(f"-> {onnx_file} (onnxruntime + numpy), {script_file} (torch.jit.load)")


if __name__ == "__main__":
    main()
