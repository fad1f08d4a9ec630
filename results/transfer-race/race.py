"""The transfer race of ``rule.md``: every arm x task x seed as a resumable run, worked by one process per core.

    python results/transfer-race/make_source.py RUNS/source
    python results/transfer-race/race.py --setting S2 --runs RUNS --keep results/transfer-race/S2   # once per core

The setting's terms (steps per run, robots per run, rollout) are the setting ladder's (``SETTINGS``, as in
``../transfer-setting/rule.md``). Each task has its run folder ``RUNS/<task>`` branched from ``RUNS/source`` (PointNav
with its goal bounded at 10 m). The jobs are a list in order (``jobs()``: seed 0 of every arm and task first, the
controls, each fine-tuned arm's many-draw start, then seeds 1 and 2); a worker claims the first job nobody holds
(``RUNS/claims/<job>``, made atomically) whose prerequisite is done -- a start waits for its first run to have begun -- and runs it in a process of
its own. A finished run is packed into ``--keep`` (``tools/pack_transfer_runs.py``: evaluations and the table of its
updates, no model), and a start's ``baseline.json`` copied there, so a restart of the machine loses at most the runs
in flight, which resume from their checkpoints if their folders survive. Ctrl-C or SIGTERM stops the worker and its
job at a checkpoint; start the workers again with ``--fresh-claims``.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

STUDY = Path(__file__).resolve().parent
ROOT = STUDY.parents[1]
SCRIPT = ROOT / "results" / "finetune-known-task" / "finetune_known_task.py"
TASKS = {"Escape": [], "Exploration": [], "PointNav": ["goal_range=10"]}
ARMS = ["divmorph", "closest", "distilled", "scratch"]
FINE_TUNED = ["divmorph", "closest", "distilled"]
SEEDS = [0, 1, 2]
EVAL = ["transfer.eval_episodes=5", "transfer.eval_splits=[train, novel]"]


@dataclass(frozen=True)
class Setting:
    """A rung of the setting ladder: steps per run and the profile settings that make it."""

    steps: int
    sets: list[str] = field(default_factory=list)


SETTINGS = {
    "S1": Setting(602_112),
    "S2": Setting(602_112, ["transfer.train_robots=eval"]),
    "S3": Setting(1_204_224, ["transfer.overrides.n_envs=8", "transfer.overrides.batch_size=1024"]),
    "S4": Setting(3_010_560, ["transfer.overrides.n_envs=16", "transfer.overrides.batch_size=2048"]),
}
EVAL_EVERY = 100_352


#: The rule's controls, each a run folder of its own beside the race's (``<task>-<control>``): what they set, and
#: the arms and seeds they run. ``lowstart``: MetaMorph→ from the Incline teacher (told Incline's instruction, so the
#: closest teacher is Incline's; Escape's start near 0.7); ``lr0``: every fine-tuned arm at learning rate 0 (the start
#: must hold); ``freed`` (in the race's own Escape folder): the student fine-tuned with its router and so its
#: Transformer's selection free.
INCLINE = "Walk forward as fast as possible up a ten degree incline."
CONTROLS = {
    "lowstart": ([f"transfer.instructions.Escape={INCLINE}"], ["closest"], SEEDS),
    "lr0": (["transfer.finetune_overrides.learning_rate=0"], FINE_TUNED, SEEDS[:1]),
    "freed": ([], ["divmorph-finetuned"], SEEDS),
}
#: ``lowstart-rule.md``: if the dense low start fails, which part of the setup blocks it -- the low start again with one
#: knob changed each (``--study lowstart-diagnosis``, a run folder per variant, seeds 0-2 of every variant in turn).
DIAGNOSIS = {
    "lowstart-W": [*CONTROLS["lowstart"][0], "transfer.critic_warmup=100352"],
    "lowstart-L": [*CONTROLS["lowstart"][0], "transfer.freeze_statistics=false"],
    "lowstart-S": [*CONTROLS["lowstart"][0], "transfer.finetune_overrides.learning_rate=lin_1e-3"],
}
#: every run folder's settings beyond the race's own, by control or variant name
SETS = {**{name: sets for name, (sets, _, _) in CONTROLS.items()}, **DIAGNOSIS}
STUDIES = ["race", "lowstart-diagnosis"]


@dataclass(frozen=True)
class Job:
    task: str
    arm: str
    seed: int | None  # None: the arm's many-draw start
    control: str = ""

    @property
    def folder(self) -> str:
        """The run folder's name: the task's, or ``<task>-<control>`` for a control with settings of its own."""
        return f"{self.task}-{self.control}" if self.control and SETS[self.control] else self.task

    @property
    def name(self) -> str:
        kind = "start" if self.seed is None else f"seed-{self.seed}"
        return f"{self.task}-{self.control + '-' if self.control else ''}{self.arm}-{kind}"


def jobs(study: str = "race") -> list[Job]:
    """The race's jobs in order, or the low-start diagnosis's (``study``). The race: seed 0 of the race; every seed of the dense low start (its failure alone turns both verdicts, so it is known
    early); the other controls' first seeds; every start; the race's other seeds; the other controls' other seeds."""
    if study == "lowstart-diagnosis":
        return [Job("Escape", "closest", seed, name) for seed in SEEDS for name in DIAGNOSIS]
    first = [Job(task, arm, SEEDS[0]) for task in TASKS for arm in ARMS]
    _, arms, seeds = CONTROLS["lowstart"]
    low_start = [Job("Escape", arm, seed, "lowstart") for seed in seeds for arm in arms]
    others = {name: control for name, control in CONTROLS.items() if name != "lowstart"}
    controls_first = [Job("Escape", arm, seeds[0], name) for name, (_, arms, seeds) in others.items() for arm in arms]
    starts = [Job(task, arm, None) for task in TASKS for arm in FINE_TUNED] + [Job("Escape", "closest", None, "lowstart")]
    rest = [Job(task, arm, seed) for seed in SEEDS[1:] for task in TASKS for arm in ARMS]
    controls_rest = [Job("Escape", arm, seed, name) for name, (_, arms, seeds) in others.items() for seed in seeds[1:] for arm in arms]
    return first + low_start + controls_first + starts + rest + controls_rest


