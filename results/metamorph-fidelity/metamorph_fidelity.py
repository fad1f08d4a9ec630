"""What do the project's departures from MetaMorph's reference network do to a teacher? (issue 43, item 4)

The ``cpu100`` teachers are MetaMorph policies with three departures from MetaMorph's reference code
(``agrimgupta92/metamorph``): a 35-feature morphology ``context`` row in every token, a hidden layer
in the per-token decoders, and no embedding dropout (the reference: 0.1 after the position
embedding, active in rollouts too). This study trains one FT teacher per variant at the ``cpu100``
teacher size and settings -- the project's network, each departure undone on its own, and all three
undone (the reference) -- and compares them, robot by robot, with the project's network.

Settings are chosen on training robots only: every teacher trains on ``unimals100-fit`` (90 official
training robots) and is measured on them and on ``unimals100-val`` (the 10 training robots held out
for choices about generalisation). The official test robots are never rolled out.

Each variant is one ``divmorph teachers`` run (resumable: run the script again after a stop) and one
``divmorph evaluate`` selection, both subprocesses, ``--jobs`` at a time (one per core). Writes
``<out>/README.md`` (the table: mean deterministic return [95% bootstrap CI over robots] on the fit
and validation robots, the paired difference from the project's network, wall time) and
``<out>/returns.csv`` (every robot and episode). Reduced scale: one seed, ``--steps`` per teacher.

    python results/metamorph-fidelity/metamorph_fidelity.py --steps 2000000 --out results/metamorph-fidelity
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pandas as pd

from divmorph.pipeline.metrics import robot_interval

#: The variants: ``--set`` overrides of the ``cpu100`` teachers' policy_kwargs (width 32, one layer).
VARIANTS: dict[str, dict[str, object]] = {
    "project": {},
    "embedding-dropout": {"embedding_dropout": 0.1, "embedding_dropout_in_rollouts": True},
    "no-context": {"use_context": False},
    "linear-decoder": {"net_arch": {"pi": [], "vf": []}},
    "reference": {
        "embedding_dropout": 0.1,
        "embedding_dropout_in_rollouts": True,
        "use_context": False,
        "net_arch": {"pi": [], "vf": []},
    },
}
WHAT = {
    "project": "the cpu100 teacher's network: context input, decoder hidden [64], no embedding dropout",
    "embedding-dropout": "+ embedding dropout 0.1, in rollouts too (as MetaMorph's code)",
    "no-context": "no context input (MetaMorph: proprioception only)",
    "linear-decoder": "linear per-token decoder (MetaMorph's FT decoder)",
    "reference": "all three: MetaMorph's reference network at this width",
}
SPLITS = {"train": "fit robots (90, trained on)", "novel": "validation robots (10, held out)"}


def run(command: list[str], log: Path) -> None:
    """Run one divmorph command, its output appended to ``log``."""
    with open(log, "a") as f:
        f.write(f"$ {' '.join(command)}\n")
        f.flush()
        subprocess.run(command, stdout=f, stderr=subprocess.STDOUT, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})


def variant_job(name: str, args: argparse.Namespace) -> None:
    """Train (or resume, or skip) one variant's teacher, then evaluate it on the fit and validation robots."""
    folder = args.out / name
    folder.mkdir(parents=True, exist_ok=True)
    sets = [f"--set=teachers.policy_kwargs.{key}={json.dumps(value)}" for key, value in VARIANTS[name].items()]
    divmorph = [sys.executable, "-m", "divmorph"]
    common = ["--profile", "cpu100", "--out", str(folder), "--train-robots", "unimals100-fit", "--novel-robots", "unimals100-val"]
    train = [*divmorph, "teachers", *common, "--task", "FT", "--no-progress", f"--set=teachers.n_timesteps={args.steps}", *sets]
    run(train, folder / "log.txt")
    evaluation = folder / "fit-val"
    if not (evaluation / "returns.csv").is_file():
        evaluate = [*divmorph, "evaluate", *common, f"--set=teachers.n_timesteps={args.steps}", *sets, "--model", "teacher"]
        evaluate += ["--task", "FT", "--split", "train", "--split", "novel", "--episodes", str(args.episodes), "--into", str(evaluation)]
        evaluate += ["--no-progress"]
        run(evaluate, folder / "log.txt")


