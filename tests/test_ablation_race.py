"""The ablation race's job list (``results/transfer-ablations/ablation_race.sh``), worked by two workers at once with a stand-in Python."""

from __future__ import annotations

import json
import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "results" / "transfer-ablations" / "ablation_race.sh"
#: a study's script of results/: the evidence's suite (`make test-results`), not the library's
pytestmark = pytest.mark.shipped_results
STUDENTS = {"no-kdiv-transformer", "no-kdiv-decoder", "no-orthogonality", "divmorph"}
INCLINE = "transfer.instructions.Escape=Walk forward as fast as possible up a ten degree incline."
G_TERMS = ["transfer.eval_episodes=5", "transfer.learngene_lr_scale=1", "transfer.rotation_lr_scale=0"]

# Logs each call (its arguments as JSON) and makes the files the real calls make: `divmorph branch` a run.json and
# robot_sets.json, `divmorph distill` (after a moment) the student's model, statistics, log and done.json -- or
# fails, for the student named in FAIL_DISTILL, or is stopped by SIGTERM, for STOP_DISTILL's --, a race run its
# --out's run.json, its seed's source.json, eval.csv, log and done.json, a start baseline.json, and the packer the
# packed form of each finished run.
STAND_IN = f"""#!{sys.executable}
import json, os, sys, time
from pathlib import Path

argv = sys.argv[1:]
work = Path(os.environ["WORK"])
with open(work / "calls.log", "a") as log:
    log.write(json.dumps(argv) + "\\n")
option = {{argv[i]: argv[i + 1] for i in range(len(argv) - 1) if argv[i].startswith("--")}}
if argv[:3] == ["-m", "divmorph.cli", "branch"]:
    Path(option["--out"]).mkdir(parents=True, exist_ok=True)
    for name in ("run.json", "robot_sets.json"):
        (Path(option["--out"]) / name).write_text("{{}}")
elif argv[:3] == ["-m", "divmorph.cli", "distill"]:
    student = option["--students"]
    time.sleep(0.5)
    if student == os.environ.get("FAIL_DISTILL"):
        sys.exit(1)
    if student == os.environ.get("STOP_DISTILL"):
        sys.exit(143)  # what `divmorph distill` returns when SIGTERM stops it
    run = Path(option["--run"])
    done = run / "student" if student == "divmorph" else run / "students" / student
    (done / "logs" / "run-0").mkdir(parents=True, exist_ok=True)
    for name in ("model.zip", "vecnormalize.pkl", "logs/run-0/progress.csv", "done.json"):
        (done / name).write_text(student)
    with open(work / "calls.log", "a") as log:
        log.write(json.dumps(["distilled", student]) + "\\n")
elif argv[0] == "tools/pack_logs.py":  # each plain log under the folder gzipped in its place
    for log in Path(argv[2]).rglob("progress.csv"):
        log.with_name("progress.csv.gz").write_text(log.read_text())
        log.unlink()
elif argv[0] == "tools/pack_transfer_runs.py":  # the packed form of each finished run, and the variant's table
    folder, variant = argv[2].rsplit("=", 1)
    for done in Path(folder).glob("transfer/*/*/seed-*/done.json"):
        target = Path(argv[1]) / variant / done.parent.relative_to(folder)
        target.mkdir(parents=True, exist_ok=True)
        for name in ("done.json", "source.json"):
            (target / name).write_text((done.parent / name).read_text())
        (target / "eval.csv.gz").write_text("packed")
    (Path(argv[1]) / f"training-{{variant}}.csv.gz").write_text("packed")
elif argv[0] == "results/finetune-known-task/finetune_known_task.py":
    seed = Path(option["--out"]) / "transfer" / option["--task"] / option["--arms"] / f"seed-{{option['--seeds']}}"
    if "--baseline-seeds" in argv:
        assert (Path(option["--out"]) / "run.json").is_file() and (seed / "source.json").is_file()
        (Path(option["--out"]) / "baseline.json").write_text(json.dumps({{option["--arms"]: {{}}}}))
    else:
        (seed / "logs" / "run-1").mkdir(parents=True, exist_ok=True)
        (Path(option["--out"]) / "run.json").write_text("{{}}")  # the script branches its --out
        for name in ("source.json", "eval.csv", "logs/run-1/progress.csv", "model.zip", "done.json"):
            (seed / name).write_text(option["--arms"])
"""


