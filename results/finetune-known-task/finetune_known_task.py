"""Does PPO fine-tuning keep what a model already knows? The teacher and the distilled students on a training task (issue 42).

On a training task the answer is known in advance: every model starts near its best, so a fall of
the return under fine-tuning is damage, not exploration. This study fine-tunes, with the transfer
race's own rules (``transfer_run(..., calibration=True)``: fine-tuning rate, critic rate, frozen
inherited statistics, Adam eps, as the run's profile records them), the task's teacher (the
``closest`` arm: on a training task its own teacher), the dense distilled student and the DivMorph
student, on the run's training robots, ``--seeds`` seeds each, and reads per run: the deterministic
return on the curve's robots at each evaluation, and from the training logs the stochastic training
return, the critic's explained variance, the approximate KL and the clip fraction of the updates.

**The baseline.** A deterministic episode on these robots is chaotic: a change of the policy far
below what PPO makes (an exported actor's 1e-6 differences) sends a 1,000-step episode elsewhere,
so the evaluation after fine-tuning is in effect a fresh draw of episodes while the step-0
evaluation is one fixed draw. ``--baseline-seeds N`` evaluates each arm's starting model on the
same robots under N evaluation seeds and reports the change against that mean as well (per robot,
paired with each run): the step-0 column alone compares a fresh draw with one that may have been
lucky or unlucky.

The run folder is a branch of ``--source`` (its teachers and students, read-only links) in ``--out``;
runs resume. ``--arms`` / ``--seeds`` split the runs between processes (one per core); ``--report``
writes ``<out>/README.md`` from whatever runs are finished.

    python results/finetune-known-task/finetune_known_task.py --source results/cpu100 --out results/finetune-known-task --arms closest distilled
    python results/finetune-known-task/finetune_known_task.py --source results/cpu100 --out results/finetune-known-task --arms divmorph
    python results/finetune-known-task/finetune_known_task.py --source results/cpu100 --out results/finetune-known-task --report
"""

from __future__ import annotations

import argparse
import fcntl
import platform
import signal
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch as th
import yaml

from divmorph.pipeline.branch import branch
from divmorph.pipeline.folders import transfer_folder
from divmorph.pipeline.metrics import run_interval
from divmorph.pipeline.provenance import recorded_profile
from divmorph.pipeline.files import is_done, log_file, read_progress
from divmorph.pipeline.transfer import transfer_run

ARMS = {
    "closest": "teacher (MetaMorph->)",
    "scratch": "MetaMorph from scratch (its start: each run's own step 0)",
    "distilled": "dense MetaMorph⚗ student",
    "divmorph": "DivMorph student",
    "divmorph-finetuned": "DivMorph student, fully fine-tuned",
    # the paper's ablations: their students are distilled in a branch of --source (`divmorph distill --students ...`)
    "no-kdiv-transformer": "DivMorph student w/o diversion in the Transformer",
    "no-kdiv-decoder": "DivMorph student w/o diversion in the decoder",
    "no-orthogonality": "DivMorph student w/o orthogonality",
}
LOGGED = {
    "rollout/ep_rew_mean": "training return (stochastic)",
    "train/explained_variance": "critic's explained variance",
    "train/approx_kl": "approx. KL",
    "train/clip_fraction": "clip fraction",
}


def overrides(args: argparse.Namespace) -> dict[str, object]:
    return {
        "transfer.n_timesteps": args.steps,
        "transfer.eval_every": args.eval_every,
        "transfer.checkpoint_every": args.eval_every,
        "transfer.eval_episodes": 3,
        **dict(parse_setting(item) for item in args.set),
    }


def parse_setting(item: str) -> tuple[str, object]:
    """``transfer.learngene_lr_scale=0`` -> ``("transfer.learngene_lr_scale", 0)`` (the value read as YAML)."""
    key, sep, value = item.partition("=")
    if not sep or not key:
        raise SystemExit(f"--set takes KEY=VALUE (e.g. transfer.learngene_lr_scale=1.0), got {item!r}")
    return key, yaml.safe_load(value)


BASELINE = "baseline.json"


