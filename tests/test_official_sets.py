"""Fetching the official unimals_100 sets: served over loopback HTTP, from a directory and from
archives; truncated, corrupted, tampered and unsafe archives; the set names everywhere."""

from __future__ import annotations

import functools
import http.server
import io
import tarfile
import threading
from pathlib import Path

import gymnasium as gym
import pytest
from conftest import OFFICIAL_TRAIN

import unimal_envs  # noqa: F401
from unimal_envs.morphology import official as O
from unimal_envs.morphology.cli import main as cli_main
from unimal_envs.morphology.loader import MorphologyError, morphology_files

pytestmark = pytest.mark.skipif(not (OFFICIAL_TRAIN / "xml").is_dir(), reason="official unimals_100 train set not available")
TOP = f"Universal-Morphology-Control-{O.PINNED_COMMIT}"


def make_archive(path: Path, tamper: bool = False, extra: tuple[str, bytes] | None = None) -> Path:
    """A tarball laid out like GitHub's archive of the authors' repository, holding data/train."""
    with tarfile.open(path, "w:gz") as tar:
        readme = tarfile.TarInfo(f"{TOP}/README.md")  # a file outside the sets: never extracted
        readme.size = 6
        tar.addfile(readme, io.BytesIO(b"readme"))
        for sub in ("xml", "metadata"):
            for i, file in enumerate(sorted((OFFICIAL_TRAIN / sub).iterdir())):
                data = file.read_bytes()
                if tamper and sub == "xml" and i == 0:
                    data = data.replace(b'gear="', b'gear="1', 1)  # still a valid robot, different bytes
                info = tarfile.TarInfo(f"{TOP}/data/train/{sub}/{file.name}")
                info.size = len(data)
                tar.addfile(info, io.BytesIO(data))
        if extra is not None:
            info = tarfile.TarInfo(extra[0])
            info.size = len(extra[1])
            tar.addfile(info, io.BytesIO(extra[1]))
    return path


@pytest.fixture(scope="module")
def archive(tmp_path_factory) -> Path:
    return make_archive(tmp_path_factory.mktemp("src") / "repo.tar.gz")


@pytest.fixture
def server(tmp_path):
    """An HTTP server on 127.0.0.1 serving ``tmp_path/www``; yields (base url, folder)."""
    www = tmp_path / "www"
    www.mkdir()
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(www))
    handler.log_message = lambda *a, **k: None
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}", www
    httpd.shutdown()
    httpd.server_close()


def leftovers(cache: Path) -> list[str]:
    return sorted(p.name for p in cache.iterdir()) if cache.exists() else []


def test_fetch_over_http_then_use_the_set_by_name(archive, server, tmp_path, monkeypatch):
    url, www = server
    (www / "repo.tar.gz").write_bytes(archive.read_bytes())
    cache = tmp_path / "cache"
    folders = O.fetch(f"{url}/repo.tar.gz", ["train"], cache=cache)
    folder = folders["unimals100-train"]
    assert leftovers(cache) == ["unimals100-train"]  # no staging folder, no downloaded archive left
    assert len(list((folder / "xml").glob("*.xml"))) == 100 and len(list((folder / "metadata").glob("*.json"))) == 100
    assert (folder / "xml" / "floor-1409-0-12-01-12-30-07.xml").read_bytes() == (
        OFFICIAL_TRAIN / "xml" / "floor-1409-0-12-01-12-30-07.xml"
    ).read_bytes()
    assert (folder / O.MANIFEST).is_file()

    # Idempotent: a cached set is not fetched again (this source would fail).
    (www / "repo.tar.gz").unlink()
    assert O.fetch(f"{url}/repo.tar.gz", ["train"], cache=cache) == folders

    monkeypatch.setenv("UNIMAL_DATA", str(cache))
    files = morphology_files("unimals100-train")
    assert len(files) == 100 and files[0].parent == folder / "xml"
    env = gym.make("Unimal-FT-v0", morphologies="unimals100-train")
    _, info = env.reset(seed=0, options={"morphology": "floor-1409-0-12-01-12-30-07"})
    assert info["morphology"] == "floor-1409-0-12-01-12-30-07"
    env.close()

    # The pipeline resolves the name and records which set and source it used.
    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.robots import robot_files, robot_set_record

    assert [f.stem for f in robot_files("unimals100-train", 3)] == [f.stem for f in files[:3]]
    profile = load_profile("demo")
    profile.train_set, profile.train_robots = "unimals100-train", 2
    record = robot_set_record(profile)
    assert record["train"]["set"] == "unimals100-train" and record["train"]["source"] == f"{url}/repo.tar.gz"
    assert record["train"]["robots"] == [f.stem for f in files[:2]]


