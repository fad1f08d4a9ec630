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
        "divmorph/examples/distill_dagger.py",
        "divmorph/examples/transfer.py",
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
    # the README's two commands, on the same env and packages
    zoo = ["--algo", "ppo", "--env", "Unimal-FT-v0", "--gym-packages", "unimal_envs", "sb3_divmorph", "-f", "logs"]
    training = ["--conf-file", "sb3_divmorph.zoo", "-n", "64", "--seed", "0", "-params", "n_envs:1", "n_steps:64", "batch_size:64"]
    train = _run([sys.executable, "-m", "rl_zoo3.train", *zoo, *training, "n_epochs:1", tiny], elsewhere, site)
    assert train.returncode == 0, train.stderr[-3000:]
    run = elsewhere / "logs" / "ppo" / "Unimal-FT-v0_1"
    assert (run / "Unimal-FT-v0.zip").is_file() and (run / "Unimal-FT-v0" / "vecnormalize.pkl").is_file()
    # enjoy replays it (rl_zoo3.enjoy imports requests: the [zoo] extra brings it)
    enjoy = _run([sys.executable, "-m", "rl_zoo3.enjoy", *zoo, "--exp-id", "1", "-n", "20", "--no-render"], elsewhere, site)
    assert enjoy.returncode == 0, enjoy.stderr[-3000:]
    assert "Loading" in enjoy.stdout + enjoy.stderr

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


def _plain_install(folder: Path) -> Path:
    """A Python with only what a plain ``pip install divmorph`` brings: a new virtual environment whose
    site-packages links to this one's entries, less the packages that only the extras bring (rl_zoo3,
    pandas, requests, Ray, MuJoCo Warp... and what only they need) and less this checkout's editable
    install. Returns its ``python``."""
    import importlib.metadata as metadata
    import site
    import venv

    from packaging.requirements import Requirement

    def closure(name: str) -> set[str]:
        seen: set[str] = set()
        stack = [name]
        while stack:
            dist = stack.pop().lower().replace("_", "-")
            if dist in seen:
                continue
            seen.add(dist)
            try:
                requires = metadata.requires(dist) or []
            except metadata.PackageNotFoundError:
                continue
            for text in requires:
                requirement = Requirement(text)
                if requirement.marker is None or requirement.marker.evaluate({"extra": ""}):
                    stack.append(requirement.name)
        return seen

    base = closure("divmorph")
    extras = set().union(*(closure(r.name) for r in map(Requirement, metadata.requires("divmorph") or []) if r.marker is not None))
    only_extras = extras - base
    hidden = {
        module
        for module, dists in metadata.packages_distributions().items()
        if all(d.lower().replace("_", "-") in only_extras for d in dists)
    }
    assert {"pandas", "rl_zoo3", "requests", "ray"} <= hidden, hidden
    venv.EnvBuilder(with_pip=False).create(folder)
    target = next((folder / "lib").glob("python*/site-packages"))
    source = Path(next(p for p in site.getsitepackages() if Path(p).is_dir()))
    for entry in source.iterdir():
        name = entry.name
        stem = name.split(".")[0].split("-")[0]
        dist = name.split("-")[0].lower().replace("_", "-") if name.endswith((".dist-info", ".egg-info")) else None
        if stem in hidden or (dist is not None and dist in only_extras) or "divmorph" in name.lower():
            continue
        (target / name).symlink_to(entry)
    return folder / "bin" / "python"


