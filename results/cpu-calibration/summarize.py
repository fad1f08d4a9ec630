# Run from the repository root: python results/cpu-calibration/summarize.py
"""Deterministic FT returns of both calibration teachers on their 10 training robots (official 1-10)."""
import json, platform, os, time, csv, io
import numpy as np, torch as th
th.set_num_threads(1)
from pathlib import Path
from divmorph.pipeline import load_profile
from divmorph.pipeline.evaluate import evaluate_model
from divmorph.pipeline.files import read_done
from divmorph.pipeline.robots import profile_robots
root = Path("results/cpu-calibration")
rows, lines = [], []
for name in ("calib-lr3e-4", "calib-lr1e-3"):
    profile = load_profile(name, root / "profiles.yml")
    robots = profile_robots(profile, "train")
    folder = root / name / "teachers" / "FT"
    res = evaluate_model(folder, "FT", robots, 1, 1000, 0)
    for r in res:
        rows.append({"run": name, **r})
    rets = np.array([r["return"] for r in res])
    prog = list(csv.DictReader(open(folder / "logs" / "run-0" / "progress.csv")))
    wall = float(prog[-1]["time/time_elapsed"])
    lines.append((name, profile.teachers.overrides["learning_rate"], rets.mean(), np.median(rets), int((rets >= 500).sum()), wall, res))
buf = io.StringIO(); w = csv.DictWriter(buf, fieldnames=list(rows[0])); w.writeheader(); w.writerows(rows)
(root / "returns.csv").write_text(buf.getvalue())
out = ["# cpu profile calibration: FT teacher learning rate", "",
       "Two MetaMorph FT teachers (width 32, 1 layer, FFN 128; PPO 4 envs x 512 steps, batch 512, 4 epochs, fixed std 0.9)",
       "on the first 10 official UNIMAL training robots, 1,000-step episodes, 1.2M env steps each, seed 0 (teacher seed 1001),",
       "run side by side (one per core, niced, sharing the 2 cores with other work) on the 2-core CPU machine.",
       "Only the learning-rate schedule differs. Deterministic return, one episode per training robot (no novel robot was looked at).", "",
       "Commands:", "```bash",
       *[f"divmorph teachers --profile {n} --profiles results/cpu-calibration/profiles.yml --out results/cpu-calibration/{n} --no-progress" for n, *_ in lines],
       "```", "",
       "| run | learning rate | mean return | median | robots >= 500 | wall time (s, shared CPU) |", "|---|---|---|---|---|---|"]
for name, lr, mean, med, n500, wall, res in lines:
    out.append(f"| {name} | {lr} | {mean:.0f} | {med:.0f} | {n500} / 10 | {wall:.0f} |")
out += ["", "Per robot (return / episode length):", "", "| robot | " + " | ".join(n for n, *_ in lines) + " |", "|---|" + "---|" * len(lines)]
by_robot = [{r["morphology"]: r for r in l[6]} for l in lines]
for robot in sorted(by_robot[0]):
    out.append(f"| {robot} | " + " | ".join(f"{b[robot]['return']:.0f} / {b[robot]['length']}" for b in by_robot) + " |")
out += ["", f"Written {time.strftime('%Y-%m-%d %H:%M')} on {platform.machine()} ({os.cpu_count()} cores), torch {th.__version__}.",
        "Short episodes are falls (termination): a third of the official robots fall at zero torque and must learn to stand first.", "",
        "The two teachers' models are not in the repository (tracked files stay under 24 MiB): the commands above train them again "
        "(~2,760 s each); the calib-lr1e-3 teacher has bit for bit the weights and statistics of `results/cpu/teachers/FT` (its model in git history since 2026-11-26). "
        "`summarize.py` needs both.", ""]
(root / "summary.md").write_text("\n".join(out))
print("\n".join(out))