def evaluate_baselines(args: argparse.Namespace, profile) -> dict[str, dict[str, dict[str, float]]]:
    """``{arm: {eval seed: {robot: mean return}}}`` of each arm's starting model on the curve robots,
    under ``--baseline-seeds`` evaluation seeds (kept in ``<out>/baseline.json``; the missing ones added)."""
    import json

    from divmorph.pipeline.envs import profile_env_kwargs
    from divmorph.pipeline.robots import transfer_eval_robots
    from divmorph.pretrained import load_pretrained

    path = args.out / BASELINE
    found = json.loads(path.read_text()) if path.is_file() else {}
    robots = transfer_eval_robots(profile, "train")
    for arm in args.arms:
        record = json.loads((transfer_folder(args.out, args.task, arm, args.seeds[0]) / "source.json").read_text())
        if record.get("source") is None:
            continue  # a random init: each run's start is its own step 0, not one model to draw many episodes of
        model = load_pretrained(args.out / record["source"])
        # told what the runs are told: the closest task's instruction under ``transfer.task_gates: closest``,
        # else the profile's ``transfer.instructions[task]`` (``--set``), else the task's own
        instruction = record.get("instruction", profile.transfer.instructions.get(args.task))
        told = {"instruction": instruction} if instruction is not None else {}
        for seed in range(args.baseline_seeds):
            if str(seed) in found.get(arm, {}):
                continue
            rows = model.evaluate(
                robots,
                task=args.task,
                episodes=3,
                seed=seed,
                max_episode_steps=profile.max_episode_steps,
                **told,
                **profile_env_kwargs(profile),
            )
            found.setdefault(arm, {})[str(seed)] = pd.DataFrame(rows).groupby("robot")["return"].mean().to_dict()
            path.write_text(json.dumps(found, indent=1))
            print(f"[finetune-known-task] baseline {arm} eval seed {seed}: {np.mean(list(found[arm][str(seed)].values())):.1f}", flush=True)
    return found


def baseline_changes(out: Path, task: str, arm: str, seeds: list[int]) -> pd.Series:
    """Per (robot, seed): the last evaluation minus the robot's mean over the baseline's evaluation seeds."""
    import json

    path = out / BASELINE
    if not path.is_file() or arm not in json.loads(path.read_text()):
        return pd.Series(dtype=float)
    baseline = pd.DataFrame(json.loads(path.read_text())[arm]).mean(axis=1)  # robot -> mean over eval seeds
    parts = []
    for seed in seeds:
        folder = transfer_folder(out, task, arm, seed)
        if not is_done(folder):
            continue
        frame = pd.read_csv(log_file(folder / "eval.csv"))
        frame = frame[frame.split == "train"].groupby(["timesteps", "robot"])["return"].mean().unstack("timesteps")
        parts.append((frame[frame.columns.max()] - baseline.reindex(frame.index)).rename(seed))
    return pd.concat(parts, axis=1).stack().rename("change") if parts else pd.Series(dtype=float)


def changes(out: Path, task: str, arm: str, seeds: list[int]) -> pd.Series:
    """Per (robot, seed): the deterministic return at the last evaluation minus the first, for the finished runs."""
    parts = []
    for seed in seeds:
        folder = transfer_folder(out, task, arm, seed)
        if not is_done(folder):
            continue
        frame = pd.read_csv(log_file(folder / "eval.csv"))
        frame = frame[frame.split == "train"].groupby(["timesteps", "robot"])["return"].mean().unstack("timesteps")
        parts.append((frame[frame.columns.max()] - frame[frame.columns.min()]).rename(seed))
    if not parts:
        return pd.Series(dtype=float)
    return pd.concat(parts, axis=1).stack().rename("change")


def by_run(values: pd.Series) -> np.ndarray:
    """Seeds x robots (robots every seed has) from values indexed by robot and seed: intervals resample the training
    runs and the robots within them, not robot x seed pairs (a run's robots share its policy)."""
    return values.unstack(0).dropna(axis=1).to_numpy()  # the first level is the robot


