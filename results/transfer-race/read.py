"""Read the transfer race by its rule (``rule.md``): steps to a level, as ratios with run-resampled intervals.

    python results/transfer-race/read.py --keep results/transfer-race/S2      # -> reading.md, curves.png there

The kept runs are ``<keep>/<task>/transfer/<task>/<arm>/seed-<n>/eval.csv.gz`` (``race.py`` packs them so), the
fine-tuned arms' many-draw starts ``<keep>/<task>/baseline.json``. Everything is read on the training robots. In
each bootstrap draw the runs of each arm are resampled (with replacement, independently per arm) and the robots
once for every arm (the arms share them); an arm's curve is its mean over the drawn runs and robots, linear between
evaluations. ``steps_to(curve, level)`` is the first step the curve reaches ``level`` (0 when its start does,
infinite when it never does within the budget).

1. ``R→ = steps_to(MetaMorph→, L→) / steps_to(DivMorph, L→)``, ``L→`` MetaMorph→'s last value in the draw; read only
   where MetaMorph→ rises (last minus its many-draw start, 95% interval over runs and robots above 0).
2. ``Rs = steps_to(scratch, Ls) / steps_to(DivMorph, Ls)``, ``Ls`` scratch's last value in the draw.

A reading holds on a task when its 95% interval lies at or above 3, does not hold when below 3, else is undecided.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from divmorph.pipeline.metrics import BOOTSTRAP, _counts, interval, paired_run_interval, run_interval

TASKS = ["Escape", "Exploration", "PointNav"]
ARMS = {
    "divmorph": "DivMorph (fixed gates)",
    "closest": "MetaMorph→ (closest teacher, fine-tuned)",
    "distilled": "MetaMorph⚗ (dense student, fine-tuned)",
    "scratch": "MetaMorph from scratch",
}
FACTOR = 3.0


def arm_runs(keep: Path, task: str, arm: str) -> dict[int, pd.DataFrame]:
    """``{seed: (timesteps x robots) mean return over episodes}`` of an arm's finished runs, training robots."""
    found = {}
    for done in sorted((keep / task / "transfer" / task / arm).glob("seed-*/done.json")):
        for name in ("eval.csv.gz", "eval.csv"):
            if (done.parent / name).is_file():
                frame = pd.read_csv(done.parent / name)
                frame = frame[frame.split == "train"]
                found[int(done.parent.name.removeprefix("seed-"))] = frame.groupby(["timesteps", "robot"])["return"].mean().unstack("robot")
                break
    return found


def as_array(runs: dict[int, pd.DataFrame], robots: list[str], steps: np.ndarray) -> np.ndarray:
    """(seeds, robots, steps), each run read at ``steps`` (linear between its evaluations)."""
    out = []
    for table in runs.values():
        index = table.index.to_numpy(float)
        out.append([np.interp(steps, index, table[robot].to_numpy(float)) for robot in robots])
    return np.array(out)


def steps_to(steps: np.ndarray, curve: np.ndarray, level: float) -> float:
    """First step the curve (linear between evaluations) reaches ``level``; 0 at the start, inf if never."""
    if curve[0] >= level:
        return 0.0
    above = np.flatnonzero(curve >= level)
    if not len(above):
        return float("inf")
    i = above[0]
    t0, t1, y0, y1 = steps[i - 1], steps[i], curve[i - 1], curve[i]
    return float(t0 + (level - y0) / (y1 - y0) * (t1 - t0))


def ratio(reference: float, divmorph: float) -> float:
    """``reference / divmorph`` steps; inf when DivMorph needs none and the reference some, nan when neither needs any."""
    if divmorph == 0:
        return float("inf") if reference > 0 else float("nan")
    return reference / divmorph


def ratios(curves: dict[str, np.ndarray], steps: np.ndarray) -> dict[str, float]:
    """``{"direct": R→, "scratch": Rs}`` of one set of mean curves."""
    found = {}
    for name, arm in (("direct", "closest"), ("scratch", "scratch")):
        if arm in curves and "divmorph" in curves:
            level = curves[arm][-1]
            found[name] = ratio(steps_to(steps, curves[arm], level), steps_to(steps, curves["divmorph"], level))
    return found


def bootstrap_ratios(values: dict[str, np.ndarray], steps: np.ndarray, draws: int = BOOTSTRAP, seed: int = 0) -> dict[str, np.ndarray]:
    """(draws,) samples of each ratio, runs resampled per arm and robots once per draw for every arm."""
    rng = np.random.default_rng(seed)
    n_robots = next(iter(values.values())).shape[1]
    robot_counts = _counts(rng, n_robots, draws)
    run_counts = {arm: _counts(rng, len(v), draws) for arm, v in values.items()}
    out: dict[str, list[float]] = {}
    for b in range(draws):
        curves = {arm: np.einsum("s,r,srt->t", run_counts[arm][b], robot_counts[b], v) / (len(v) * n_robots) for arm, v in values.items()}
        for name, value in ratios(curves, steps).items():
            out.setdefault(name, []).append(value)
    return {name: np.array(samples) for name, samples in out.items()}


def verdict_of(low: float, high: float) -> str:
    if np.isnan(low) or np.isnan(high):
        return "undecided"
    return "holds" if low >= FACTOR else ("does not hold" if high < FACTOR else "undecided")


