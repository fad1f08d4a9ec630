"""Torch's thread count for small policies, on an idle and on a busy machine.

Torch starts one intra-op thread per core. A small policy's ops (a width-32 to 64 Transformer over a
robot's ~10 limb tokens) are too short to split, so extra threads only wait for each other, and on a
machine whose cores are busy with other jobs each op waits for every thread to be scheduled. This
measures what a user meets -- one ``predict`` of ``DivMorphPolicy`` (``preset="small"``) and the
README's ``PPO(...).learn(128)`` -- with ``torch.set_num_threads(1)`` and with torch's default, each
in a fresh process, first with no extra load, then with ``--load`` busy-looping processes of its own
(each pinned to nothing, as other users' jobs would be). Rounds alternate the two settings.

Usage::

    python benchmarks/threads.py [--load 6] [--rounds 3]

Writes ``results/threads.md``.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import platform
import statistics
import subprocess
import sys
from datetime import date
from pathlib import Path

RESULTS = Path(__file__).resolve().parent.parent / "results" / "threads.md"

#: One measurement, in a fresh process: ``argv[1]`` is the thread count (0: torch's default).
PROBE = r"""
import json, sys, time
import torch
if int(sys.argv[1]):
    torch.set_num_threads(int(sys.argv[1]))
import gymnasium as gym
from stable_baselines3 import PPO
from stable_baselines3.common.monitor import Monitor
import sb3_divmorph  # noqa: F401
from unimal_envs.morphology.loader import morphology_files
env = Monitor(gym.make("unimal_envs:Unimal-Escape-v0", morphologies=morphology_files("train")[:3]))
model = PPO("DivMorphPolicy", env, n_steps=64, batch_size=64, policy_kwargs=dict(preset="small"), seed=0)
start = time.perf_counter()
model.learn(128)
learn = time.perf_counter() - start
obs, _ = env.reset(seed=0)
model.predict(obs, deterministic=True)
times = []
for _ in range(30):
    start = time.perf_counter()
    model.predict(obs, deterministic=True)
    times.append(time.perf_counter() - start)
times.sort()
print(json.dumps({"threads": torch.get_num_threads(), "learn_s": learn, "predict_ms": 1000 * times[len(times) // 2]}))
"""


def _busy() -> None:
    while True:
        pass


def measure(threads: int) -> dict:
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "HF_HUB_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}
    done = subprocess.run([sys.executable, "-c", PROBE, str(threads)], capture_output=True, text=True, env=env, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--load", type=int, default=6, help="busy processes started for the loaded measurement")
    parser.add_argument("--rounds", type=int, default=3, help="measurements per setting and load (median kept)")
    args = parser.parse_args(argv)
    rows = []
    for load in (0, args.load):
        busy = [multiprocessing.Process(target=_busy, daemon=True) for _ in range(load)]
        for p in busy:
            p.start()
        try:
            found: dict[int, list[dict]] = {1: [], 0: []}
            for _ in range(args.rounds):
                for threads in found:
                    found[threads].append(measure(threads))
        finally:
            for p in busy:
                p.terminate()
        loadavg = os.getloadavg()[0]
        for threads, runs in found.items():
            rows.append(
                dict(
                    load=load,
                    loadavg=loadavg,
                    threads=runs[0]["threads"],
                    setting="torch.set_num_threads(1)" if threads else "torch's default",
                    predict_ms=statistics.median(r["predict_ms"] for r in runs),
                    learn_s=statistics.median(r["learn_s"] for r in runs),
                )
            )
            print(rows[-1], flush=True)
    lines = [
        "# Torch threads for small policies, idle and busy",
        "",
        f"`python benchmarks/threads.py --load {args.load} --rounds {args.rounds}` on {date.today()}, "
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores; median of {args.rounds} fresh processes per cell. "
        '`DivMorphPolicy` (`preset="small"`) on Escape with 3 robots: one deterministic `predict`, and '
        "`PPO(..., n_steps=64, batch_size=64).learn(128)` (the README's example). 'busy' adds the script's own "
        "busy-looping processes (other users' jobs); the load average is read at the end of each block.",
        "",
        "| machine | extra busy processes | load average | torch threads | setting | predict (ms) | learn(128) (s) |",
        "|---|---:|---:|---:|---|---:|---:|",
    ]
    for r in rows:
        state = "busy" if r["load"] else "as found"
        lines.append(
            f"| {state} | {r['load']} | {r['loadavg']:.1f} | {r['threads']} | {r['setting']} | {r['predict_ms']:.1f} | {r['learn_s']:.1f} |"
        )
    RESULTS.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