def test_a_plain_install_runs_every_command_that_needs_no_extra(installed, tmp_path):
    """Without the extras (no pandas, rl_zoo3, requests, Ray, Warp), ``divmorph record`` with no ``--robot``
    films the run's best training robot, ``divmorph plot`` draws the run's logs and each command's
    ``--help`` answers (break: import pandas in ``divmorph.pretrained.best_robots`` -> "No module named 'pandas'")."""
    import csv

    from test_usability import tiny_model

    site, elsewhere = installed
    python = str(_plain_install(tmp_path / "plain"))
    run = tmp_path / "run"
    teacher = run / "teachers" / "FT"
    tiny_model(teacher, steps=64)
    (run / "run.json").write_text('{"configuration": {}}')
    (run / "robot_sets.json").write_text('{"train": {"set": "train", "robots": ["train-000", "train-001"]}}')
    (run / "evaluate").mkdir()
    with open(run / "evaluate" / "returns.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["model", "task", "split", "morphology", "episode", "return", "length", "seed"])
        writer.writerows([["teacher", "FT", "train", "train-000", 0, 5.0, 10, ""], ["teacher", "FT", "train", "train-001", 0, 9.0, 10, ""]])
    divmorph = [python, str(site / "bin" / "divmorph")]
    hidden = _run([python, "-c", "import pandas"], elsewhere, site)
    assert hidden.returncode != 0 and "No module named 'pandas'" in hidden.stderr  # the plain install lacks what it should
    video = tmp_path / "best.gif"
    args = [str(teacher), "--steps", "6", "--width", "32", "--height", "32", "--no-progress", "--out", str(video)]
    filmed = _run([*divmorph, "record", *args], elsewhere, site)
    assert filmed.returncode == 0, filmed.stderr[-3000:]
    assert "no --robot: filming train-001" in filmed.stdout and video.is_file()
    logs = teacher / "logs" / "run-0"  # a pipeline stage's SB3 log: the first row before any episode ended
    logs.mkdir(parents=True)
    (logs / "progress.csv").write_text("time/total_timesteps,rollout/ep_rew_mean\n32,\n64,1.5\n96,2.5\n")
    plotted = _run([*divmorph, "plot", str(teacher), "--out", str(tmp_path / "curve.png")], elsewhere, site)
    assert plotted.returncode == 0, plotted.stderr[-3000:]
    assert (tmp_path / "curve.png").is_file()
    for command in ("pipeline", "teachers", "distill", "transfer", "evaluate", "report", "export", "record", "plot", "fetch-models"):
        helped = _run([*divmorph, command, "--help"], elsewhere, site)
        assert helped.returncode == 0 and "usage:" in helped.stdout, (command, helped.stderr[-2000:])


def test_the_installed_packages_declare_their_type_hints(installed):
    site, _ = installed
    assert all((site / package / "py.typed").is_file() for package in ("sb3_divmorph", "unimal_envs", "divmorph"))


def test_the_readmes_first_python_example_runs_from_the_wheel(installed, official_sets):
    """The README's first Python block (the official training robots, ``PPO("DivMorphPolicy", env)``) runs
    from the installed wheel in a folder outside the checkout, after the robot fetch it names, and says
    what it trained (break: drop the policy aliases' registration in ``sb3_divmorph/__init__.py`` ->
    "Policy DivMorphPolicy unknown")."""
    import re

    site, elsewhere = installed
    readme = (REPO / "README.md").read_text()
    block = re.findall(r"```python\n(.*?)```", readme, flags=re.S)[0]
    assert 'PPO("DivMorphPolicy", env' in block and "results/" not in block
    assert 'morphologies="unimals100-train"' in block and "torch.set_num_threads(1)" in block
    assert "python -m unimal_envs.morphology fetch" in readme.split(block)[0]  # the fetch is named before the block
    done = _run([sys.executable, "-c", block], elsewhere, site, env={"UNIMAL_DATA": str(official_sets)})
    assert done.returncode == 0, done.stderr[-3000:]
    assert re.search(r"^DivMorph trained 128 steps on Escape over 100 official training robots", done.stdout, flags=re.M), done.stdout


def test_the_examples_run_from_the_wheel(installed):
    """A pip user reaches the examples as ``python -m divmorph.examples.NAME`` (break: drop the
    ``divmorph.examples`` mapping in setup.py -> "No module named divmorph.examples")."""
    site, elsewhere = installed
    for name in ("distill_dagger", "load_run_model", "transfer", "export_actor"):
        helped = _run([sys.executable, "-m", f"divmorph.examples.{name}", "--help"], elsewhere, site)
        assert helped.returncode == 0 and "usage:" in helped.stdout, (name, helped.stderr[-2000:])


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
