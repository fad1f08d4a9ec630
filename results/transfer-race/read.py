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

The controls (``rule.md``, all on Escape) are read first: every fine-tuned arm at learning rate 0 must hold still
(its change's interval holds 0); MetaMorph→ from the Incline teacher's low start must rise where scratch rises; the
student with its selection freed is set beside the fixed gates (last against last, runs resampled per arm, robots
paired). A failed control makes both verdicts "not decided: our setup", naming it.
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


def arm_runs(keep: Path, task: str, arm: str, folder: str | None = None, split: str = "train") -> dict[int, pd.DataFrame]:
    """``{seed: (timesteps x robots) mean return over episodes}`` of an arm's finished runs on one robot split
    (``train`` decides, ``novel`` is reported beside); ``folder`` the run folder when it is not the task's own (a
    control's, e.g. ``Escape-lr0``)."""
    found = {}
    for done in sorted((keep / (folder or task) / "transfer" / task / arm).glob("seed-*/done.json")):
        for name in ("eval.csv.gz", "eval.csv"):
            if (done.parent / name).is_file():
                frame = pd.read_csv(done.parent / name)
                frame = frame[frame.split == split]
                if frame.empty:
                    break
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


def on_common_grid(runs: dict[str, dict[int, pd.DataFrame]]) -> tuple[dict[str, np.ndarray], list[str], np.ndarray]:
    """``({name: (seeds, robots, steps)}, robots, steps)``: several arms' runs on the robots they all have, at every
    evaluation step up to the shortest run's last."""
    tables = [t for found in runs.values() for t in found.values()]
    robots = sorted(set.intersection(*(set(t.columns) for t in tables)))
    end = min(t.index.max() for t in tables)
    steps = np.unique(np.concatenate([t.index.to_numpy(float) for t in tables]))
    steps = steps[steps <= end]
    return {name: as_array(found, robots, steps) for name, found in runs.items()}, robots, steps


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


def starts_of(keep: Path, folder: str) -> dict[str, dict]:
    """The fine-tuned arms' many-draw starts kept for a run folder (``baseline.json``), by arm; empty if none yet."""
    path = keep / folder / "baseline.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def gain(values: np.ndarray, start: dict | None, robots: list[str]) -> tuple[float, float, float, tuple[float, float]]:
    """``(start, last, last - start, 95% interval)`` of an arm's (seeds, robots, steps) curves: against its many-draw
    start when it has one (paired by robot), else each run's own step 0 (a random init)."""
    last = values[:, :, -1]
    if start is not None:
        begin = pd.DataFrame(start).mean(axis=1).reindex(robots).to_numpy()[None]
        return begin.mean(), last.mean(), last.mean() - begin.mean(), paired_run_interval(last, begin)
    change = last - values[:, :, 0]
    return values[:, :, 0].mean(), last.mean(), change.mean(), run_interval(change)


def read_task(keep: Path, task: str) -> dict[str, object] | None:
    runs = {arm: arm_runs(keep, task, arm) for arm in ARMS}
    runs = {arm: found for arm, found in runs.items() if found}
    if "divmorph" not in runs:
        return None
    values, robots, steps = on_common_grid(runs)
    starts = starts_of(keep, task)
    gains = {arm: gain(v, starts.get(arm), robots) for arm, v in values.items()}
    means = {arm: v.mean(axis=(0, 1)) for arm, v in values.items()}
    point = ratios(means, steps)
    # each arm's steps to the two levels of the readings (mean curves): the table's last columns
    levels = {name: means[arm][-1] for name, arm in (("direct", "closest"), ("scratch", "scratch")) if arm in means}
    reach = {arm: {name: steps_to(steps, curve, level) for name, level in levels.items()} for arm, curve in means.items()}
    samples = bootstrap_ratios(values, steps)
    readings = {}
    for name in point:
        low, high = interval(
            np.nan_to_num(samples[name], nan=1.0, posinf=np.inf, neginf=-np.inf)
        )  # neither arm needing a step: as fast, ratio 1
        readings[name] = (point[name], low, high, verdict_of(low, high))
    closest_rises = "closest" in gains and gains["closest"][3][0] > 0
    if "direct" in readings and not closest_rises:
        readings["direct"] = (*readings["direct"][:3], "no reference (MetaMorph→ does not rise)")
    seeds = {arm: len(found) for arm, found in runs.items()}
    return dict(task=task, steps=steps, values=values, gains=gains, readings=readings, seeds=seeds, robots=len(robots), reach=reach)


def read_held_out(keep: Path, task: str) -> dict[str, object] | None:
    """The held-out robots' curves and each arm's gain over its own runs' step 0 (the many-draw starts are measured
    on the training robots only): reported beside the reading, deciding nothing."""
    runs = {arm: arm_runs(keep, task, arm, split="novel") for arm in ARMS}
    runs = {arm: found for arm, found in runs.items() if found}
    if "divmorph" not in runs:
        return None
    values, robots, steps = on_common_grid(runs)
    gains = {arm: gain(v, None, robots) for arm, v in values.items()}
    return dict(task=task, steps=steps, values=values, gains=gains, seeds={arm: len(f) for arm, f in runs.items()}, robots=len(robots))


def _gain_cells(g: tuple[float, float, float, tuple[float, float]]) -> str:
    """``start | last | gain [low, high]`` of a :func:`gain` for a table row."""
    start, last, change, (low, high) = g
    return f"{start:.1f} | {last:.1f} | {change:+.1f} [{low:+.1f}, {high:+.1f}]"


def _steps(value: float | None) -> str:
    if value is None:
        return "--"
    if value == 0:
        return "0 (its start)"
    return "never" if np.isinf(value) else f"{value / 1e3:,.0f}k"


def overall(readings: list[str]) -> str:
    decided = [r for r in readings if not r.startswith("no reference")]
    if len(decided) < 2:
        return "not decidable at this scale (fewer than two tasks have a reference)"
    if sum(r == "does not hold" for r in decided) >= 2:
        return "does not hold"
    if sum(r == "holds" for r in decided) >= 2 and "does not hold" not in decided:
        return "holds"
    return "not decidable at this scale"


#: The rule's controls, all on Escape: the run folder and arm of each, and what its line reads.
CONTROL_TASK = "Escape"
LOW_START = "the dense low start"
FREED = "divmorph-finetuned"


def _curves(keep: Path, arms: dict[str, tuple[str, str]]) -> tuple[dict[str, np.ndarray], list[str]] | None:
    """``({name: (seeds, robots, steps)}, robots)`` of several (folder, arm) run sets on the robots and steps they all
    have, or ``None`` when one has no finished run."""
    runs = {name: arm_runs(keep, CONTROL_TASK, arm, folder) for name, (folder, arm) in arms.items()}
    if not all(runs.values()):
        return None
    values, robots, _ = on_common_grid(runs)
    return values, robots


def read_controls(keep: Path) -> list[dict[str, object]]:
    """The rule's controls, one row per control and arm: ``control``, ``arm``, ``seeds``, ``gain`` (as :func:`gain`),
    ``reading`` and ``failed`` (a failure of our setup: a start that moves at rate 0, or a low start that does not
    recover where scratch climbs). Controls with no finished run yet are left out."""
    rows: list[dict[str, object]] = []
    race_starts = starts_of(keep, CONTROL_TASK)
    for arm in ("divmorph", "closest", "distilled"):
        found = _curves(keep, {arm: (f"{CONTROL_TASK}-lr0", arm)})
        if found is None:
            continue
        (values,), robots = list(found[0].values()), found[1]
        g = gain(values, starts_of(keep, f"{CONTROL_TASK}-lr0").get(arm), robots)
        still = g[3][0] <= 0 <= g[3][1]
        reading = "holds still" if still else "moves at learning rate 0: our setup"
        rows.append(dict(control="learning rate 0", arm=ARMS[arm], seeds=len(values), gain=g, reading=reading, failed=not still))
    found = _curves(keep, {"low": (f"{CONTROL_TASK}-lowstart", "closest"), "scratch": (CONTROL_TASK, "scratch")})
    if found is not None:
        values, robots = found
        g = gain(values["low"], starts_of(keep, f"{CONTROL_TASK}-lowstart").get("closest"), robots)
        scratch = gain(values["scratch"], None, robots)
        if g[3][0] > 0:
            reading, failed = "recovers from its low start", False
        elif scratch[3][0] > 0:
            reading, failed = (
                f"does not recover where scratch climbs ({scratch[2]:+.1f} [{scratch[3][0]:+.1f}, {scratch[3][1]:+.1f}]): our setup",
                True,
            )
        else:
            reading, failed = "neither it nor scratch rises: says nothing", False
        label = "MetaMorph→ from the Incline teacher (told Incline's instruction)"
        rows.append(dict(control=LOW_START, arm=label, seeds=len(values["low"]), gain=g, reading=reading, failed=failed))
    found = _curves(keep, {"freed": (CONTROL_TASK, FREED), "fixed": (CONTROL_TASK, "divmorph")})
    if found is not None:
        values, robots = found
        start = race_starts.get("divmorph")  # the freed arm starts from the same student
        g = gain(values["freed"], start, robots)
        low, high = paired_run_interval(values["freed"][:, :, -1], values["fixed"][:, :, -1])
        difference = values["freed"][:, :, -1].mean() - values["fixed"][:, :, -1].mean()
        side = "freed gains more" if low > 0 else ("fixed gates gain more" if high < 0 else "within noise of fixed gates")
        reading = f"last minus fixed gates' last {difference:+.1f} [{low:+.1f}, {high:+.1f}]: {side}"
        label = "DivMorph with its selection freed (router and every weight)"
        rows.append(dict(control="the selection freed", arm=label, seeds=len(values["freed"]), gain=g, reading=reading, failed=False))
    return rows


#: the seeds each variant runs (``lowstart-rule.md``)
DIAGNOSIS_SEEDS = 3
#: ``lowstart-rule.md``'s variants of the low start, in the order the rule reads them
DIAGNOSIS = {
    "lowstart-W": "W: critic first (100,352 critic-only steps)",
    "lowstart-L": "L: observation statistics learning",
    "lowstart-S": "S: scratch's rate (lin_1e-3)",
}


def low_start_step_0(keep: Path) -> dict[str, dict[str, float]] | None:
    """The low start's step-0 evaluations, ``{seed: {robot: return}}``, as the variants' start until its many-draw
    start is measured (``None`` without low-start runs). The same model on the same robots before any update: a
    variant's own first evaluation can come after it has changed something (statistics learning updates the
    statistics during its first rollout)."""
    runs = arm_runs(keep, CONTROL_TASK, "closest", f"{CONTROL_TASK}-lowstart")
    if not runs:
        return None
    return {str(seed): frame.sort_index().iloc[0].to_dict() for seed, frame in runs.items()}  # rows: timesteps


def diagnosis_complete(rows: list[dict[str, object]]) -> bool:
    """Whether every variant of the diagnosis has all its seeds in (``lowstart-rule.md``: seeds 0-2)."""
    return len(rows) == len(DIAGNOSIS) and all(int(row["seeds"]) >= DIAGNOSIS_SEEDS for row in rows)  # type: ignore[call-overload]


def read_diagnosis(keep: Path) -> tuple[list[dict[str, object]], str | None]:
    """The low start's diagnosis (``lowstart-rule.md``): each variant's gain against the low start's many-draw start
    (the low start's step-0 evaluations until that is measured), and the block the first recovering variant names (``None`` while none
    has recovered). Variants with no finished run are left out."""
    rows: list[dict[str, object]] = []
    start = starts_of(keep, f"{CONTROL_TASK}-lowstart").get("closest") or low_start_step_0(keep)
    for name, label in DIAGNOSIS.items():
        found = _curves(keep, {name: (f"{CONTROL_TASK}-{name}", "closest")})
        if found is None:
            continue
        (values,), robots = list(found[0].values()), found[1]
        g = gain(values, start, robots)
        reading = "recovers" if g[3][0] > 0 else "does not recover"
        rows.append(dict(control="low-start diagnosis", arm=label, seeds=len(values), gain=g, reading=reading, failed=False))
    block = next((str(row["arm"]) for row in rows if row["reading"] == "recovers"), None)
    return rows, block


def figure(tasks: list[dict[str, object]], held_out: list[dict[str, object]], out: Path) -> None:
    """Mean curves with 95% bands (runs and robots resampled): training robots above, held-out robots below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from divmorph.pipeline.metrics import bootstrap_curves

    rows = [("training robots", tasks)] + ([("held-out robots", held_out)] if held_out else [])
    fig, axes = plt.subplots(len(rows), len(tasks), figsize=(5 * len(tasks), 3.4 * len(rows) + 0.6), squeeze=False)
    colours = dict(zip(ARMS, ("tab:green", "tab:blue", "tab:purple", "tab:orange")))
    seeds = {arm: max(found["seeds"].get(arm, 0) for found in tasks) for arm in ARMS}  # type: ignore[attr-defined]
    for row, (split, readings) in zip(axes, rows):
        by_task = {found["task"]: found for found in readings}
        for ax, task in zip(row, (found["task"] for found in tasks)):
            ax.set_title(f"{task}: {split}")
            ax.set_xlabel("env steps (millions)")
            ax.set_ylabel("mean return (deterministic)")
            found = by_task.get(task)
            if found is None:
                continue
            steps = found["steps"] / 1e6  # type: ignore[operator]
            for arm, v in found["values"].items():  # type: ignore[attr-defined]
                low, high = np.percentile(bootstrap_curves(v), [2.5, 97.5], axis=0)
                ax.plot(steps, v.mean(axis=(0, 1)), color=colours[arm])
                ax.fill_between(steps, low, high, color=colours[arm], alpha=0.2)
    handles = [plt.Line2D([], [], color=colours[arm]) for arm in ARMS if seeds[arm]]
    labels = [f"{ARMS[arm]} ({seeds[arm]} seed{'s' if seeds[arm] > 1 else ''})" for arm in ARMS if seeds[arm]]
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
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
    lines = [
        "| task | arm | seeds | start | last | gain [95% CI, runs and robots] | steps to MetaMorph→'s last | steps to scratch's last |",
        "|---|---|---:|---:|---:|---|---:|---:|",
    ]
    for found in tasks:
        for arm, g in found["gains"].items():  # type: ignore[attr-defined]
            reach = found["reach"][arm]  # type: ignore[index]
            lines.append(
                f"| {found['task']} | {ARMS[arm]} | {found['seeds'][arm]} | {_gain_cells(g)} "  # type: ignore[index]
                f"| {_steps(reach.get('direct'))} | {_steps(reach.get('scratch'))} |"
            )
    lines += ["", "| task | reading | ratio of steps [95% CI] | verdict (line: 3x) |", "|---|---|---|---|"]
    names = {"direct": "1: MetaMorph→'s final return", "scratch": "2: scratch's final return"}
    verdicts: dict[str, list[str]] = {"direct": [], "scratch": []}
    for found in tasks:
        for name, (value, low, high, verdict) in found["readings"].items():  # type: ignore[attr-defined]
            lines.append(f"| {found['task']} | {names[name]} | {value:.2f} [{low:.2f}, {high:.2f}] | {verdict} |")
            verdicts[name].append(verdict)
    held_out = [found for task in TASKS if (found := read_held_out(args.keep, task)) is not None]
    lines += ["", "Held-out robots (reported beside, deciding nothing; start: each run's own step 0):", ""]
    lines += ["| task | arm | seeds | start | last | gain [95% CI, runs and robots] |", "|---|---|---:|---:|---:|---|"]
    for found in held_out:
        for arm, g in found["gains"].items():  # type: ignore[attr-defined]
            lines.append(f"| {found['task']} | {ARMS[arm]} | {found['seeds'][arm]} | {_gain_cells(g)} |")  # type: ignore[index]
    controls = read_controls(args.keep)
    failed = [str(row["control"]) for row in controls if row["failed"]]
    lines += ["", f"Controls ({CONTROL_TASK}; read first: a failure names our setup):", ""]
    lines += ["| control | arm | seeds | start | last | change [95% CI] | reading |", "|---|---|---:|---:|---:|---|---|"]
    for row in controls:
        lines.append(f"| {row['control']} | {row['arm']} | {row['seeds']} | {_gain_cells(row['gain'])} | {row['reading']} |")  # type: ignore[arg-type]
    if not controls:
        lines.append("| (no control finished yet) | | | | | | |")
    diagnosis, block = read_diagnosis(args.keep)
    if diagnosis:
        lines += ["", "The low start's diagnosis (`lowstart-rule.md`; beside the verdict, naming the block):", ""]
        lines += ["| variant | seeds | start | last | gain [95% CI] | reading |", "|---|---:|---:|---:|---|---|"]
        for row in diagnosis:
            lines.append(f"| {row['arm']} | {row['seeds']} | {_gain_cells(row['gain'])} | {row['reading']} |")  # type: ignore[arg-type]
        lines.append("")
        if block:
            lines.append(f"Block named: {block}; the race's fine-tuned arms rerun with it (`lowstart-rule.md`).")
        elif diagnosis_complete(diagnosis):
            lines.append("No variant recovers on its seeds: the block is the trained start itself at this scale.")
        else:
            lines.append("No variant recovers (yet): the block is not named.")
    verdict = {name: overall(found) for name, found in verdicts.items()}
    if failed == [LOW_START] and block is None and diagnosis_complete(diagnosis):
        # lowstart-rule.md's last branch: no part of the setup we can change lets a trained wrong start recover
        verdict = {name: f"not decidable at this scale (the control that stops it: {LOW_START})" for name in verdict}
    elif failed:
        verdict = {name: f"not decided: our setup (failed: {', '.join(failed)})" for name in verdict}
    lines += [
        "",
        f"Against direct fine-tuning (the abstract's 3x): **{verdict['direct']}**.",
        f"Against scratch (Sec. 6.1): **{verdict['scratch']}**.",
    ]
    text = "\n".join(lines)
    out.mkdir(parents=True, exist_ok=True)
    (out / "reading.md").write_text(text + "\n")
    figure(tasks, held_out, out / "curves.png")
    print(text)
    return text


if __name__ == "__main__":
    main()
