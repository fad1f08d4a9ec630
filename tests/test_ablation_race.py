"""The ablation race's job list (``studies/ablation_race.sh``), worked by two workers at once with a stand-in Python."""

from __future__ import annotations

import os
import stat
import subprocess
from collections import Counter
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "studies" / "ablation_race.sh"

# Logs each call; `divmorph distill` takes a moment, then marks its student distilled as the real one does.
STAND_IN = """#!/usr/bin/env bash
echo "$*" >> "$WORK/calls.log"
if [ "$1 $2 $3" = "-m divmorph.cli distill" ]; then
    student=${@: -1}
    sleep 0.5
    mkdir -p "$WORK/ablate-$student/students/$student" && touch "$WORK/ablate-$student/students/$student/done.json"
    echo "distilled $student" >> "$WORK/calls.log"
fi
"""


def test_two_workers_run_every_job_once_and_race_only_distilled_students_on_the_race_terms(tmp_path):
    """Two workers started together share the 33 jobs (3 distillations, 3 measurements of the starts, 27 race
    runs) without running any twice; every race run comes after its student's distillation and carries the
    race's terms (602,112 steps, the closest task's gates, 5 episodes per point); PointNav's nine runs come
    before any other task's."""
    python = tmp_path / "python"
    python.write_text(STAND_IN)
    python.chmod(python.stat().st_mode | stat.S_IEXEC)
    env = {**os.environ, "WORK": str(tmp_path), "PY": str(python), "CODE": str(tmp_path), "POLL": "0.1"}
    workers = [
        subprocess.Popen(["bash", str(SCRIPT), str(tmp_path / "claims")], env=env, stdout=subprocess.PIPE, text=True) for _ in range(2)
    ]
    logs = [worker.communicate(timeout=120)[0] for worker in workers]
    assert all(worker.returncode == 0 for worker in workers)

    claimed = [line.split(" starts job ")[1].split(": ", 1) for log in logs for line in log.splitlines() if " starts job " in line]
    assert sorted(int(number) for number, _ in claimed) == list(range(33))  # each job once
    jobs = [job for _, job in sorted(claimed, key=lambda claim: int(claim[0]))]
    assert max(Counter(jobs).values()) == 1
    # the list's order: PointNav's nine race runs before any other task's
    race_tasks = [job.split()[2] for job in jobs if job.startswith("race ")]
    assert race_tasks[:9] == ["PointNav"] * 9 and "PointNav" not in race_tasks[9:]
    assert all(log.count(" starts job ") > 0 for log in logs)  # both workers worked

    calls = (tmp_path / "calls.log").read_text().splitlines()
    distilled = {call.split()[-1]: i for i, call in enumerate(calls) if call.startswith("distilled ")}
    races = [(i, call) for i, call in enumerate(calls) if call.startswith("studies/finetune_known_task.py")]
    assert set(distilled) == {"no-kdiv-transformer", "no-kdiv-decoder", "no-orthogonality"} and len(races) == 27
    for i, call in races:
        args = call.split()
        student = args[args.index("--arms") + 1]
        assert distilled[student] < i
        assert "--steps 602112" in call and "transfer.task_gates=closest" in call and "transfer.eval_episodes=5" in call