def training_seconds(folder: Path) -> float:
    """The teacher's training time over all its segments (SB3's ``time/time_elapsed`` at the end of each)."""
    total = 0.0
    for log in (folder / "teachers" / "FT" / "logs").glob("run-*/progress.csv"):
        rows = pd.read_csv(log)
        if "time/time_elapsed" in rows and len(rows):
            total += float(rows["time/time_elapsed"].iloc[-1])
    return total


def table(returns: pd.DataFrame, walls: dict[str, float]) -> list[str]:
    per_robot = returns.groupby(["variant", "split", "morphology"])["return"].mean()
    lines = [
        f"| variant | what differs | {SPLITS['train']}: mean [95% CI] | paired difference from `project` | "
        f"{SPLITS['novel']}: mean [95% CI] | paired difference from `project` | wall time of the run |",
        "|---|---|---|---|---|---|---:|",
    ]
    for name in VARIANTS:
        if name not in per_robot.index.get_level_values(0):
            continue
        cells = []
        for split in SPLITS:
            values = per_robot.loc[(name, split)]
            lo, hi = robot_interval(values.to_numpy())
            cells.append(f"{values.mean():.0f} [{lo:.0f}, {hi:.0f}]")
            if name == "project" or "project" not in per_robot.index.get_level_values(0):
                cells.append("--")
                continue
            base = per_robot.loc[("project", split)]
            difference = (values - base.reindex(values.index)).to_numpy()
            lo, hi = robot_interval(difference)
            cells.append(f"{difference.mean():+.0f} [{lo:+.0f}, {hi:+.0f}]")
        wall = walls.get(name)
        lines.append(f"| `{name}` | {WHAT[name]} | " + " | ".join(cells) + f" | {'' if wall is None else f'{wall:,.0f} s'} |")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2_000_000, help="env steps per teacher (default 2M)")
    parser.add_argument("--episodes", type=int, default=3, help="deterministic episodes per robot (default 3)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--jobs", type=int, default=2, help="variants trained side by side (one per core)")
    parser.add_argument("--out", type=Path, default=Path("results/metamorph-fidelity"))
    args = parser.parse_args(argv)
    if args.steps < 1 or args.episodes < 1 or args.jobs < 1:
        parser.error("--steps, --episodes and --jobs must be positive")
    args.out.mkdir(parents=True, exist_ok=True)
    start = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    with ThreadPoolExecutor(args.jobs) as pool:
        list(pool.map(lambda name: variant_job(name, args), args.variants))  # (list: a job's error is raised here)
    walls = {name: training_seconds(args.out / name) for name in VARIANTS if (args.out / name).is_dir()}
    frames = []
    for name in VARIANTS:
        path = args.out / name / "fit-val" / "returns.csv"
        if path.is_file():
            frames.append(pd.read_csv(path).assign(variant=name))
    returns = pd.concat(frames)
    returns.to_csv(args.out / "returns.csv", index=False)
    rows = table(returns, walls)
    text = "\n".join(
        [
            "# MetaMorph's reference network against the project's (issue 43, item 4)",
            "",
            (__doc__ or "").split("\n\n")[1].replace("\n", " "),
            "",
            f"FT teachers at the `cpu100` teacher settings (width 32, one layer, PPO 16 x 512 steps, lin_1e-3), "
            f"{args.steps:,} env steps each, seed 0, trained on `unimals100-fit`; {args.episodes} deterministic "
            "episodes per robot; 95% bootstrap intervals over robots (paired: the same robots and episodes' seeds).",
            "",
            *rows,
            "",
            f"Command: `python results/metamorph-fidelity/metamorph_fidelity.py --steps {args.steps} --episodes {args.episodes} --out {args.out}` "
            f"(started {start}, {args.jobs} variants side by side on {platform.node()}: {os.cpu_count()} CPU cores, "
            "torch 1 thread per process; training wall time summed over a run's segments, from its progress logs).",
            "",
        ]
    )
    (args.out / "README.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
