"""The transfer race's student, kept in a commit out of the tree: the README's command restores it, and it is
the ``cpu100-transfer`` profile's student (its proportions, its load-balanced router, its budget), and it acts."""

from __future__ import annotations

import dataclasses
import io
import subprocess
import tarfile
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
STUDY = REPO / "results" / "transfer-student"
#: the commit that holds the student (out of the tree, which it would take over 24 MiB)
STUDENT_COMMIT = "9626364"
KEPT = "results/transfer-student/kept"
pytestmark = pytest.mark.shipped_results


@pytest.fixture(scope="module")
def kept(tmp_path_factory) -> Path:
    """The kept student taken out of its commit as the README says (skips where the history is absent)."""
    folder = tmp_path_factory.mktemp("kept")
    archive = subprocess.run(["git", "archive", STUDENT_COMMIT, KEPT], cwd=REPO, capture_output=True)
    if archive.returncode != 0:
        pytest.skip(f"commit {STUDENT_COMMIT} is not in this checkout's history")
    with tarfile.open(fileobj=io.BytesIO(archive.stdout)) as tar:
        tar.extractall(folder, filter="data")
    return folder / KEPT


def test_the_readme_names_the_commit_that_holds_the_student():
    assert f"git archive {STUDENT_COMMIT} {KEPT}" in (STUDY / "README.md").read_text()


def test_the_kept_student_is_the_transfer_profiles_student_and_acts(kept, official_cache):
    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.provenance import recorded_profile
    from divmorph.pipeline.students import STUDENTS
    from divmorph.pretrained import load_pretrained

    recorded = recorded_profile(kept / "run.json")
    profile = load_profile("cpu100-transfer")
    assert dataclasses.asdict(recorded.student)["policy_kwargs"] == profile.student.policy_kwargs
    assert dataclasses.asdict(recorded.distill) == dataclasses.asdict(profile.distill)
    student = load_pretrained(kept / "student")
    assert isinstance(student.model.policy, STUDENTS["divmorph"].policy) and student.normalizer is not None
    assert student.model.policy_kwargs.items() >= STUDENTS["divmorph"].kwargs(profile).items()
    assert 400_000 <= student.model.num_timesteps < 400_000 + 8 * 256
    (row,) = student.evaluate(student.robots[:1], task="FT", episodes=1, seed=0, max_episode_steps=50)
    assert np.isfinite(row["return"]) and row["length"] > 0