def read_task(keep: Path, task: str) -> dict[str, object] | None:
    runs = {arm: arm_runs(keep, task, arm) for arm in ARMS}
    runs = {arm: found for arm, found in runs.items() if found}
    if "divmorph" not in runs:
        return None
    robots = sorted(set.intersection(*(set(t.columns) for found in runs.values() for t in found.values())))
    end = min(t.index.max() for found in runs.values() for t in found.values())
    steps = np.unique(np.concatenate([t.index.to_numpy(float) for found in runs.values() for t in found.values()]))
    steps = steps[steps <= end]
    values = {arm: as_array(found, robots, steps) for arm, found in runs.items()}
    starts = json.loads((keep / task / "baseline.json").read_text()) if (keep / task / "baseline.json").is_file() else {}
    gains = {}
    for arm, v in values.items():
        if arm in starts:
            start = pd.DataFrame(starts[arm]).mean(axis=1).reindex(robots).to_numpy()[None]
            gains[arm] = (start.mean(), v[:, :, -1].mean(), v[:, :, -1].mean() - start.mean(), paired_run_interval(v[:, :, -1], start))
        else:  # a random init: each run's own step 0
            change = v[:, :, -1] - v[:, :, 0]
            gains[arm] = (v[:, :, 0].mean(), v[:, :, -1].mean(), change.mean(), run_interval(change))
    point = ratios({arm: v.mean(axis=(0, 1)) for arm, v in values.items()}, steps)
    samples = bootstrap_ratios(values, steps)
    readings = {}
    for name in point:
        low, high = interval(np.nan_to_num(samples[name], nan=1.0))  # neither arm needing a step: as fast, ratio 1
        readings[name] = (point[name], low, high, verdict_of(low, high))
    closest_rises = "closest" in gains and gains["closest"][3][0] > 0
    if "direct" in readings and not closest_rises:
        readings["direct"] = (*readings["direct"][:3], "no reference (MetaMorph→ does not rise)")
    seeds = {arm: len(found) for arm, found in runs.items()}
    return dict(task=task, steps=steps, values=values, gains=gains, readings=readings, seeds=seeds, robots=len(robots))


def overall(readings: list[str]) -> str:
    decided = [r for r in readings if not r.startswith("no reference")]
    if len(decided) < 2:
        return "not decidable at this scale (fewer than two tasks have a reference)"
    if sum(r == "does not hold" for r in decided) >= 2:
        return "does not hold"
    if sum(r == "holds" for r in decided) >= 2 and "does not hold" not in decided:
        return "holds"
    return "not decidable at this scale"


def figure(tasks: list[dict[str, object]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from divmorph.pipeline.metrics import bootstrap_curves

    fig, axes = plt.subplots(1, len(tasks), figsize=(5 * len(tasks), 3.8), squeeze=False)
    for ax, found in zip(axes[0], tasks):
        steps = found["steps"] / 1e6  # type: ignore[operator]
        for (arm, label), colour in zip(ARMS.items(), ("tab:green", "tab:blue", "tab:purple", "tab:orange")):
            if arm not in found["values"]:  # type: ignore[operator]
                continue
            v = found["values"][arm]  # type: ignore[index]
            low, high = np.percentile(bootstrap_curves(v), [2.5, 97.5], axis=0)
            ax.plot(steps, v.mean(axis=(0, 1)), color=colour, label=f"{label} ({len(v)} seeds)")
            ax.fill_between(steps, low, high, color=colour, alpha=0.2)
        ax.set_title(f"{found['task']}: training robots")
        ax.set_xlabel("env steps (millions)")
        ax.set_ylabel("mean return (deterministic)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--keep", type=Path, required=True, help="the race's kept runs, e.g. results/transfer-race/S2")
    parser.add_argument("--out", type=Path, default=None, help="where reading.md and curves.png go (default: --keep)")
    args = parser.parse_args(argv)
    out = args.out or args.keep
    tasks = [found for task in TASKS if (found := read_task(args.keep, task)) is not None]
    if not tasks:
        raise SystemExit(f"no finished DivMorph run under {args.keep}")
    lines = ["| task | arm | seeds | start | last | gain [95% CI, runs and robots] |", "|---|---|---:|---:|---:|---|"]
    for found in tasks:
        for arm, (start, last, gain, (low, high)) in found["gains"].items():  # type: ignore[attr-defined]
            lines.append(
                f"| {found['task']} | {ARMS[arm]} | {found['seeds'][arm]} | {start:.1f} | {last:.1f} | {gain:+.1f} [{low:+.1f}, {high:+.1f}] |"
            )  # type: ignore[index]
    lines += ["", "| task | reading | ratio of steps [95% CI] | verdict (line: 3x) |", "|---|---|---|---|"]
    names = {"direct": "1: MetaMorph→'s final return", "scratch": "2: scratch's final return"}
    verdicts: dict[str, list[str]] = {"direct": [], "scratch": []}
    for found in tasks:
        for name, (value, low, high, verdict) in found["readings"].items():  # type: ignore[attr-defined]
            lines.append(f"| {found['task']} | {names[name]} | {value:.2f} [{low:.2f}, {high:.2f}] | {verdict} |")
            verdicts[name].append(verdict)
    lines += [
        "",
        f"Against direct fine-tuning (the abstract's 3x): **{overall(verdicts['direct'])}**.",
        f"Against scratch (Sec. 6.1): **{overall(verdicts['scratch'])}**.",
    ]
    text = "\n".join(lines)
    out.mkdir(parents=True, exist_ok=True)
    (out / "reading.md").write_text(text + "\n")
    figure(tasks, out / "curves.png")
    print(text)
    return text


if __name__ == "__main__":
    main()