def command(job: Job, setting: Setting, runs: Path) -> list[str]:
    sets = [*setting.sets, *EVAL, *TASKS[job.task], *(SETS[job.control] if job.control else [])]
    line = [sys.executable, str(SCRIPT), "--source", str(runs / "source"), "--out", str(runs / job.folder), "--task", job.task]
    line += ["--steps", str(setting.steps), "--eval-every", str(EVAL_EVERY), "--arms", job.arm]
    for item in sets:
        line += ["--set", item]
    if job.seed is None:
        return [*line, "--seeds", str(SEEDS[0]), "--baseline-seeds", "5", "--baseline-only"]
    return [*line, "--seeds", str(job.seed)]


def run_folder(runs: Path, job: Job, seed: int) -> Path:
    return runs / job.folder / "transfer" / job.task / job.arm / f"seed-{seed}"


def ready(job: Job, runs: Path) -> bool:
    """A start needs its arm's first run begun (its ``source.json``); a run can always start."""
    return job.seed is not None or (run_folder(runs, job, SEEDS[0]) / "source.json").is_file()


def done(job: Job, runs: Path, keep: Path) -> bool:
    if job.seed is None:
        path = keep / job.folder / "baseline.json"
        return path.is_file() and job.arm in json.loads(path.read_text())
    return (keep / job.folder / "transfer" / job.task / job.arm / f"seed-{job.seed}" / "done.json").is_file()


def keep_finished(job: Job, runs: Path, keep: Path) -> None:
    """Pack the task's finished runs, or copy its starts, into ``keep`` (one packer at a time)."""
    keep.mkdir(parents=True, exist_ok=True)
    with open(keep / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if job.seed is None:
            (keep / job.folder).mkdir(exist_ok=True)
            shutil.copyfile(runs / job.folder / "baseline.json", keep / job.folder / "baseline.json")
        else:
            pack = [sys.executable, str(ROOT / "tools" / "pack_transfer_runs.py"), str(keep), f"{runs / job.folder}={job.folder}"]
            subprocess.run(pack, check=True)


def work(setting: Setting, runs: Path, keep: Path, poll: float, study: str = "race") -> None:
    claims = runs / "claims"
    claims.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    while True:
        waiting = False
        for job in jobs(study):
            if done(job, runs, keep) or (claims / job.name).exists():
                continue
            if not ready(job, runs):
                waiting = True
                continue
            try:
                (claims / job.name).mkdir()
            except FileExistsError:
                continue
            print(f"[race] {job.name}: {' '.join(command(job, setting, runs))}", flush=True)
            code = subprocess.run(command(job, setting, runs), cwd=ROOT, env=env).returncode
            if code != 0:
                print(f"[race] {job.name} stopped with exit status {code}; this worker stops", flush=True)
                raise SystemExit(code)
            keep_finished(job, runs, keep)
            break
        else:
            if not waiting:
                print("[race] every job is done or held by another worker", flush=True)
                return
            time.sleep(poll)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--setting", required=True, choices=list(SETTINGS), help="the ladder's chosen setting")
    parser.add_argument("--runs", type=Path, required=True, help="where the run folders go (RUNS/source made first)")
    parser.add_argument("--keep", type=Path, required=True, help="the tracked folder of the finished runs, packed")
    parser.add_argument("--fresh-claims", action="store_true", help="forget the claims of stopped workers first")
    parser.add_argument("--poll", type=float, default=60.0, help="seconds between looks for a job that cannot start yet")
    parser.add_argument("--list", action="store_true", help="print the jobs' commands and stop")
    parser.add_argument("--study", choices=STUDIES, default="race", help="the race, or the low start's diagnosis (lowstart-rule.md)")
    args = parser.parse_args(argv)
    setting = SETTINGS[args.setting]
    if args.list:
        for job in jobs(args.study):
            print(job.name, "done" if done(job, args.runs, args.keep) else "", " ".join(command(job, setting, args.runs)))
        return
    if not (args.runs / "source" / "run.json").is_file():
        raise SystemExit(f"no race source in {args.runs}: run python results/transfer-race/make_source.py {args.runs / 'source'} first")
    if args.fresh_claims:
        shutil.rmtree(args.runs / "claims", ignore_errors=True)
    work(setting, args.runs.resolve(), args.keep.resolve(), args.poll, args.study)


if __name__ == "__main__":
    main()
