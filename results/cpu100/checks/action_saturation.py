"""How far beyond the action bounds do a run's teacher and distilled students put their action means? (issue 42)

The environments clip actions to [-1, 1]. A PPO teacher's Gaussian mean is unbounded, and DAgger
regresses a student's means onto the teacher's, so a student copies every mean beyond the bound.
Where a mean sits far outside, the executed action is the bound whatever the mean does, so PPO's
gradient on that mean carries no information about the return -- one suspect for the loss of return
when a distilled student is fine-tuned on a task it already knows (``results/critic-start``).

This study rolls out the task's teacher deterministically on training robots spread over the run's
set (its own statistics), keeps the raw observations, and feeds the same states to the teacher and
to each student (each through its own statistics; the students read the task's instruction in the
observation). Per model it writes the share of real action slots whose mean lies beyond 1 (and 2,
5), the median and 99th percentile of |mean|, and the students' mean absolute difference from the
teacher's means, with the bounded difference (both clipped to [-1, 1]: what the env executes).

    python results/cpu100/checks/action_saturation.py --run results/cpu100 --task FT --robots 20 --steps 300 \\
        --out results/cpu100/checks/action-saturation.md
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np
import torch as th

from divmorph.pipeline.curves import robot_venv
from divmorph.pretrained import Pretrained, load_pretrained

#: The models compared, by their folder in a run.
MODELS = {
    "teacher": "teachers/{task}",
    "DivMorph student": "student",
    "dense MetaMorph⚗ student": "students/distilled",
    "deployment student": "students/deploy-g1k1",
}


def teacher_states(teacher: Pretrained, task: str, robots: list[Path], steps: int, seed: int) -> dict[str, np.ndarray]:
    """Raw observations along the teacher's own deterministic episodes (one env per robot)."""
    venv = robot_venv(f"Unimal-{task}-v0", robots, steps, seed, **teacher.env_kwargs)
    obs = venv.reset()
    states = []
    for _ in range(steps):
        states.append(obs)
        obs, _, _, _ = venv.step(teacher.predict(obs))
    venv.close()
    return {key: np.concatenate([s[key] for s in states]) for key in states[0]}


def action_means(model: Pretrained, raw: dict[str, np.ndarray]) -> np.ndarray:
    """The model's Gaussian means on the real action slots (flattened) of ``raw`` states."""
    obs = model.normalizer.normalize_obs(raw) if model.normalizer is not None else raw
    tensors, _ = model.model.policy.obs_to_tensor(obs)
    with th.no_grad():
        mean = model.model.policy.get_distribution(tensors).distribution.mean.numpy()
    real = raw["act_padding_mask"] < 0.5
    return mean[real]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True)
    parser.add_argument("--task", default="FT")
    parser.add_argument("--robots", type=int, default=20, help="training robots, spread over the run's set")
    parser.add_argument("--steps", type=int, default=300, help="steps of each teacher episode (states kept)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    start = time.perf_counter()
    models = {}
    for label, folder in MODELS.items():
        path = args.run / folder.format(task=args.task)
        if (path / "model.zip").is_file():
            models[label] = load_pretrained(path)
    teacher = models["teacher"]
    trained = teacher.robots
    robots = [trained[i] for i in np.linspace(0, len(trained) - 1, min(args.robots, len(trained))).round().astype(int)]
    raw = teacher_states(teacher, args.task, robots, args.steps, args.seed)
    means = {label: action_means(model, raw) for label, model in models.items()}
    reference = means["teacher"]
    lines = [
        f"# Action means beyond the bounds: `{args.run}`, {args.task}",
        "",
        (__doc__ or "").split("\n\n")[1].replace("\n", " "),
        "",
        f"States: the {args.task} teacher's deterministic episodes on {len(robots)} training robots spread over the run's "
        f"set, {args.steps} steps each ({len(raw['act_padding_mask'])} states, {reference.size} real action slots); seed {args.seed}.",
        "",
        "| model | mean beyond 1 | beyond 2 | beyond 5 | median abs mean | 99th percentile | mean abs difference from the teacher | the same, both clipped to [-1, 1] |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, values in means.items():
        size = np.abs(values)
        difference = np.abs(values - reference).mean()
        clipped = np.abs(np.clip(values, -1, 1) - np.clip(reference, -1, 1)).mean()
        lines.append(
            f"| {label} | {100 * (size > 1).mean():.1f}% | {100 * (size > 2).mean():.1f}% | {100 * (size > 5).mean():.1f}% | "
            f"{np.median(size):.2f} | {np.percentile(size, 99):.2f} | {difference:.3f} | {clipped:.3f} |"
        )
    lines += [
        "",
        f"Command: `python results/cpu100/checks/action_saturation.py --run {args.run} --task {args.task} --robots {args.robots} --steps {args.steps} "
        f"--seed {args.seed} --out {args.out}`; {time.perf_counter() - start:.0f} s on {platform.node()} (1 torch thread).",
        "",
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
