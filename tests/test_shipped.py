"""A pip install has no ``results/``: ``divmorph fetch-models`` copies a shipped run's models, checked
against the package's checksums, into a cache where ``load_pretrained`` finds them by their usual path."""

from __future__ import annotations

import io
import shutil
import sys
import tarfile
from pathlib import Path

import pytest

from divmorph.cli import main as cli
from divmorph.pretrained import PretrainedError, load_pretrained
from divmorph.shipped import ShippedModelsError, fetch_models, shipped_runs

REPO = Path(__file__).resolve().parents[1]
RUN = REPO / "results" / "cpu100"
pytestmark = [pytest.mark.shipped_results, pytest.mark.skipif(not RUN.is_dir(), reason="needs the checkout's results/cpu100")]


def test_the_shipped_checksums_are_those_of_the_shipped_files():
    """A re-saved model without a new manifest would make every fetch fail: the manifest is current."""
    sys.path.insert(0, str(REPO / "tools"))
    try:
        from shipped_models import manifest
    finally:
        sys.path.pop(0)
    assert manifest() == shipped_runs()
    assert {"teachers/FT/model.zip", "student/vecnormalize.pkl", "run.json", "robot_sets.json"} <= set(shipped_runs()["cpu100"])


def test_a_fetched_run_loads_by_its_usual_path_from_anywhere(tmp_path, monkeypatch, official_cache, capsys):
    """From a folder with no ``results/``, the README's path fails naming the fetch command; after
    ``divmorph fetch-models cpu100 --source <checkout>`` it loads the teacher with its robots and
    statistics (break: drop the cache lookup in ``find_model`` -> "no such file or directory")."""
    monkeypatch.setenv("DIVMORPH_MODELS", str(tmp_path / "models"))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(PretrainedError, match="divmorph fetch-models cpu100"):
        load_pretrained("results/cpu100/teachers/FT")
    assert cli(["fetch-models", "cpu100", "--source", str(REPO)]) == 0
    assert str(tmp_path / "models" / "cpu100") in capsys.readouterr().out
    teacher = load_pretrained("results/cpu100/teachers/FT")
    assert teacher.saved.model == tmp_path / "models" / "cpu100" / "teachers" / "FT" / "model.zip"
    assert teacher.normalizer is not None and len(teacher.robots) == 100
    assert load_pretrained("cpu100/student").saved.model.is_file()


def _archive(path: Path, top: str, change: str | None = None) -> Path:
    """A .tar.gz of the run's shipped files under ``<top>/results/cpu100/`` (a code host's archive), ``change`` altered."""
    with tarfile.open(path, "w:gz", compresslevel=1) as tar:
        for relative in shipped_runs()["cpu100"]:
            data = (RUN / relative).read_bytes()
            if relative == change:
                data = data[:-1] + bytes([data[-1] ^ 1])
            info = tarfile.TarInfo(f"{top}/results/cpu100/{relative}")
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return path


def test_an_archive_is_fetched_and_a_changed_file_is_refused_with_nothing_installed(tmp_path):
    cache = tmp_path / "models"
    bad = _archive(tmp_path / "bad.tar.gz", "divmorph-0123abc", change="teachers/FT/model.zip")
    with pytest.raises(ShippedModelsError, match="teachers/FT/model.zip in .* differs"):
        fetch_models("cpu100", bad, cache=cache)
    assert not (cache / "cpu100").exists() and not [p for p in cache.iterdir() if p.name.startswith(".")]
    good = _archive(tmp_path / "good.tar.gz", "divmorph-0123abc")
    folder = fetch_models("cpu100", good, cache=cache)
    assert (folder / "teachers" / "FT" / "model.zip").read_bytes() == (RUN / "teachers" / "FT" / "model.zip").read_bytes()
    with pytest.raises(ShippedModelsError, match="no shipped run 'cpu'"):
        fetch_models("cpu", good, cache=cache)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ShippedModelsError, match="has no results/cpu100/"):
        fetch_models("cpu100", empty, cache=tmp_path / "other", force=True)
    shutil.rmtree(cache)


def test_an_unreachable_models_source_says_what_to_give_instead(tmp_path):
    """Offline, a URL source fails naming what ``--source`` takes instead (break: the bare "could not download" -> fails)."""
    with pytest.raises(ShippedModelsError, match=r"could not download .*give --source a clone of the divmorph repository"):
        fetch_models("cpu100", "http://127.0.0.1:9/divmorph.tar.gz", cache=tmp_path / "models")
