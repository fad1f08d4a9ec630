"""The ablation race's job list (``results/transfer-pointnav/ablation_race.sh``), worked by two workers at once with a stand-in Python."""

from __future__ import annotations

import os
import stat
import subprocess
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "results" / "transfer-pointnav" / "ablation_race.sh"
#: a study's script of results/: the evidence's suite (`make test-results`), not the library's
pytestmark = pytest.mark.shipped_results
STUDENTS = {"no-kdiv-transformer", "no-kdiv-decoder", "no-orthogonality"}

# Logs each call and makes the folders the real calls make; `divmorph distill` takes a moment, then marks its student distilled as the real one does when it
# finishes -- or fails, for the student named in FAIL_DISTILL.
STAND_IN = """#!/usr/bin/env bash
echo "$*" >> "$WORK/calls.log"
if [ "$1 $2 $3" = "-m divmorph.cli branch" ]; then
    mkdir -p "${@: -1}" && touch "${@: -1}/run.json"
fi
if [ "$1" = results/novel-task-gates/novel_task_gates.py ]; then
    mkdir -p "$5"  # its --out
fi
if [ "$1 $2 $3" = "-m divmorph.cli distill" ]; then
    student=${@: -1}
    sleep 0.5
    [ "$student" = "${FAIL_DISTILL:-}" ] && exit 1
    mkdir -p "$WORK/ablate-$student/students/$student" && touch "$WORK/ablate-$student/students/$student/done.json"
    echo "distilled $student" >> "$WORK/calls.log"
fi
"""


def run_workers(tmp_path: Path, **env: str) -> tuple[list[tuple[int, str, int]], list[str]]:
    """Two workers to the end; returns the jobs they ran (number, job, exit status) and the stand-in's calls."""
    python = tmp_path / "python"
    python.write_text(STAND_IN)
    python.chmod(python.stat().st_mode | stat.S_IEXEC)
    env = {**os.environ, "WORK": str(tmp_path / "work"), "PY": str(python), "CODE": str(tmp_path), "POLL": "0.1", **env}
    workers = [
        subprocess.Popen(["bash", str(SCRIPT), "claims"], cwd=tmp_path, env=env, stdout=subprocess.PIPE, text=True) for _ in range(2)
    ]
    try:
        logs = [worker.communicate(timeout=60)[0] for worker in workers]
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
    return sorted(ended), (tmp_path / "work" / "calls.log").read_text().splitlines()


def races(calls: list[str]) -> list[tuple[int, dict[str, str]]]:
    """The race runs among the calls: (position, {option: value})."""
    found = []
    for i, call in enumerate(calls):
        if call.startswith("results/finetune-known-task/finetune_known_task.py"):
            words = call.split()
            found.append((i, {word: words[j + 1] for j, word in enumerate(words) if word.startswith("--")}))
    return found


def test_two_workers_run_every_job_once_and_race_only_distilled_students_on_the_race_terms(tmp_path):
    """Two workers started together, from a relative claims folder, share the 33 jobs (3 distillations, 3
    measurements of the starts, 27 race runs) without running any twice; each (student, task, seed) races once,
    after its student's distillation, in the student's branch, on the race's terms (602,112 steps, the closest
    task's gates, 5 episodes per point); the list puts PointNav's nine runs before any other task's."""
    ended, calls = run_workers(tmp_path)
    assert [number for number, _, _ in ended] == list(range(33))  # each job once
    assert all(status == 0 for _, _, status in ended)
    race_tasks = [job.split()[2] for _, job, _ in ended if job.startswith("race ")]
    assert race_tasks[:9] == ["PointNav"] * 9 and "PointNav" not in race_tasks[9:]

    distilled = {call.split()[-1]: i for i, call in enumerate(calls) if call.startswith("distilled ")}
    assert set(distilled) == STUDENTS
    runs = races(calls)
    assert len({(options["--arms"], options["--task"], options["--seeds"]) for _, options in runs}) == len(runs) == 27
    work = tmp_path / "work"
    for i, options in runs:
        student, task = options["--arms"], options["--task"]
        assert distilled[student] < i
        assert options["--source"] == f"{work}/ablate-{student}" and options["--out"] == f"{work}/race600/{task}-{student}"
        assert options["--steps"] == "602112" and options["--eval-every"] == "200704"
    assert all(
        "--set transfer.eval_episodes=5 --set transfer.task_gates=closest" in call
        for call in calls
        if call.startswith("results/finetune-known-task/finetune_known_task.py")
    )


def test_a_failed_distillation_skips_its_students_jobs_and_the_others_finish(tmp_path):
    """The decoder ablation's distillation fails: the workers still finish, the log gives its exit status, none of
    that student's jobs calls anything, and the other two students' 18 race runs all run."""
    ended, calls = run_workers(tmp_path, FAIL_DISTILL="no-kdiv-decoder")
    statuses = {job: status for _, job, status in ended}
    assert statuses["distill no-kdiv-decoder"] == 1 and statuses["race no-kdiv-decoder Escape 2"] == 1
    assert statuses["race no-kdiv-transformer Escape 2"] == 0
    assert {options["--arms"] for _, options in races(calls)} == STUDENTS - {"no-kdiv-decoder"}
    assert len(races(calls)) == 18
    assert not any("no-kdiv-decoder" in call for call in calls if not call.startswith("-m divmorph.cli"))
