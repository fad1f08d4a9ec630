"""``tools/archive_runs.py``: a finished study's raw runs leave the tree, stay in history, and come back by one command."""

from __future__ import annotations

import gzip
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
TOOL = REPO / "tools" / "archive_runs.py"


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout


def tool(repo: Path, *args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "tools/archive_runs.py", *args], cwd=cwd or repo, capture_output=True, text=True)


@pytest.fixture
def repo(tmp_path) -> Path:
    """A repository with the tool, a shipped run's manifest, and one finished study (its reading and its raw runs)."""
    if shutil.which("git") is None:
        pytest.skip("git is not installed")
    repo = tmp_path / "repo"
    (repo / "tools").mkdir(parents=True)
    shutil.copy(TOOL, repo / "tools")
    (repo / "divmorph").mkdir()
    (repo / "divmorph" / "shipped_models.json").write_text(json.dumps({"run": {"teachers/FT/model.zip": "0" * 64}}))
    study = repo / "results" / "study"
    (study / "runs" / "seed-0").mkdir(parents=True)
    (study / "README.md").write_text("# the study\n")
    (study / "read.py").write_text("print('reading')\n")
    (study / "table.csv").write_text("arm,return\nscratch,1.0\n")
    (study / "runs" / "seed-0" / "eval.csv.gz").write_bytes(gzip.compress(b"step,return\n0,1.0\n"))
    (study / "runs" / "seed-0" / "done.json").write_text('{"steps": 10}')
    (repo / "results" / "run" / "teachers" / "FT").mkdir(parents=True)
    (repo / "results" / "run" / "teachers" / "FT" / "model.zip").write_bytes(b"model")
    (repo / "results" / "run" / "teachers" / "FT" / "progress.csv.gz").write_bytes(gzip.compress(b"log"))
    git(repo, "init", "-q")
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "add", ".")
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "the study")
    return repo


def test_a_study_archived_keeps_its_reading_and_restores_its_raw_runs_byte_for_byte(repo, tmp_path):
    study = repo / "results" / "study"
    raw = {p.relative_to(repo): p.read_bytes() for p in [study / "runs/seed-0/eval.csv.gz", study / "runs/seed-0/done.json"]}
    done = tool(repo, "archive", "results/study", "results/run")
    assert done.returncode == 0, done.stderr
    git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "archive")
    tracked = set(git(repo, "ls-files").split())
    # the reading and the shipped model stay; the raw runs and the run's logs leave the tree and the disk
    assert {"results/study/README.md", "results/study/read.py", "results/study/table.csv", "results/run/teachers/FT/model.zip"} <= tracked
    assert not any(name.startswith("results/study/runs") or name.endswith("progress.csv.gz") for name in tracked)
    assert not (study / "runs").exists()
    (study / "README.md").write_text("# the study, read again\n")  # a reading written since the archive
    listed = tool(repo, "list")
    assert "results/study" in listed.stdout and "results/run" in listed.stdout

    back = tool(repo, "restore", "results/study", cwd=repo)
    assert back.returncode == 0 and "restored 2 files" in back.stdout, back.stdout + back.stderr
    assert {path: (repo / path).read_bytes() for path in raw} == raw
    assert (study / "README.md").read_text() == "# the study, read again\n"  # never overwritten

    into = tmp_path / "elsewhere"
    assert tool(repo, "restore", "results/study/runs", "--into", str(into)).returncode == 0
    assert (into / "results/study/runs/seed-0/eval.csv.gz").read_bytes() == raw[Path("results/study/runs/seed-0/eval.csv.gz")]


def test_what_cannot_be_done_is_refused_naming_why(repo):
    (repo / "results" / "study" / "runs" / "seed-0" / "done.json").write_text('{"steps": 20}')
    refused = tool(repo, "archive", "results/study")
    assert refused.returncode != 0 and "commit these first" in refused.stderr and "done.json" in refused.stderr
    missing = tool(repo, "restore", "results/other")
    assert missing.returncode != 0 and "nothing under results/other is archived" in missing.stderr
    outside = tool(repo, "restore", "tools")
    assert outside.returncode != 0 and "only studies under results/" in outside.stderr