def run_workers(tmp_path: Path, work: str = "work", **env: str) -> tuple[list[tuple[int, str, int]], list[list[str]]]:
    """Two workers to the end, in the folder ``work`` (KEEP: ``tmp_path/kept``); returns the jobs they ran
    (number, job, exit status) and the stand-in's calls."""
    python = tmp_path / "python"
    python.write_text(STAND_IN)
    python.chmod(python.stat().st_mode | stat.S_IEXEC)
    (tmp_path / work).mkdir()
    env = {
        **os.environ,
        "WORK": str(tmp_path / work),
        "KEEP": str(tmp_path / "kept"),
        "PY": str(python),
        "CODE": str(tmp_path),
        "POLL": "0.1",
        **env,
    }
    workers = [
        subprocess.Popen(["bash", str(SCRIPT), f"claims-{work}"], cwd=tmp_path, env=env, stdout=subprocess.PIPE, text=True)
        for _ in range(2)
    ]
    try:
        logs = [worker.communicate(timeout=120)[0] for worker in workers]
    finally:
        for worker in workers:
            worker.kill()
    assert all(worker.returncode == 0 for worker in workers)
    assert all(" starts job " in log for log in logs)  # both workers worked
    ended = []
    for line in "".join(logs).splitlines():
        if " ends job " in line:
            head, job = line.split(" ends job ")[1].split(": ", 1)
            number, status = head.split(" (exit ")
            ended.append((int(number), job, int(status.rstrip(")"))))
    log = tmp_path / work / "calls.log"
    calls = [json.loads(line) for line in log.read_text().splitlines()] if log.is_file() else []
    return sorted(ended), calls


def study_calls(calls: list[list[str]]) -> list[tuple[int, dict[str, str], list[str]]]:
    """The calls of finetune_known_task.py: (position, {option: value}, [every --set value])."""
    found = []
    for i, argv in enumerate(calls):
        if argv[0] == "results/finetune-known-task/finetune_known_task.py":
            options = {argv[j]: argv[j + 1] for j in range(1, len(argv) - 1) if argv[j].startswith("--")}
            settings = [argv[j + 1] for j in range(1, len(argv) - 1) if argv[j] == "--set"]
            found.append((i, options, settings))
    return found


def races(calls):
    return [(i, options, settings) for i, options, settings in study_calls(calls) if "--baseline-seeds" not in options]


def test_two_workers_run_every_job_once_and_race_only_distilled_students_on_g_terms(tmp_path):
    """Two workers started together, from a relative claims folder, share the 36 jobs (4 distillations at 400k
    steps, each in a teachers-only branch; 24 race runs; 8 measurements of the starts) without running any twice;
    each (student, task, seed) races once, after its student's distillation, from the student's branch into its
    folder for the task, on G's terms (602,112 steps, learngenes at 1x, rotations frozen, 5 episodes per point);
    Escape from the low start (Incline's instruction) before PointNav (the bounded goal, Patrol's gates); each start
    is measured once a run of its folder has begun, on the same terms. What is finished is kept: each student
    (model, statistics, packed log, its branch's settings), each run's small files (its model left behind), each
    start. Runs are kept as tools/pack_transfer_runs.py packs them: no model, no full log."""
    ended, calls = run_workers(tmp_path)
    assert [number for number, _, _ in ended] == list(range(36))  # each job once
    assert all(status == 0 for _, _, status in ended)
    race_tasks = [job.split()[2] for _, job, _ in ended if job.startswith("race ")]
    assert race_tasks == ["Escape"] * 12 + ["PointNav"] * 12

    distilled = {argv[1]: i for i, argv in enumerate(calls) if argv[0] == "distilled"}
    assert set(distilled) == STUDENTS
    work, kept = tmp_path / "work", tmp_path / "kept"
    for argv in calls:
        if argv[:3] == ["-m", "divmorph.cli", "distill"]:
            assert "distill.n_timesteps=400000" in argv
        if argv[:3] == ["-m", "divmorph.cli", "branch"]:
            assert argv[argv.index("--from") + 1] == "results/cpu100" and argv[argv.index("--stages") + 1] == "teachers"
    runs = races(calls)
    assert len({(options["--arms"], options["--task"], options["--seeds"]) for _, options, _ in runs}) == len(runs) == 24
    first_run = {}
    for i, options, settings in runs:
        student, task = options["--arms"], options["--task"]
        assert distilled[student] < i and options["--source"] == f"{work}/distill-{student}"
        assert options["--out"] == f"{work}/race/{task}-{student}"
        assert options["--steps"] == "602112" and options["--eval-every"] == "200704"
        assert all(term in settings for term in G_TERMS)
        if task == "Escape":
            assert "transfer.task_gates=instruction" in settings and INCLINE in settings and "goal_range=10" not in settings
        else:
            assert "transfer.task_gates=closest" in settings and "goal_range=10" in settings and INCLINE not in settings
        if options["--seeds"] == "0":
            first_run[options["--out"]] = (i, settings)
        run = kept / "race" / f"{task}-{student}" / "transfer" / task / student / f"seed-{options['--seeds']}"
        assert sorted(p.relative_to(run).as_posix() for p in run.rglob("*") if p.is_file()) == ["done.json", "eval.csv.gz", "source.json"]
        assert (kept / "race" / f"training-{task}-{student}.csv.gz").is_file()
    starts = [(i, options, settings) for i, options, settings in study_calls(calls) if "--baseline-seeds" in options]
    assert {options["--out"] for _, options, _ in starts} == set(first_run) and len(starts) == 8
    for i, options, settings in starts:
        assert options["--baseline-seeds"] == "5" and "--baseline-only" in calls[i]
        assert first_run[options["--out"]][0] < i and first_run[options["--out"]][1] == settings
        assert (kept / "race" / Path(options["--out"]).name / "baseline.json").is_file()
    for student in STUDENTS:
        assert sorted(
            p.relative_to(kept / "students" / student).as_posix() for p in (kept / "students" / student).rglob("*") if p.is_file()
        ) == [
            "robot_sets.json",
            "run.json",
            "student/done.json",
            "student/logs/run-0/progress.csv.gz",
            "student/model.zip",
            "student/vecnormalize.pkl",
        ]


