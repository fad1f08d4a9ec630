"""Does the deployment size claim hold at the paper's width? A deployment student at width 128 on CPU (issue 44, item 4).

The paper deploys DivMorph as compact actors 16.7x (flat tasks) / 8.9x (height-map tasks) smaller
than MetaMorph at teacher-level return. `results/cpu100` measured 6.6-8x at width 64, where the
embeddings and output heads -- which pruning does not shrink -- are a large share of the weights.
This study reads a run in which a `deploy-g1k1` student (one learngene per layer, top-1 gates) of
width 128 was distilled on FT alone from the cpu100 FT teacher, for the budget a CPU allows, and
reports, like for like:

* the compact actors' size against a MetaMorph actor of the same width folded the same way
  (`divmorph export`'s `reduction_vs_metamorph`), per exported robot;
* the return it keeps: the student and its teacher, one deterministic episode on each of the 100
  training robots (`divmorph evaluate --episodes 1`), the share of the teacher's mean with a 95%
  bootstrap interval over robots (paired).

    python results/deployment-w128/deployment_at_width.py --run RUN --eval EVAL_FOLDER --out results/deployment-w128
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from divmorph.pipeline.files import log_file, read_done


def paired_share(student: np.ndarray, teacher: np.ndarray, draws: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """The student's mean over the teacher's mean, with a 95% bootstrap interval (robots resampled, pairs kept)."""
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, len(student), size=(draws, len(student)))
    shares = student[rows].mean(1) / teacher[rows].mean(1)
    return float(student.mean() / teacher.mean()), float(np.percentile(shares, 2.5)), float(np.percentile(shares, 97.5))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--run", type=Path, required=True, help="the run folder with students/deploy-g1k1 and export/")
    parser.add_argument("--eval", type=Path, required=True, help="the folder `divmorph evaluate --into` wrote")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--student", default="deploy-g1k1")
    args = parser.parse_args(argv)

    reports = [json.loads(p.read_text()) for p in sorted((args.run / "export" / args.student).glob("*/report.json"))]
    returns = pd.read_csv(log_file(args.eval / "returns.csv"))
    train = returns[(returns.split == "train") & (returns.task == "FT")]
    by = train.groupby(["model", "morphology"])["return"].mean().unstack("model")
    student, teacher = by[f"student-{args.student}"].to_numpy(), by["teacher"].to_numpy()
    share, lo, hi = paired_share(student, teacher)
    kwargs = json.loads((args.run / "run.json").read_text())["configuration"]["student"]["overrides"][args.student]
    done = read_done(args.run / "students" / args.student)

    lines = [
        "# The deployment size claim at the paper's width (128), with the return it keeps (issue 44, item 4)",
        "",
        (__doc__ or "").split("\n\n")[1].replace("\n", " "),
        "",
        f"Student: `{args.student}` with {kwargs} (the cpu100 students' 1 layer), distilled by DAgger on FT alone from "
        f"the cpu100 FT teacher (width 32) for {done['num_timesteps']:,} steps on the 100 training robots "
        f"(the cpu100 recipe otherwise: buffer 200k, batch 1024, one epoch per rollout). A reduced budget: the "
        "cpu100 students had 1M steps over five tasks.",
        "",
        "| robot | compact actor (weights) | MetaMorph actor of the same width, folded the same way | reduction (like for like) | max abs diff | latency compact / student (ms) |",
        "|---|---:|---:|---:|---:|---|",
    ]
    for r in reports:
        lines.append(
            f"| `{r['robot']}` | {r['compact_weights']:,} | {r['metamorph_folded_weights']:,} | **{r['reduction_vs_metamorph']:.1f}x** | "
            f"{r['max_abs_diff']:.1e} | {r['latency_compact_ms']:.3f} / {r['latency_student_ms']:.3f} |"
        )
    lines += [
        "",
        f"Return kept (one deterministic episode per training robot, {len(student)} robots): the student "
        f"{student.mean():.0f}, the teacher {teacher.mean():.0f}: **{share:.0%} [{lo:.0%}, {hi:.0%}]** of the teacher "
        "(the paper: teacher level). The compact actors reproduce the student's actions to the tolerance above, so "
        "they keep what the student keeps.",
        "",
    ]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "README.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