def test_fetch_from_a_directory_and_the_cli(tmp_path, capsys):
    cache = tmp_path / "cache"
    assert cli_main(["fetch", "--source", str(OFFICIAL_TRAIN), "--sets", "train", "--cache", str(cache)]) == 0
    assert "unimals100-train: 100 robots" in capsys.readouterr().out
    assert len(list((cache / "unimals100-train" / "xml").glob("*.xml"))) == 100


@pytest.mark.parametrize("damage", ["truncated", "corrupted"])
def test_a_damaged_download_is_a_clear_error_and_installs_nothing(archive, server, tmp_path, damage):
    url, www = server
    data = bytearray(archive.read_bytes())
    if damage == "truncated":
        data = data[: len(data) // 2]
    else:
        for i in range(len(data) // 2, len(data) // 2 + 64):
            data[i] ^= 0xFF
    (www / "repo.tar.gz").write_bytes(bytes(data))
    cache = tmp_path / "cache"
    with pytest.raises(O.FetchError, match="truncated or corrupted"):
        O.fetch(f"{url}/repo.tar.gz", ["train"], cache=cache)
    assert leftovers(cache) == []
    with pytest.raises(MorphologyError, match="not in the cache"):
        O.official_set_dir("unimals100-train", cache)


def test_a_tampered_robot_fails_the_checksums(tmp_path):
    cache = tmp_path / "cache"
    with pytest.raises(O.FetchError, match="checksums"):
        O.fetch(make_archive(tmp_path / "bad.tar.gz", tamper=True), ["train"], cache=cache)
    assert leftovers(cache) == []


@pytest.mark.parametrize("member", ["../evil.txt", "/tmp/evil.txt", f"{TOP}/data/train/../../evil.txt"])
def test_unsafe_archive_members_are_refused(tmp_path, member):
    cache = tmp_path / "cache"
    with pytest.raises(O.FetchError, match="absolute path or a '..'"):
        O.fetch(make_archive(tmp_path / "evil.tar.gz", extra=(member, b"x")), ["train"], cache=cache)
    assert leftovers(cache) == [] and not (tmp_path / "evil.txt").exists()


def test_wrong_count_and_missing_folder(tmp_path):
    with pytest.raises(O.FetchError, match="holds no data/test/xml"):
        O.fetch(make_archive(tmp_path / "a.tar.gz"), ["test"], cache=tmp_path / "c1")
    partial = tmp_path / "partial"
    for sub in ("xml", "metadata"):
        (partial / "train" / sub).mkdir(parents=True)
        for file in sorted((OFFICIAL_TRAIN / sub).iterdir())[:5]:
            (partial / "train" / sub / file.name).write_bytes(file.read_bytes())
    with pytest.raises(O.FetchError, match="expected 100 robots"):
        O.fetch(partial, ["train"], cache=tmp_path / "c2")


def test_a_set_not_fetched_names_the_command(tmp_path, monkeypatch):
    monkeypatch.setenv("UNIMAL_DATA", str(tmp_path))
    with pytest.raises(MorphologyError, match=r"python -m unimal_envs\.morphology fetch --sets test"):
        morphology_files("unimals100-test")
    with pytest.raises(MorphologyError, match="fetch --sets mutants"):
        gym.make("Unimal-FT-v0", morphologies="unimals100-mutants")


OFFICIAL_TEST = OFFICIAL_TRAIN.parent / "test"
needs_test_set = pytest.mark.skipif(not (OFFICIAL_TEST / "xml").is_dir(), reason="official unimals_100 test set not available")


def copy_test_set(target: Path) -> Path:
    """A directory source holding ``test/{xml,metadata}`` copied from the official test set."""
    for sub in ("xml", "metadata"):
        (target / "test" / sub).mkdir(parents=True)
        for file in (OFFICIAL_TEST / sub).iterdir():
            (target / "test" / sub / file.name).write_bytes(file.read_bytes())
    return target


@needs_test_set
def test_the_test_set_leaves_out_its_byte_copies_of_training_robots(tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    folder = O.fetch(copy_test_set(tmp_path / "src"), ["test"], cache=cache)["unimals100-test"]
    names = sorted(p.stem for p in (folder / "xml").glob("*.xml"))
    assert len(names) == 97 and not set(names) & set(O.TEST_BYTE_COPIES)
    assert not any((folder / "metadata" / f"{n}.json").exists() for n in O.TEST_BYTE_COPIES)
    # what is left holds no training robot's bytes; what was left out is named, each with its original
    training = {f.read_bytes() for f in (OFFICIAL_TRAIN / "xml").iterdir()}
    assert not any((folder / "xml" / f"{n}.xml").read_bytes() in training for n in names)
    for copy, original in O.TEST_BYTE_COPIES.items():
        assert (OFFICIAL_TEST / "xml" / f"{copy}.xml").read_bytes() == (OFFICIAL_TRAIN / "xml" / f"{original}.xml").read_bytes()
    manifest = (folder / O.MANIFEST).read_text()
    assert '"robots": 97' in manifest and all(n in manifest for n in O.TEST_BYTE_COPIES)
    monkeypatch.setenv("UNIMAL_DATA", str(cache))
    assert [p.stem for p in morphology_files("unimals100-test")] == names


@needs_test_set
def test_a_test_set_with_another_copy_of_a_training_robot_is_refused(tmp_path):
    source = copy_test_set(tmp_path / "src")
    victim = sorted(n for n in (p.stem for p in (source / "test" / "xml").iterdir()) if n not in O.TEST_BYTE_COPIES)[0]
    training = sorted((OFFICIAL_TRAIN / "xml").iterdir())[-1]
    (source / "test" / "xml" / f"{victim}.xml").write_bytes(training.read_bytes())
    with pytest.raises(O.FetchError, match=victim):
        O.fetch(source, ["test"], cache=tmp_path / "cache")
    assert not (tmp_path / "cache" / "unimals100-test").exists()


@needs_test_set
def test_a_cache_fetched_with_the_byte_copies_still_lists_97_robots(tmp_path, monkeypatch):
    # a cache written before the copies were left out: the 102 files and a manifest
    folder = copy_test_set(tmp_path) / "test"
    (folder / O.MANIFEST).write_text("{}")
    folder.rename(tmp_path / "unimals100-test")
    monkeypatch.setenv("UNIMAL_DATA", str(tmp_path))
    files = morphology_files("unimals100-test")
    assert len(files) == 97 and not {f.stem for f in files} & set(O.TEST_BYTE_COPIES)


def test_the_validation_split_holds_out_ten_training_robots_of_every_family(tmp_path, monkeypatch):
    O.fetch(OFFICIAL_TRAIN, ["train"], cache=tmp_path)
    monkeypatch.setenv("UNIMAL_DATA", str(tmp_path))
    train, val, fit = (set(p.stem for p in morphology_files(f"unimals100-{s}")) for s in ("train", "val", "fit"))
    assert len(val) == 10 and len(fit) == 90 and val | fit == train and not val & fit
    assert {name.split("-")[0] for name in val} == {"floor", "mvt", "vt"}
    env = gym.make("Unimal-FT-v0", morphologies="unimals100-val")
    assert {m.name for m in env.unwrapped.morphologies} == val
    env.close()


def test_a_run_records_a_held_out_set_that_is_not_fetched_here_instead_of_failing(tmp_path, monkeypatch):
    """A stage that only trains (a GPU job carrying the training robots) may run where the novel set
    is not fetched: the run's record says so; the training robots must be there."""
    from divmorph.pipeline.config import load_profile
    from divmorph.pipeline.robots import robot_set_record

    monkeypatch.setenv("UNIMAL_DATA", str(tmp_path))
    O.fetch(OFFICIAL_TRAIN, ["train"], cache=tmp_path)
    record = robot_set_record(load_profile("gpu"))
    assert len(record["train"]["robots"]) == 100 and "fetch --sets test" in record["novel"]["not_on_this_machine"]
    with pytest.raises(MorphologyError, match="unimals100-test"):
        robot_set_record(load_profile("gpu", overrides={"train_set": "unimals100-test"}))


def test_an_unreachable_source_says_how_to_fetch_offline(tmp_path):
    """Offline, the download error names ``--source`` and the archive to bring (break: the bare
    "could not download URL: <reason>" message -> fails)."""
    with pytest.raises(O.FetchError) as raised:
        O.fetch("http://127.0.0.1:9/unimals.tar.gz", ["train"], cache=tmp_path / "cache")  # port 9: nothing answers
    said = str(raised.value)
    assert "could not download http://127.0.0.1:9/unimals.tar.gz" in said
    assert "--source PATH" in said and O.PINNED_COMMIT in said and "Universal-Morphology-Control" in said
    assert not (tmp_path / "cache" / "unimals100-train").exists()
