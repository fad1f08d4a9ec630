"""Move a recorded ``cpu100`` run onto the official held-out robots as its novel split (issue 43).

The run was recorded with ``novel_set: novel``: the project's generated robots. The profile now names
the official held-out robots (``unimals100-test``, 97 robots) as the novel split and reports the
generated robots apart, as the out-of-distribution split ``ood``. Nothing is re-run or dropped here;
rows are relabelled with the robots they were measured on:

- every ``split=novel`` row of ``evaluate/returns.csv(.gz)``, of each transfer run's ``eval.csv(.gz)``
  and of ``transfer/<task>/metrics.csv`` becomes ``split=ood`` (those rows are generated robots);
- ``run.json`` records the new configuration and robot sets, with a history entry that says what
  changed and why (so ``divmorph evaluate`` then adds the official held-out robots' rows);
- ``robot_sets.json`` names the three splits.

Idempotent: a run already moved is left as it is. Usage (from the repository root, the official
sets fetched): ``python results/cpu100/streams/official_test_split.py results/cpu100 [...]``
"""

from __future__ import annotations

import csv
import gzip
import io
import json
import sys
import time
from pathlib import Path

from divmorph.pipeline.config import load_profile
from divmorph.pipeline.provenance import RECORD
from divmorph.pipeline.files import atomic_write_bytes, atomic_write_json
from divmorph.pipeline.robots import record_robot_sets, robot_set_record

NOTE = (
    "issue 43: the novel split is the official held-out robots (unimals100-test, 97 robots); the rows measured on "
    "the generated `novel` set before are relabelled split=ood (out of distribution), nothing re-run"
)


def relabel(path: Path) -> int:
    """Rewrite ``split=novel`` as ``split=ood`` in a CSV (plain or gzip); returns how many rows changed."""
    packed = path.suffix == ".gz"
    text = (gzip.decompress(path.read_bytes()) if packed else path.read_bytes()).decode()
    rows = list(csv.DictReader(io.StringIO(text)))
    if not rows or "split" not in rows[0]:
        return 0
    changed = 0
    for row in rows:
        if row["split"] == "novel":
            row["split"] = "ood"
            changed += 1
    if changed:
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        data = buffer.getvalue().encode()
        atomic_write_bytes(path, gzip.compress(data, mtime=0) if packed else data)
    return changed


def move(run: Path) -> None:
    record_path = run / RECORD
    record = json.loads(record_path.read_text())
    if record["configuration"].get("novel_set") != "novel":
        print(f"{run}: novel split already {record['configuration'].get('novel_set')!r}; nothing to do")
        return
    files = [*run.glob("evaluate/returns.csv*"), *run.glob("transfer/*/*/seed-*/eval.csv*"), *run.glob("transfer/*/metrics.csv*")]
    counts = {str(f.relative_to(run)): relabel(f) for f in files}
    print(f"{run}: {sum(counts.values())} rows relabelled novel -> ood in {sum(1 for n in counts.values() if n)} files")
    profile = load_profile("cpu100")
    old = record["configuration"]
    new = {**old, "novel_set": profile.novel_set, "ood_set": profile.ood_set, "ood_robots": profile.ood_robots}
    record["configuration"] = new
    record["robots"] = robot_set_record(profile)
    record["history"].append(
        {
            "command": f"python results/cpu100/streams/official_test_split.py {run}",
            "time": time.strftime("%Y-%m-%d %H:%M:%S"),
            "changed": [f"novel_set: {old['novel_set']!r} -> {profile.novel_set!r}", f"ood_set: None -> {profile.ood_set!r}"],
            "forced": False,
            "retrained": [],
            "superseded": None,
            "note": NOTE,
        }
    )
    atomic_write_json(record_path, record)
    if (run / "robot_sets.json").is_file():
        record_robot_sets(profile, run)


if __name__ == "__main__":
    for folder in sys.argv[1:]:
        move(Path(folder))
