"""``divmorph migrate``: rewrite run folders' ``run.json`` of record format 1 in today's keys."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

#: the name the record of the old format is kept under, beside the new one
BACKUP = "run.format-1.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("runs", nargs="+", help="run folders, or folders searched for run folders (every run.json below them)")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 when a record needs migrating")
    parser.add_argument("--no-backup", action="store_true", help=f"do not keep the old record as {BACKUP} (e.g. under git)")


def _records(paths: list[str]) -> list[Path]:
    records: list[Path] = []
    for path in map(Path, paths):
        if (path / "run.json").is_file():
            records.append(path / "run.json")
        elif path.is_dir():
            records.extend(sorted(p for p in path.rglob("run.json") if "superseded" not in p.parts))
        else:
            raise FileNotFoundError(f"no such run folder: {path}")
    return records


def run(args: argparse.Namespace) -> int:
    from divmorph.pipeline.files import atomic_write_json
    from divmorph.pipeline.retired import migrate_record

    command_line = "divmorph " + shlex.join(getattr(args, "argv", None) or sys.argv[1:])
    try:
        records = _records(args.runs)
    except FileNotFoundError as error:
        print(f"divmorph migrate: {error}", file=sys.stderr)
        return 2
    if not records:
        print(f"divmorph migrate: no run.json under {' '.join(args.runs)}", file=sys.stderr)
        return 2
    pending = 0
    for path in records:
        old = json.loads(path.read_text())
        new, changes = migrate_record(old, command_line)
        if new is old:
            print(f"{path}: already in today's format")
            continue
        pending += 1
        if args.check:
            print(f"{path}: needs migrating")
            continue
        if not args.no_backup:
            (path.parent / BACKUP).write_text(path.read_text())
        atomic_write_json(path, new)
        kept = "" if args.no_backup else f" (the old record kept in {path.parent / BACKUP})"
        print(f"{path}: migrated{kept}" + "".join(f"\n  {change}" for change in changes))
    if args.check and pending:
        print(f"divmorph migrate: {pending} record(s) to migrate: divmorph migrate {' '.join(args.runs)}", file=sys.stderr)
        return 1
    return 0
