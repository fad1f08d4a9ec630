"""The files of a run folder: atomic writes, done markers, and the CSV logs (plain or packed).

A stage's output folder is *done* once its ``done.json`` exists; that file is written last and
atomically (every file is written to a temporary name and renamed into place), so a stage killed at
any point is either done or not. A recorded run ships its finished stages' CSV logs
gzip-compressed (``progress.csv.gz``, ``eval.csv.gz``, ``returns.csv.gz``: tools/pack_logs.py) to
keep the repository small; every reader takes either form, and a plain file, written later, wins
over its packed twin.
"""

from __future__ import annotations

import csv
import gzip
import io
import json
import os
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import unimal_envs  # noqa: F401  (registers the Unimal-* ids)


DONE = "done.json"


MODEL = "model.zip"


NORMALIZER = "vecnormalize.pkl"


#: Beside every model the pipeline saves: the env settings and robots it trained with, read from its envs.
ENV_SETTINGS = "env.json"


def _umask() -> int:
    """The process umask (reading it means setting it; it is put back at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that readers see the old file or the new one, never a part."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        # mkstemp creates the file 0600; results are for sharing, so give it the mode open() would
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def atomic_write_json(path: Path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, default=str) + "\n")


def atomic_save(path: Path, save: Callable[[Path], None]) -> None:
    """Call ``save(tmp_path)`` (e.g. ``model.save``) then move the result onto ``path`` atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{path.suffix}")
    try:
        save(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def is_done(folder: Path) -> bool:
    return (folder / DONE).is_file()


def mark_done(folder: Path, **info: Any) -> None:
    atomic_write_json(folder / DONE, {"finished": time.strftime("%Y-%m-%d %H:%M:%S"), **info})


def read_done(folder: Path) -> dict[str, Any]:
    return json.loads((folder / DONE).read_text())


# A recorded run ships its finished stages' CSV logs gzip-compressed (``progress.csv.gz``,
# ``eval.csv.gz``, ``returns.csv.gz``: benchmarks/pack_logs.py) to keep the repository small; every
# reader takes either form, and a plain file, written later, wins over its packed twin.
def log_file(path: Path) -> Path | None:
    """``path`` if it exists, else its packed twin ``<path>.gz`` if that exists, else ``None``."""
    path = Path(path)
    packed = path.with_name(path.name + ".gz")
    return path if path.is_file() else packed if packed.is_file() else None


def read_csv_rows(path: Path) -> list[dict[str, str]]:
    """The rows of the CSV ``path`` or of its packed twin (empty when there is neither); ``path`` may
    name the packed file itself (as :func:`log_files` gives it)."""
    path = Path(path)
    found = path if path.suffix == ".gz" and path.is_file() else log_file(path)
    if found is None:
        return []
    with gzip.open(found, "rt", newline="") if found.suffix == ".gz" else open(found, newline="") as f:
        return list(csv.DictReader(f))


def log_files(folder: Path, pattern: str) -> list[Path]:
    """The CSV logs ``folder.glob(pattern)`` finds, each in the form :func:`log_file` reads (a file
    and its packed twin count once)."""
    names = {p.with_suffix("") if p.suffix == ".gz" else p for p in (*folder.glob(pattern), *folder.glob(pattern + ".gz"))}
    return [found for name in sorted(names) if (found := log_file(name)) is not None]


def read_progress(folder: Path) -> dict[str, np.ndarray]:
    """All ``progress.csv`` rows of a training run (resumed attempts concatenated), by column."""
    rows: list[dict[str, str]] = []
    for log in sorted(log_files(folder / "logs", "run-*/progress.csv"), key=lambda p: int(p.parent.name.split("-")[1])):
        rows += read_csv_rows(log)
    columns: dict[str, list[float]] = defaultdict(list)
    keys = {k for row in rows for k in row}
    for row in rows:
        for key in keys:
            value = row.get(key, "")
            columns[key].append(float(value) if value not in ("", None) else np.nan)
    return {k: np.asarray(v) for k, v in columns.items()}


def write_csv(path: Path, rows: list[dict[str, Any]], columns: list[str]) -> None:
    """Write ``rows`` (dicts) as a CSV with these ``columns``, atomically."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns)
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(path, buffer.getvalue())
