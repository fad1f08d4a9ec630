"""Write ``divmorph/shipped_models.json``: the checksums of the shipped runs' files that
``divmorph fetch-models`` copies (each model with its statistics and env settings, and the run's records).

    python tools/shipped_models.py          # after re-saving a shipped model; tests/test_shipped.py checks it is current
"""

from __future__ import annotations

import hashlib
import json
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the runs whose models ship in the repository
RUNS = ("cpu100",)
#: what a fetched run holds: every model with what it loads with, and the records that name its robots and settings
MODEL_FILES = ("model.zip", "vecnormalize.pkl", "env.json")
RUN_RECORDS = ("run.json", "robot_sets.json", "evaluate/returns.csv.gz")


def manifest() -> dict[str, dict[str, str]]:
    """``{run: {relative path: sha256}}`` from the files in ``results/``."""
    found: dict[str, dict[str, str]] = {}
    for run in RUNS:
        folder = ROOT / "results" / run
        tracked = subprocess.run(["git", "ls-files", f"results/{run}"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
        paths = [
            ROOT / t for t in tracked if Path(t).name in MODEL_FILES or Path(t).relative_to(f"results/{run}").as_posix() in RUN_RECORDS
        ]
        found[run] = {p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(set(paths))}
    return found


if __name__ == "__main__":
    out = ROOT / "divmorph" / "shipped_models.json"
    out.write_text(json.dumps(manifest(), indent=1, sort_keys=True) + "\n")
    print(f"{out}: {sum(len(v) for v in manifest().values())} files")
