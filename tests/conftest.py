"""Shared fixtures: a tiny hand-written UNIMAL builder, and the robot sets tests run on."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
# Every worker starts from an empty robot cache of its own: a test that reads an official set by name
# must ask for the `official_cache` fixture, never find the user's ~/.cache/unimal_envs (or another test's).
_EMPTY_CACHE = tempfile.mkdtemp(prefix="unimal-data-empty-")
os.environ["UNIMAL_DATA"] = _EMPTY_CACHE

import pytest  # noqa: E402

OFFICIAL = Path(__file__).resolve().parents[1].parent / "shared" / "unimals_100"
OFFICIAL_TRAIN = OFFICIAL / "train"


def pytest_unconfigure(config) -> None:
    shutil.rmtree(_EMPTY_CACHE, ignore_errors=True)


def unimal_xml(legs: int = 2, hinges: str = "xy", torso_z: float = 0.6, extra_body: str = "", joint_type: str = "hinge") -> str:
    """A minimal valid UNIMAL robot: a torso with ``legs`` capsule legs pointing down and outwards.

    :param legs: number of limbs attached to the torso.
    :param hinges: "x", "y" or "xy": the hinges of every leg.
    :param torso_z: spawn height of the torso.
    :param extra_body: raw MJCF appended inside the torso body (to build broken robots).
    :param joint_type: type of the first leg's first joint (to build non-UNIMAL robots).
    """
    bodies, motors = [], []
    for k in range(legs):
        angle = 360.0 * k / legs
        import math

        dx, dy = round(0.7 * math.cos(math.radians(angle)), 2), round(0.7 * math.sin(math.radians(angle)), 2)
        joints = []
        for axis in hinges:
            vec = "1 0 0" if axis == "x" else "0 1 0"
            jtype = joint_type if (k == 0 and not joints) else "hinge"
            rng = 'range="-45 45"' if jtype == "hinge" else 'limited="false"'
            joints.append(f'<joint name="limb{axis}/{k}" type="{jtype}" pos="0 0 0" axis="{vec}" {rng}/>')
            motors.append(f'<motor name="limb{axis}/{k}" joint="limb{axis}/{k}" gear="200"/>')
        bodies.append(
            f'<body name="limb/{k}" pos="{dx * 0.14:.3f} {dy * 0.14:.3f} -0.07">{"".join(joints)}'
            f'<geom name="limb/{k}" type="capsule" fromto="0 0 0 {dx * 0.4:.3f} {dy * 0.4:.3f} -0.4" size="0.05" density="800"/></body>'
        )
    return f"""<mujoco model="unimal">
  <compiler angle="degree"/>
  <option timestep="0.005"/>
  <default><motor ctrlrange="-1 1" ctrllimited="true"/><joint damping="1" stiffness="1" armature="1" limited="true"/></default>
  <worldbody>
    <body name="torso/0" pos="0 0 {torso_z}">
      <joint name="root" type="free" limited="false" damping="0" stiffness="0" armature="0"/>
      <geom name="torso/0" type="sphere" size="0.1" density="800"/>
      {"".join(bodies)}{extra_body}
    </body>
  </worldbody>
  <actuator>{"".join(motors)}</actuator>
</mujoco>
"""


@pytest.fixture
def write_robot(tmp_path):
    """Write an MJCF string to ``tmp_path/<name>.xml`` and return the path."""

    def write(xml: str, name: str = "robot") -> Path:
        path = tmp_path / f"{name}.xml"
        path.write_text(xml)
        return path

    return write


@pytest.fixture(scope="session")
def official_train() -> Path:
    """The official unimals_100 training set, when this checkout sits next to ../shared."""
    if not (OFFICIAL_TRAIN / "xml").is_dir():
        pytest.skip(f"official unimals_100 set not found at {OFFICIAL_TRAIN}")
    return OFFICIAL_TRAIN


@pytest.fixture(scope="session")
def official_sets(tmp_path_factory) -> Path:
    """A robot cache holding the official ``unimals100-train`` and ``unimals100-test`` sets, installed
    once per worker from ../shared (the same fetch and checks a user's ``unimal-envs fetch`` runs)."""
    if not all((OFFICIAL / name / "xml").is_dir() for name in ("train", "test")):
        pytest.skip(f"official unimals_100 sets not found at {OFFICIAL}")
    from unimal_envs.morphology.official import fetch

    cache = tmp_path_factory.mktemp("unimal-data")
    fetch(OFFICIAL, ["train", "test"], cache=cache)
    return cache


@pytest.fixture
def official_cache(official_sets, monkeypatch) -> Path:
    """Point ``$UNIMAL_DATA`` at :func:`official_sets` for one test, so the official sets resolve by
    name (``unimals100-train``, ``unimals100-test``, their subsets)."""
    monkeypatch.setenv("UNIMAL_DATA", str(official_sets))
    return official_sets


@pytest.fixture(scope="session")
def train_files() -> list[Path]:
    """Three robots of the shipped generated ``train`` set."""
    from unimal_envs.morphology.loader import morphology_files

    return morphology_files("train")[:3]


@pytest.fixture(scope="session")
def archived_study(tmp_path_factory):
    """``archived_study("results/cpu") -> Path``: the study as its archive holds it (its raw runs out of
    the tree, ``results/archive.json``), restored under a temporary folder by ``tools/archive_runs.py``
    -- the README's command, with ``--into``. Skips where git or the archive's commit is absent."""
    import importlib.util

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("archive_runs", root / "tools" / "archive_runs.py")
    archive_runs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(archive_runs)
    into = tmp_path_factory.mktemp("archived")
    done: set[str] = set()

    def restore(path: str) -> Path:
        if path not in done:
            if shutil.which("git") is None:
                pytest.skip("git is not installed")
            try:
                archive_runs.restore([str(root / path)], into)
            except archive_runs.ArchiveError as error:
                pytest.skip(str(error))
            done.add(path)
        return into / path

    return restore
