"""Make the race's source run folder: cpu100's teachers and dense distilled student (MetaMorph⚗) with the
``cpu100-transfer`` student (``results/transfer-student/``) as its DivMorph student.

    python results/transfer-race/make_source.py RUNS/source

``finetune_known_task.py --source RUNS/source`` then branches every task's run folder from it. The teachers and
MetaMorph⚗ are linked from ``results/cpu100`` (as ``divmorph branch`` links them); the student is restored from
the commit that keeps it (``tools/archive_runs.py``) and copied in; the record is the student's run's
(``cpu100-transfer``'s settings), with this step in its history.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from divmorph.pipeline.branch import branch
from divmorph.pipeline.files import atomic_write_json

ROOT = Path(__file__).resolve().parents[2]
KEPT = "results/transfer-student/kept"


def make_source(out: Path, root: Path = ROOT) -> Path:
    """Compose the source folder ``out`` (new or empty); returns it."""
    branch(root / "results" / "cpu100", out, ("teachers", "distill"), command="python results/transfer-race/make_source.py")
    with tempfile.TemporaryDirectory() as scratch:
        kept = root / KEPT
        if not (kept / "student" / "model.zip").is_file():
            subprocess.run(
                [sys.executable, str(root / "tools" / "archive_runs.py"), "restore", KEPT, "--into", scratch], check=True, cwd=root
            )
            kept = Path(scratch) / KEPT
        (out / "student").unlink()  # cpu100's student, linked by the branch
        shutil.copytree(kept / "student", out / "student", ignore=shutil.ignore_patterns("logs"))
        record = json.loads((kept / "run.json").read_text())
    linked = json.loads((out / "run.json").read_text())["history"][-1]
    record["history"] = [
        *record.get("history", []),
        {
            **linked,
            "time": time.strftime("%Y-%m-%d %H:%M:%S"),
            "note": f"teachers and students/distilled of results/cpu100; student of {KEPT}",
        },
    ]
    atomic_write_json(out / "run.json", record)
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path, help="the source folder to make (new or empty)")
    print(make_source(parser.parse_args(argv).out))


if __name__ == "__main__":
    main()
