"""The transfer race's student, archived out of the tree: the README's command restores it, and it is
the ``cpu100-transfer`` profile's student (its proportions, its load-balanced router, its budget), and it acts."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
STUDY = REPO / "results" / "transfer-student"
KEPT = "results/transfer-student/kept"
pytestmark = pytest.mark.shipped_results


@pytest.fixture(scope="module")
def kept(archived_study) -> Path:
    """The kept student, restored out of the archive as the README says (skips where the history is absent)."""
    return archived_study(KEPT)


def test_the_readme_names_the_command_that_restores_the_student():
    assert f"python tools/archive_runs.py restore {KEPT}" in (STUDY / "README.md").read_text()


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
