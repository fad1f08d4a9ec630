"""The repository's tracked files stay small enough to travel with every GPU job.

A job on the GPU machine carries the tracked tree plus what it needs (at most 64 MiB in all, see
``../shared/gpu/README.md``), so the tracked files must stay under 16 MiB. Large outputs that a
command can make again stay out of git (``.gitignore`` names each one with its command); a finished
study's raw runs are archived (``tools/archive_runs.py``); shipped SB3 models are saved slim
(``tools/slim_models.py``).
"""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 16 * 2**20


def tracked_files() -> list[Path]:
    """The files git tracks in this checkout (skips the test outside a git checkout or without git)."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
        listed = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except subprocess.CalledProcessError:
        pytest.skip("not inside a git checkout")
    if Path(top).resolve() != ROOT:
        pytest.skip(f"the git checkout at {top} is not this project's")
    return [ROOT / name for name in listed.decode().split("\0") if name]


def test_the_tracked_files_stay_under_16_mib():
    # like `git ls-files -z | xargs -0 du -cb`: a link counts as itself, a tracked file deleted here counts 0
    sizes = {path: path.lstat().st_size for path in tracked_files() if os.path.lexists(path)}
    total = sum(sizes.values())
    largest = sorted(sizes.items(), key=lambda item: -item[1])[:15]
    names = "\n".join(f"  {size / 2**20:6.2f} MiB  {path.relative_to(ROOT)}" for path, size in largest)
    assert total <= LIMIT, (
        f"the tracked files total {total / 2**20:.1f} MiB > {LIMIT / 2**20:.0f} MiB (every GPU job carries them). "
        f"Leave what a command can make again out of git (.gitignore, with the command), archive a finished study's raw "
        f"runs (python tools/archive_runs.py archive results/<study>), or save it smaller. "
        f"Largest tracked files:\n{names}"
    )


def test_shipped_models_carry_no_optimiser_moments_or_last_observation():
    models = [path for path in tracked_files() if path.name == "model.zip" and path.is_file()]
    heavy = []
    for path in models:
        with zipfile.ZipFile(path) as archive:
            optimiser = archive.getinfo("policy.optimizer.pth").file_size
            policy = archive.getinfo("policy.pth").file_size
            data = json.load(io.TextIOWrapper(archive.open("data"), encoding="utf-8"))
        if optimiser > policy / 10 or "_last_obs" in data or "_last_original_obs" in data:
            heavy.append(f"{path.relative_to(ROOT)} (optimiser {optimiser:,} B, policy {policy:,} B)")
    assert not heavy, (
        "re-save with `python tools/slim_models.py --write "
        + " ".join(str(Path(h.split(" ")[0]).parent) for h in heavy)
        + "`: "
        + "; ".join(heavy)
    )
