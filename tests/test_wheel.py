"""The built wheel, installed into a fresh folder and run from another one: the shipped profiles
and rl-zoo hyperparameters are found, rl-zoo trains with them, and ``divmorph record`` films the result."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import imageio.v3 as iio
import pytest

REPO = Path(__file__).resolve().parents[1]


def _run(command: list[str], cwd: Path, site: Path, timeout: int = 300, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    # Only the installed copy on the path (not this checkout); one torch thread (small models, busy CPUs).
    merged = {
        **os.environ,
        **(env or {}),
        "PYTHONPATH": str(site),
        "MUJOCO_GL": "egl",
        "OMP_NUM_THREADS": "1",
        "HF_HUB_OFFLINE": "1",
        "TRANSFORMERS_OFFLINE": "1",
    }
    return subprocess.run(command, cwd=cwd, env=merged, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, Path]:
    """``(site folder, another working folder)``: the wheel built from this checkout, installed."""
    root = tmp_path_factory.mktemp("wheel")
    # Build from a clean copy: pip builds in the source folder, and a build/ left there would both
    # litter the checkout and carry files into later wheels after they are deleted here.
    source = root / "source"
    shutil.copytree(
        REPO,
        source,
        ignore=shutil.ignore_patterns(
            ".git",
            ".venv",
            "build",
            "runs",
            "logs",
            "results",
            "tests",
            "benchmarks",
            "studies",
            "tools",
            "*.egg-info",
            "__pycache__",
            ".*cache",
            ".hypothesis",
        ),
    )
    build = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-v", "-w", str(root / "dist"), str(source)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, build.stderr[-3000:]
    # packaging metadata that setuptools will stop accepting is an error to come: none is left
    said = build.stdout + build.stderr
    assert "BuildBackendWarning" not in said and "SetuptoolsDeprecationWarning" not in said, said[-3000:]
    wheel = next((root / "dist").glob("divmorph-*.whl"))
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
    shipped = {
        "unimal_envs/assets/unimal_template.xml",
        "unimal_envs/data/task_embeddings.npz",
        "unimal_envs/data/unimals100_train.sha256",
        "unimal_envs/py.typed",
        "sb3_divmorph/py.typed",
        "sb3_divmorph/zoo_configs/divmorph.yml",
        "sb3_divmorph/zoo_configs/ppo.yml",
        "divmorph/py.typed",
        "divmorph/shipped_models.json",
        "divmorph/cli/__init__.py",
        "divmorph/pipeline/transfer.py",
    }
    assert shipped <= names, shipped - names
    for split in ("train", "novel"):  # the 200 generated robots, each with its metadata
        assert sum(n.startswith(f"unimal_envs/data/morphologies/{split}/xml/") for n in names) == 100, split
        assert sum(n.startswith(f"unimal_envs/data/morphologies/{split}/metadata/") for n in names) == 100, split
    assert not any(n.startswith(("tests/", "results/", "studies/")) or "__pycache__" in n for n in names)
    site = root / "site"
    install = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(site), str(wheel)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert install.returncode == 0, install.stderr[-3000:]
    elsewhere = root / "elsewhere"
    elsewhere.mkdir()
    located = _run([sys.executable, "-c", "import sb3_divmorph.zoo as z; print(z.__file__); print(z.zoo_configs_dir())"], elsewhere, site)
    assert located.returncode == 0, located.stderr
    module, configs = located.stdout.split()
    assert Path(module).is_relative_to(site) and Path(configs) == site / "sb3_divmorph" / "zoo_configs"
    return site, elsewhere


def test_installed_cli_finds_its_profiles_from_any_folder(installed):
    site, elsewhere = installed
    divmorph = [sys.executable, str(site / "bin" / "divmorph")]
    listed = _run([*divmorph, "profiles"], elsewhere, site)
    assert listed.returncode == 0, listed.stderr
    assert str(site / "sb3_divmorph" / "zoo_configs" / "divmorph.yml") in listed.stdout
    assert {"demo", "gpu", "cpu"} <= set(listed.stdout.split())
    # the profile's `hyperparams: zoo_configs/ppo.yml` resolves to the installed file
    code = (
        "from divmorph.pipeline.config import load_profile, load_zoo_entry, resolve_path; p = load_profile('demo'); "
        "print(resolve_path(p.teachers.hyperparams), load_zoo_entry(p.teachers.hyperparams, 'Unimal-FT-v0').n_envs)"
    )
    entry = _run([sys.executable, "-c", code], elsewhere, site)
    assert entry.returncode == 0, entry.stderr
    assert entry.stdout.split() == [str(site / "sb3_divmorph" / "zoo_configs" / "ppo.yml"), "4"]
    # a stage reads the profile, and stops only because there is no teacher yet
    stage = _run([*divmorph, "distill", "--profile", "demo", "--out", "run", "--no-progress"], elsewhere, site)
    assert stage.returncode == 2
    assert "profiles file" not in stage.stderr and "teacher for FT not found" in stage.stderr


def test_installed_rl_zoo_trains_with_the_shipped_entries_and_record_films_it(installed):
    site, elsewhere = installed
    tiny = "policy_kwargs:dict(d_model=16, n_layers=1, ff_dim=32, exteroception={})"
    train = _run(
        [
            sys.executable,
            "-m",
            "rl_zoo3.train",
            "--algo",
            "ppo",
            "--env",
            "Unimal-FT-v0",
            "--gym-packages",
            "unimal_envs",
            "sb3_divmorph",
            "--conf-file",
            "sb3_divmorph.zoo",
            "-n",
            "64",
            "-f",
            "logs",
            "--seed",
            "0",
            "-params",
            "n_envs:1",
            "n_steps:64",
            "batch_size:64",
            "n_epochs:1",
            tiny,
        ],
        elsewhere,
        site,
    )
    assert train.returncode == 0, train.stderr[-3000:]
    run = elsewhere / "logs" / "ppo" / "Unimal-FT-v0_1"
    assert (run / "Unimal-FT-v0.zip").is_file() and (run / "Unimal-FT-v0" / "vecnormalize.pkl").is_file()

    video = elsewhere / "ft.mp4"
    record = _run(
        [
            sys.executable,
            str(site / "bin" / "divmorph"),
            "record",
            str(run),
            "--steps",
            "10",
            "--width",
            "64",
            "--height",
            "64",
            "--out",
            str(video),
            "--no-progress",
        ],
        elsewhere,
        site,
    )
    assert record.returncode == 0, record.stderr[-3000:]
    assert "no statistics" not in record.stdout  # the run's vecnormalize.pkl was found and used
    frames = iio.imread(video)
    assert frames.shape[1:] == (64, 64, 3) and 2 <= len(frames) <= 11


def test_the_installed_packages_declare_their_type_hints(installed):
    site, _ = installed
    assert all((site / package / "py.typed").is_file() for package in ("sb3_divmorph", "unimal_envs", "divmorph"))


def test_the_readmes_first_python_example_runs_from_the_wheel(installed):
    """The README's first Python block (an env and ``PPO("DivMorphPolicy", env)``) runs from the installed
    wheel in a folder outside the checkout, with nothing fetched (break: drop the policy aliases'
    registration in ``sb3_divmorph/__init__.py`` -> "Policy DivMorphPolicy unknown")."""
    import re

    site, elsewhere = installed
    block = re.findall(r"```python\n(.*?)```", (REPO / "README.md").read_text(), flags=re.S)[0]
    assert 'PPO("DivMorphPolicy", env' in block and "results/" not in block
    done = _run([sys.executable, "-c", block + "\nprint('trained', model.num_timesteps)"], elsewhere, site)
    assert done.returncode == 0, done.stderr[-3000:]
    assert re.search(r"^trained \d+", done.stdout, flags=re.M), done.stdout


@pytest.mark.shipped_results
def test_the_readme_quick_start_runs_from_the_wheel_after_the_documented_fetch(installed, official_sets, tmp_path):
    """A pip user: ``divmorph fetch-models cpu100 --source <checkout>`` (the README's command), then the
    README's quick-start block, run from a folder with no ``results/``, prints a return for each robot
    in the order the block names them (break: leave out the fetch -> "no such file or directory")."""
    import re

    site, elsewhere = installed
    readme = (REPO / "README.md").read_text()
    block = next(b for b in re.findall(r"```python\n(.*?)```", readme, flags=re.S) if "load_pretrained(" in b and "evaluate(" in b)
    env = {"DIVMORPH_MODELS": str(tmp_path / "models"), "UNIMAL_DATA": str(official_sets)}
    fetched = _run(
        [sys.executable, str(site / "bin" / "divmorph"), "fetch-models", "cpu100", "--source", str(REPO)], elsewhere, site, env=env
    )
    assert fetched.returncode == 0, fetched.stderr[-3000:]
    quick = _run([sys.executable, "-c", block], elsewhere, site, env=env)
    assert quick.returncode == 0, quick.stderr[-3000:]
    asked = re.findall(r'"([a-z]+-\d{4}[-\d]*)"', block)
    assert re.findall(r"^(\S+): return \d+", quick.stdout, flags=re.M) == asked, quick.stdout
