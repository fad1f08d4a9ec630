"""The documentation site builds offline with no warning (a broken link or API reference fails), and
its pages carry the API reference generated from the docstrings."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_the_docs_build_strictly_with_the_generated_api_reference(tmp_path):
    pytest.importorskip("mkdocs", reason="the docs need the dev extra (mkdocs, mkdocstrings)")
    site = tmp_path / "site"
    build = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, build.stderr[-3000:]
    api = (site / "api" / "index.html").read_text()
    # the generated reference holds the docstrings' parameters, not just the names
    for text in ("UnimalEnv", "reset_noise_scale", "make_batched_env", "terrain_variants", "DivMorphPolicy", "load_profile"):
        assert text in api, text