def compare(args: argparse.Namespace) -> None:
    """A table of variants (``LABEL=FOLDER``, the first the reference) for one arm: the change under
    fine-tuning and its difference from the reference's, paired per robot and seed."""
    variants = [tuple(item.split("=", 1)) for item in args.compare]
    arm = args.arms[0]
    reference = changes(Path(variants[0][1]), args.task, arm, args.seeds)
    lines = [
        f"| variant ({ARMS[arm]}) | runs | change 0 -> last [95% CI] | minus {variants[0][0]}'s (paired) | change against the multi-seed baseline |",
        "|---|---:|---|---|---|",
    ]
    for label, folder in variants:
        mine = changes(Path(folder), args.task, arm, args.seeds)
        if mine.empty:
            lines.append(f"| {label} | 0 | – | – |")
            continue
        lo, hi = run_interval(by_run(mine))
        paired = (mine - reference).dropna().to_numpy()
        plo, phi = run_interval(by_run((mine - reference).dropna())) if paired.size else (np.nan, np.nan)
        against = baseline_changes(Path(folder), args.task, arm, args.seeds)
        if against.empty and args.baseline_from is not None:  # the starting model is the same in every variant
            import shutil

            shutil.copy(args.baseline_from / BASELINE, Path(folder) / BASELINE)
            against = baseline_changes(Path(folder), args.task, arm, args.seeds)
        blo, bhi = run_interval(by_run(against)) if not against.empty else (np.nan, np.nan)
        lines.append(
            f"| {label} | {mine.index.get_level_values(1).nunique()} | {mine.mean():+.0f} [{lo:+.0f}, {hi:+.0f}] | "
            f"{paired.mean():+.0f} [{plo:+.0f}, {phi:+.0f}] | "
            + (f"{against.mean():+.0f} [{blo:+.0f}, {bhi:+.0f}] |" if not against.empty else "– |")
        )
    print("\n".join(lines))


