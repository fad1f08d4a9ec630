"""Raw runs of finished studies: out of the tree, kept in git history, restored by one command.

    python tools/archive_runs.py list                                 # what is archived, and where
    python tools/archive_runs.py restore results/cpu100/transfer      # put the raw files back in place
    python tools/archive_runs.py restore results/cpu100 --into /tmp/x # or under another folder
    python tools/archive_runs.py archive results/<study> [...]        # take a finished study's raw files out

A study under ``results/`` keeps its reading in the tree (README and other pages, scripts, figures,
small tables) and the shipped models (``divmorph/shipped_models.json``). Its raw runs (curves, logs,
run records, models that are not shipped, videos) are large and only the study's own scripts read
them, so they live in git history: ``results/archive.json`` names, for each archived path prefix, the
commit whose tree still holds its files. ``restore`` takes those files out of that commit
(``git archive``) and writes only the ones missing from the destination, so it never overwrites a
reading written since. ``archive`` records ``HEAD`` for the given folders and ``git rm``-s their raw
files; commit the result (the files stay in ``HEAD``'s tree, the commit the record names).

Needs a git checkout with its history (a shallow clone lacks the commits: ``git fetch --unshallow``).
"""

from __future__ import annotations

import argparse
import io
import json
import subprocess
import sys
import tarfile
from pathlib import Path, PurePosixPath

ROOT = Path(__file__).resolve().parents[1]
RECORD = ROOT / "results" / "archive.json"
SHIPPED = ROOT / "divmorph" / "shipped_models.json"
#: what a study's reading is made of: it stays in the tree
READING_SUFFIXES = (".md", ".py", ".sh", ".png", ".svg", ".jpg", ".yml", ".yaml")
#: a plain table this small is part of the reading (a larger one is raw data)
SMALL_TABLE = 20_000


class ArchiveError(RuntimeError):
    """The archive cannot do what was asked (the message says why and what to do)."""


def git(*args: str, binary: bool = False) -> str | bytes:
    done = subprocess.run(["git", *args], cwd=ROOT, capture_output=True)
    if done.returncode != 0:
        raise ArchiveError(f"git {' '.join(args)} failed: {done.stderr.decode().strip()}")
    return done.stdout if binary else done.stdout.decode()


def entries() -> list[dict[str, object]]:
    """``[{"commit": sha, "date": ..., "paths": [prefix, ...]}, ...]``, oldest first."""
    return json.loads(RECORD.read_text())["archives"] if RECORD.is_file() else []


def shipped_files() -> set[str]:
    """The shipped runs' models and records (``results/<run>/...``), and ``results/<run>/`` itself."""
    runs = json.loads(SHIPPED.read_text())
    return {f"results/{run}/{path}" for run, files in runs.items() for path in files} | {f"results/{run}/" for run in runs}


def is_raw(path: str, size: int, shipped: set[str]) -> bool:
    """A tracked file of a study that is raw data (not its reading, not a shipped model or record)."""
    if path in shipped or path == "results/archive.json" or path.endswith(READING_SUFFIXES):
        return False
    in_shipped_run = any(path.startswith(run) for run in shipped if run.endswith("/"))
    if path.endswith(".json") and in_shipped_run:
        return size > SMALL_TABLE  # a shipped run's stage records (done.json, ...): what loading a model reads
    return not (path.endswith(".csv") and size <= SMALL_TABLE)


def within(path: str, prefix: str) -> bool:
    return path == prefix or path.startswith(prefix.rstrip("/") + "/")


def normalised(path: str) -> str:
    """A repository-relative posix path (``./results/x/`` -> ``results/x``), checked to be under ``results/``."""
    absolute = (Path.cwd() / path).resolve()
    try:
        relative = PurePosixPath(absolute.relative_to(ROOT).as_posix())
    except ValueError:
        raise ArchiveError(f"{path} is not inside this repository ({ROOT})") from None
    if relative.parts[:1] != ("results",):
        raise ArchiveError(f"{path}: only studies under results/ are archived")
    return str(relative)