def test_a_later_session_restores_the_kept_students_and_runs_only_what_is_not_kept(tmp_path):
    """After a full race, a session on a fresh machine (new WORK, the same KEEP) restores every student from KEEP
    without distilling it; of one run and one start removed from KEEP it runs exactly those, the start in a race
    folder branched again from the student's and told what the kept first seed was told; nothing else is called."""
    run_workers(tmp_path)
    kept = tmp_path / "kept"
    shutil.rmtree(kept / "race" / "Escape-no-orthogonality" / "transfer" / "Escape" / "no-orthogonality" / "seed-2")
    (kept / "race" / "PointNav-divmorph" / "baseline.json").unlink()

    ended, calls = run_workers(tmp_path, work="later")
    assert all(status == 0 for _, _, status in ended)
    later = tmp_path / "later"
    assert not any(argv[0] == "distilled" or argv[:3] == ["-m", "divmorph.cli", "distill"] for argv in calls)
    for student in STUDENTS:
        folder = later / f"distill-{student}" / ("student" if student == "divmorph" else f"students/{student}")
        assert (folder / "model.zip").read_text() == student and (folder / "done.json").is_file()
    runs = [(options["--arms"], options["--task"], options["--seeds"]) for _, options, _ in races(calls)]
    assert runs == [("no-orthogonality", "Escape", "2")]
    starts = [options for _, options, _ in study_calls(calls) if "--baseline-seeds" in options]
    assert [(options["--arms"], options["--task"]) for options in starts] == [("divmorph", "PointNav")]
    branched = [argv for argv in calls if argv[:3] == ["-m", "divmorph.cli", "branch"] and f"{later}/race/PointNav-divmorph" in argv]
    assert branched and branched[0][branched[0].index("--from") + 1] == f"{later}/distill-divmorph"
    assert (kept / "race" / "PointNav-divmorph" / "baseline.json").is_file()
    assert (kept / "race" / "Escape-no-orthogonality" / "transfer" / "Escape" / "no-orthogonality" / "seed-2" / "done.json").is_file()


def test_a_failed_distillation_skips_its_students_jobs_and_the_others_finish(tmp_path):
    """The decoder ablation's distillation fails: the workers still finish, the log gives its exit status, none of
    that student's jobs calls anything, nothing of it is kept, and the other students' 18 race runs all run."""
    ended, calls = run_workers(tmp_path, FAIL_DISTILL="no-kdiv-decoder")
    statuses = {job: status for _, job, status in ended}
    assert statuses["distill no-kdiv-decoder"] == 1 and statuses["race no-kdiv-decoder Escape 2"] == 1
    assert statuses["starts no-kdiv-decoder PointNav"] == 1
    assert statuses["race no-kdiv-transformer Escape 2"] == 0
    assert {options["--arms"] for _, options, _ in races(calls)} == STUDENTS - {"no-kdiv-decoder"}
    assert len(races(calls)) == 18
    assert not any("no-kdiv-decoder" in " ".join(argv) for argv in calls if argv[:2] != ["-m", "divmorph.cli"])
    assert not (tmp_path / "kept" / "students" / "no-kdiv-decoder").exists()


def test_a_stopped_distillation_stops_its_worker_without_marking_the_student_failed(tmp_path):
    """SIGTERM stops the first distillation (exit 143, as `divmorph distill` returns): its worker stops with that
    status after logging it, and the student is not marked failed (so a restarted race distils it on, rather than
    skipping its races)."""
    python = tmp_path / "python"
    python.write_text(STAND_IN)
    python.chmod(python.stat().st_mode | stat.S_IEXEC)
    (tmp_path / "work").mkdir()
    env = {
        **os.environ,
        "WORK": str(tmp_path / "work"),
        "KEEP": str(tmp_path / "kept"),
        "PY": str(python),
        "CODE": str(tmp_path),
        "POLL": "0.1",
    }
    worker = subprocess.run(
        ["bash", str(SCRIPT), "claims"],
        cwd=tmp_path,
        env={**env, "STOP_DISTILL": "no-kdiv-transformer"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert worker.returncode == 143
    assert "ends job 0 (exit 143): distill no-kdiv-transformer" in worker.stdout and " starts job 1" not in worker.stdout
    assert not (tmp_path / "work" / "FAILED-no-kdiv-transformer").exists()