def report(args: argparse.Namespace) -> None:
    rows, logs = [], []
    for arm in ARMS:
        for seed in args.seeds:
            folder = transfer_folder(args.out, args.task, arm, seed)
            if not is_done(folder):
                continue
            frame = pd.read_csv(log_file(folder / "eval.csv"))
            frame = frame[frame.split == "train"].groupby(["timesteps", "robot"], as_index=False)["return"].mean()
            rows.append(frame.assign(arm=arm, seed=seed))
            # a resumed run logs each attempt to its own logs/run-K; an attempt cut off early may be empty
            progress = pd.DataFrame(read_progress(folder))
            logs.append(progress.assign(arm=arm, seed=seed))
    if not rows:
        raise SystemExit(f"no finished run in {args.out}")
    data, progress = pd.concat(rows), pd.concat(logs)
    steps = sorted(s for s in data.timesteps.unique() if s % args.eval_every == 0)
    lines = [
        f"# Fine-tuning on a task the models already know: {args.task}, `{args.source}`",
        "",
        (__doc__ or "").split("\n\n")[1].replace("\n", " "),
        "",
        f"{args.steps:,} env steps per run, evaluations every {args.eval_every:,} on the run's curve robots "
        f"({overrides(args)['transfer.eval_episodes']} deterministic episodes each, averaged per robot); mean over robots x seeds with a 95% bootstrap interval over training runs and robots; the change is paired "
        "per robot and seed.",
        "",
        "| model | seeds | " + " | ".join(f"{s / 1000:.0f}k" for s in steps) + " | change 0 -> last [95% CI] |",
        "|---|---:|" + "---|" * len(steps) + "---|",
    ]
    for arm, label in ARMS.items():
        mine = data[data.arm == arm]
        if mine.empty:
            continue
        cells = []
        for s in steps:
            values = by_run(mine[mine.timesteps == s].set_index(["robot", "seed"])["return"])
            lo, hi = run_interval(values)
            cells.append(f"{values.mean():.0f} [{lo:.0f}, {hi:.0f}]")
        first = mine[mine.timesteps == steps[0]].set_index(["robot", "seed"])["return"]
        last = mine[mine.timesteps == steps[-1]].set_index(["robot", "seed"])["return"]
        change = (last - first).dropna()
        lo, hi = run_interval(by_run(change))
        lines.append(f"| {label} | {mine.seed.nunique()} | " + " | ".join(cells) + f" | {change.mean():+.0f} [{lo:+.0f}, {hi:+.0f}] |")
    import json

    if (args.out / BASELINE).is_file():
        saved = json.loads((args.out / BASELINE).read_text())
        lines += [
            "",
            "Against the starting model's mean over evaluation seeds (the same robots, 3 episodes each per seed; the change "
            "is the last evaluation minus each robot's baseline mean, per robot and run):",
            "",
            "| model | baseline seeds | baseline mean (per seed; seed 0 = the curve's step 0) | last evaluation | change against the baseline [95% CI] |",
            "|---|---:|---|---:|---|",
        ]
        for arm, label in ARMS.items():
            if arm not in saved or data[data.arm == arm].empty:
                continue
            per_seed = {k: np.mean(list(v.values())) for k, v in saved[arm].items()}
            change = baseline_changes(args.out, args.task, arm, args.seeds)
            lo, hi = run_interval(by_run(change))
            last = data[(data.arm == arm) & (data.timesteps == steps[-1])]["return"].mean()
            seeds_text = ", ".join(f"{per_seed[k]:.0f}" for k in sorted(per_seed, key=int))
            lines.append(
                f"| {label} | {len(per_seed)} | {np.mean(list(per_seed.values())):.0f} ({seeds_text}) | {last:.0f} | "
                f"{change.mean():+.0f} [{lo:+.0f}, {hi:+.0f}] |"
            )
    lines += ["", "From the training logs (mean over seeds; first half / second half of the run's updates):", ""]
    lines += ["| model | " + " | ".join(LOGGED.values()) + " |", "|---|" + "---|" * len(LOGGED)]
    for arm, label in ARMS.items():
        mine = progress[progress.arm == arm]
        if mine.empty:
            continue
        cells = []
        for key in LOGGED:
            halves = []
            for _, run in mine.groupby("seed"):
                values = run[key].dropna().to_numpy() if key in run else np.array([])
                if values.size:
                    halves.append((values[: len(values) // 2 or 1].mean(), values[len(values) // 2 :].mean()))
            cells.append(" / ".join(f"{np.mean([h[i] for h in halves]):.3g}" for i in (0, 1)) if halves else "–")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += [
        "",
        f"Commands: `python results/finetune-known-task/finetune_known_task.py --source {args.source} --out {args.out} --task {args.task} "
        f"--steps {args.steps} --eval-every {args.eval_every} --arms ... --seeds {' '.join(map(str, args.seeds))}` "
        f"(one process per core), then `--report`; {time.strftime('%Y-%m-%d')}, {platform.node()}, 1 torch thread per process.",
        "",
    ]
    (args.out / "README.md").write_text("\n".join(lines))
    print("\n".join(lines))


def stop_as_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt  # a transfer run saves what it has learnt since its last checkpoint on it


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--source", type=Path, default=Path("results/cpu100"), help="the run whose teachers and students are fine-tuned")
    parser.add_argument("--out", type=Path, default=Path("results/finetune-known-task"))
    parser.add_argument("--task", default="FT", help="a training task")
    parser.add_argument("--steps", type=int, default=100_000, help="env steps per run")
    parser.add_argument("--eval-every", type=int, default=50_000)
    parser.add_argument("--arms", nargs="+", default=list(ARMS), choices=list(ARMS))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--report", action="store_true", help="only write the README from the finished runs")
    parser.add_argument(
        "--baseline-seeds", type=int, default=0, help="evaluate each arm's starting model under this many evaluation seeds (see above)"
    )
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="a profile setting for the runs (a variant: give it its own --out)"
    )
    parser.add_argument("--baseline-only", action="store_true", help="with --baseline-seeds: only measure the starts (no run, no report)")
    parser.add_argument("--baseline-from", type=Path, default=None, help="with --compare: a folder whose baseline.json the variants share")
    parser.add_argument(
        "--compare",
        nargs="+",
        metavar="LABEL=FOLDER",
        help="only print the change of the first --arms arm in each folder, paired against the first",
    )
    args = parser.parse_args(argv)
    th.set_num_threads(1)
    # SIGTERM (a `kill`, a session's end) stops a run as Ctrl-C does: at a checkpoint, exit status 130
    signal.signal(signal.SIGTERM, stop_as_interrupt)
    if args.compare:
        compare(args)
        return
    if args.baseline_seeds:
        # the starts are measured in the envs the runs train in (``--set goal_range=...`` included)
        evaluate_baselines(args, recorded_profile(args.out / "run.json", overrides(args)))
        if args.baseline_only:
            return
    if not args.report:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        # one process per core may start on the same --out at once: the first branches it, the others wait
        lock_path = args.out.parent / f".{args.out.name}.branch.lock"
        with open(lock_path, "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            if not (args.out / "run.json").exists():
                branch(args.source, args.out, ("teachers", "distill"), command="python results/finetune-known-task/finetune_known_task.py")
            lock_path.unlink(missing_ok=True)  # safe: whoever locks a new file after this finds run.json
        profile = recorded_profile(args.out / "run.json", overrides(args))
        for arm in args.arms:
            for seed in args.seeds:
                print(f"[finetune-known-task] {arm} seed {seed} on {args.task}", flush=True)
                transfer_run(profile, args.out, args.task, arm, seed, progress_bar=False, calibration=True).run()
    report(args)


if __name__ == "__main__":
    main()