def archived_files(commit: str, prefix: str) -> list[str]:
    """The files of ``commit``'s tree under ``prefix``."""
    listed = git("ls-tree", "-r", "-z", "--name-only", commit, "--", prefix, binary=True)
    return [name for name in listed.decode().split("\0") if name]


def restore(paths: list[str], into: Path | None = None) -> list[Path]:
    """Write the archived files under ``paths`` that are missing from ``into`` (default: the checkout).

    :returns: the files written.
    :raises ArchiveError: a path no archive covers, or a commit this checkout's history lacks.
    """
    destination = ROOT if into is None else Path(into)
    wanted = [normalised(path) for path in paths]
    written: list[Path] = []
    for prefix in wanted:
        matches = [
            (entry["commit"], archived)
            for entry in entries()
            for archived in entry["paths"]
            if within(archived, prefix) or within(prefix, archived)
        ]
        if not matches:
            known = sorted({p for entry in entries() for p in entry["paths"]})
            raise ArchiveError(f"nothing under {prefix} is archived; archived: {', '.join(known) or 'nothing'}")
        for commit, archived in matches:
            narrow = prefix if within(prefix, archived) else archived
            try:
                git("cat-file", "-e", f"{commit}^{{commit}}")
            except ArchiveError:
                raise ArchiveError(
                    f"commit {commit} (which holds {archived}) is not in this checkout's history: "
                    "clone the repository with its history (`git fetch --unshallow` in a shallow clone)"
                ) from None
            names = [n for n in archived_files(commit, narrow) if not (destination / n).exists()]
            if not names:
                continue
            archive = git("archive", "--format=tar", commit, "--", *names, binary=True)
            with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
                tar.extractall(destination, filter="data")
            written += [destination / name for name in names]
    return written


def archive(paths: list[str]) -> list[str]:
    """``git rm`` the raw files under ``paths`` and record ``HEAD`` as the commit that keeps them.

    :raises ArchiveError: a raw file differs from ``HEAD`` (commit it first), or none is found.
    """
    shipped = shipped_files()
    prefixes = [normalised(path) for path in paths]
    tracked = git("ls-files", "-z", "--", *prefixes, binary=True).decode().split("\0")
    raw = [name for name in tracked if name and is_raw(name, (ROOT / name).stat().st_size, shipped)]
    if not raw:
        raise ArchiveError(f"no raw file is tracked under {', '.join(prefixes)}")
    changed = git("diff", "--name-only", "HEAD", "--", *raw).split()
    if changed:
        raise ArchiveError(f"commit these first (the archive is HEAD's tree): {', '.join(changed[:5])}")
    head = git("rev-parse", "HEAD").strip()
    date = git("show", "-s", "--format=%cs", head).strip()
    holding = [prefix for prefix in prefixes if any(within(name, prefix) for name in raw)]
    record = {"archives": [*entries(), {"commit": head, "date": date, "paths": holding}]}
    for start in range(0, len(raw), 500):
        git("rm", "-q", "--", *raw[start : start + 500])
    RECORD.write_text(json.dumps(record, indent=1) + "\n")
    git("add", str(RECORD.relative_to(ROOT)))
    return raw


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    commands.add_parser("list", help="the archived paths and the commits that keep them")
    put_back = commands.add_parser("restore", help="write the archived files under PATH that are missing")
    put_back.add_argument("paths", nargs="+", metavar="PATH")
    put_back.add_argument("--into", type=Path, default=None, help="a folder to restore under (default: the checkout)")
    take_out = commands.add_parser("archive", help="git rm a finished study's raw files, recording HEAD")
    take_out.add_argument("paths", nargs="+", metavar="PATH")
    args = parser.parse_args(argv)
    try:
        if args.command == "list":
            for entry in entries():
                for path in entry["paths"]:
                    print(f"{path}  (commit {str(entry['commit'])[:10]}, {entry['date']})")
        elif args.command == "restore":
            written = restore(args.paths, args.into)
            print(f"restored {len(written)} files" + (f" under {args.into}" if args.into else ""))
        else:
            removed = archive(args.paths)
            print(f"{len(removed)} raw files removed from the tree, kept in HEAD; commit the result")
    except ArchiveError as error:
        sys.exit(f"archive_runs: {error}")


if __name__ == "__main__":
    main()
