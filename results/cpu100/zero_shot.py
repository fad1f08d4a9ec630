"""How much of its return does each model keep on robots it never trained on? (issue 43)

Reads a run's evaluation (``evaluate/returns.csv``: every model, task and robot split, deterministic
episodes) and, where given, evaluations of variation sets (``--variations``: ``divmorph evaluate
--split ood --set ood_set=<variation set>`` selections), and writes ``<out>`` (markdown):

1. per task and model, the mean return on the training robots, on the novel robots (the official
   held-out robots) and on the out-of-distribution robots (the generated set), each with a 95%
   bootstrap interval over robots, and the share kept on the novel robots;
2. the paper's comparison on the novel robots: the DivMorph student minus HyperDistill, paired
   over the same robots, and the same on the out-of-distribution robots, reported apart;
3. zero-shot on the variations of the training robots: each model's return on a robot's variant
   minus on the robot itself, paired over robots.

Each robot's return is the mean of its episodes; intervals resample robots (the unit a
morphology-agnostic controller varies over).

    python results/cpu100/zero_shot.py --run results/cpu100 --variations results/cpu100/variations/*/ --out results/cpu100/zero-shot.md
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import numpy as np

from divmorph.pipeline.metrics import interval, robot_interval
from divmorph.pipeline.report import read_returns, robot_means

MODELS = {
    "teacher": "teacher (MetaMorph)",
    "student": "DivMorph student",
    "student-distilled": "dense MetaMorph⚗ student",
    "student-deploy-g1k1": "deployment student (w64)",
    "hyperdistill": "HyperDistill",
    "teacher-untrained": "untrained teacher",
}
SPLITS = {"train": "training robots", "novel": "official held-out robots", "ood": "generated robots (out of distribution)"}
DRAWS = 10_000


def cell(values: np.ndarray) -> str:
    lo, hi = robot_interval(values)
    return f"{values.mean():.0f} [{lo:.0f}, {hi:.0f}]"


def paired(a: dict[str, float], b: dict[str, float]) -> tuple[str, int]:
    """Mean of ``a - b`` over their common robots, with a 95% bootstrap interval, and how many robots."""
    robots = sorted(set(a) & set(b))
    difference = np.array([a[r] - b[r] for r in robots])
    lo, hi = robot_interval(difference)
    return f"{difference.mean():+.0f} [{lo:+.0f}, {hi:+.0f}]", len(robots)


def kept(train: np.ndarray, held_out: np.ndarray, rng: np.random.Generator) -> str:
    """Held-out mean / training mean, training and held-out robots resampled independently."""
    ratios = held_out[rng.integers(0, len(held_out), (DRAWS, len(held_out)))].mean(1) / train[
        rng.integers(0, len(train), (DRAWS, len(train)))
    ].mean(1)
    lo, hi = interval(ratios)
    return f"{100 * held_out.mean() / train.mean():.0f}% [{100 * lo:.0f}, {100 * hi:.0f}]"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="a run folder with evaluate/returns.csv")
    parser.add_argument("--variations", type=Path, nargs="*", default=[], help="evaluation folders of variation sets (returns.csv)")
    parser.add_argument("--out", type=Path, required=True, help="the markdown file to write")
    args = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    rows = read_returns(args.run / "evaluate" / "returns.csv")
    per_robot = robot_means(rows)
    tasks = list(dict.fromkeys(r["task"] for r in rows if r["model"] == "teacher"))
    counts = {split: len({r["morphology"] for r in rows if r["split"] == split and r["model"] == "teacher"}) for split in SPLITS}
    lines = [
        f"# Zero-shot in `{args.run}`: the official held-out robots, the generated robots, variations",
        "",
        f"`python results/cpu100/zero_shot.py --run {args.run}"
        + (f" --variations {' '.join(str(v) for v in args.variations)}" if args.variations else "")
        + f" --out {args.out}`. Deterministic episodes (`evaluate/returns.csv`); each robot's return the mean of "
        "its episodes; 95% bootstrap intervals over robots. Robots: " + ", ".join(f"{counts[s]} {w}" for s, w in SPLITS.items()) + ".",
        "",
        "## Return on each robot split, and the share kept on the official held-out robots",
        "",
        "| task | model | " + " | ".join(SPLITS.values()) + " | kept on the held-out robots [95% CI] |",
        "|---|---|" + "---|" * (len(SPLITS) + 1),
    ]
    for task in tasks:
        for model, label in MODELS.items():
            values = {s: np.array(list(per_robot.get((model, task, s), {}).values())) for s in SPLITS}
            if not values["train"].size:
                continue
            cells = [cell(v) if v.size else "–" for v in values.values()]
            share = kept(values["train"], values["novel"], rng) if values["novel"].size and model != "teacher-untrained" else "–"
            lines.append(f"| {task} | {label} | " + " | ".join(cells) + f" | {share} |")
    for split in ("novel", "ood"):
        lines += [
            "",
            f"## The DivMorph student against HyperDistill on the {SPLITS[split]}",
            "",
            "| task | DivMorph student - HyperDistill [paired 95% CI] | robots | on the training robots |",
            "|---|---|---:|---|",
        ]
        for task in tasks:
            student, hyper = per_robot.get(("student", task, split)), per_robot.get(("hyperdistill", task, split))
            if not student or not hyper:
                continue
            held_out, n = paired(student, hyper)
            train, _ = paired(per_robot[("student", task, "train")], per_robot[("hyperdistill", task, "train")])
            lines.append(f"| {task} | {held_out} | {n} | {train} |")
    if args.variations:
        lines += [
            "",
            "## Variations of the training robots (one variant per robot)",
            "",
            "Return on a robot's variant minus on the robot itself (its training-robot return above), paired over robots.",
            "",
            "| variation set | task | model | on the variants [95% CI] | variant - original [paired 95% CI] | robots |",
            "|---|---|---|---|---|---:|",
        ]
        for folder in args.variations:
            varied = robot_means(read_returns(folder / "returns.csv"))
            by_parent: dict[tuple[str, str], dict[str, float]] = defaultdict(dict)
            for (model, task, _), robots in varied.items():
                for name, value in robots.items():
                    by_parent[(model, task)][name.rsplit("-", 2)[0]] = value
            for (model, task), values in sorted(by_parent.items(), key=lambda kv: (kv[0][1], list(MODELS).index(kv[0][0]))):
                difference, n = paired(values, per_robot[(model, task, "train")])
                lines.append(
                    f"| `{folder.name}` | {task} | {MODELS[model]} | {cell(np.array(list(values.values())))} | {difference} | {n} |"
                )
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
