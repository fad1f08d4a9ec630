"""The README and ``examples/`` as a new user meets them: every Python block of the README and every
example runs (at the small budgets they declare), and every command a shell block names exists."""

from __future__ import annotations

import importlib.util
import os
import re
import runpy
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch as th
from conftest import OFFICIAL_TRAIN

from divmorph.cli import main as cli

REPO = Path(__file__).resolve().parents[1]
README = (REPO / "README.md").read_text()
#: the README and the documentation pages: every code block of either is held to the same rules
PAGES = [README, *(p.read_text() for folder in ("docs", "docs/claims") for p in sorted((REPO / folder).glob("*.md")))]
EXAMPLES = REPO / "examples"
#: every example with the arguments the test runs it with (smaller than the defaults where it matters)
EXAMPLE_RUNS = [
    ("distill_dagger.py", ["--steps", "256", "--out", "run"]),
    ("load_run_model.py", ["run/student", "--task", "FT", "--robots", "1", "--steps", "20"]),
    ("transfer.py", ["run/student", "--task", "Escape", "--steps", "1024", "--robots", "2", "--eval-steps", "50", "--out", "run/escape"]),
    ("export_actor.py", ["run/student", "--task", "FT", "--robot", "train-000", "--out", "exported"]),
]


def code_blocks(language: str, pages: list[str] | None = None) -> list[str]:
    """The ``language`` code blocks of the README and the docs pages (or of ``pages``), in order."""
    return [
        code
        for page in (PAGES if pages is None else pages)
        for lang, code in re.findall(r"```(\w*)\n(.*?)```", page, flags=re.S)
        if lang == language
    ]


def run_example(name: str, args: list[str], monkeypatch, capsys) -> str:
    monkeypatch.setattr(sys, "argv", [str(EXAMPLES / name), *args])
    runpy.run_path(str(EXAMPLES / name), run_name="__main__")
    return capsys.readouterr().out


@pytest.fixture
def restore_threads():
    threads = th.get_num_threads()
    yield
    th.set_num_threads(threads)


def test_readme_opens_with_make_demo_and_make_test():
    first = code_blocks("bash", [README])[0].splitlines()
    assert [line.split()[:2] for line in first[:2]] == [["make", "demo"], ["make", "test"]]


def test_every_example_and_python_block_runs(tmp_path, monkeypatch, capsys, restore_threads, official_cache):
    assert sorted(p.name for p in EXAMPLES.glob("*.py") if p.name != "__init__.py") == sorted(name for name, _ in EXAMPLE_RUNS), (
        "an example is not run here"
    )
    monkeypatch.chdir(tmp_path)

    out = run_example(*EXAMPLE_RUNS[0], monkeypatch, capsys)
    for folder in ("run/teachers/FT", "run/teachers/Incline", "run/student"):
        assert (tmp_path / folder / "model.zip").is_file() and (tmp_path / folder / "vecnormalize.pkl").is_file()
    assert "labelled states" in out

    out = run_example(*EXAMPLE_RUNS[1], monkeypatch, capsys)
    assert re.search(r"train-000, episode 0: return -?\d+\.\d over \d+ steps", out)

    out = run_example(*EXAMPLE_RUNS[2], monkeypatch, capsys)
    ratio = float(re.search(r"update ratio (\S+) \(configured 0.1\)", out).group(1))
    assert 0.03 < ratio < 0.3  # the measured learngene / selected-tailor ratio is near its 0.1 target
    assert re.search(r"zero-shot: mean return -?\d", out) and re.search(r"after \d+ steps: mean return -?\d", out)
    assert "fixed-gate transfer has not yet been seen to learn" in out  # a lower return is not mistaken for a fault
    assert (tmp_path / "run" / "escape" / "model.zip").is_file() and (tmp_path / "run" / "escape" / "vecnormalize.pkl").is_file()
    with pytest.raises(SystemExit):  # a MetaMorph teacher has no gates to fix: said so, no raw state_dict error
        run_example("transfer.py", ["run/teachers/FT", "--task", "Escape"], monkeypatch, capsys)
    assert "needs a DivMorph student" in capsys.readouterr().err

    out = run_example(*EXAMPLE_RUNS[3], monkeypatch, capsys)
    assert float(re.search(r"max \|ONNX - student\| over 20 steps (\S+)", out).group(1)) <= 1e-5
    assert (tmp_path / "exported" / "actor.onnx").is_file() and (tmp_path / "exported" / "actor.pt").is_file()

    # Every README and docs Python block runs on its own in a fresh interpreter, as a reader pasting
    # only that block would run it (the ONNX and TorchScript ones run the actor exported above). The
    # blocks that load a shipped model run in the results suite (test_the_shipped_model_blocks_run).
    blocks = code_blocks("python")
    assert len(blocks) >= 5
    for index, code in enumerate(blocks):
        if '"results/' in code:
            continue
        done = subprocess.run(
            [sys.executable, "-c", "import torch; torch.set_num_threads(1)\n" + code],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, f"python block {index} (README, then docs/) fails on its own:\n{code}\n{done.stderr[-2000:]}"
    # ... and the quick start's numbers, checked in this process.
    namespace: dict = {"__name__": "__readme__"}
    quick_start = None
    for index, code in enumerate(blocks):
        if "zoo_hyperparams(" in code or "OnnxActor(" in code:
            exec(compile(code, f"README.md python block {index}", "exec"), namespace)  # noqa: S102
        if "zoo_hyperparams(" in code:
            quick_start = namespace["model"]
    # the quick-start PPO runs with the zoo's rollout size, not SB3's default 2048 steps x 10 epochs of 64
    assert quick_start is not None and quick_start.num_timesteps == 2048
    assert quick_start.n_steps == 512 and quick_start.batch_size == 512 and quick_start.n_epochs == 4
    assert np.isfinite(namespace["reward"]) and namespace["means"].shape == (1, 24)  # the exported actors ran


@pytest.mark.shipped_results
def test_the_shipped_model_blocks_run(tmp_path):
    """The README and docs blocks that load a shipped model run from the repository's root, as a
    reader of the README would, with the official robots fetched into a cache of this test's own."""
    blocks = [code for code in code_blocks("python") if '"results/' in code]
    assert blocks, "the README shows a shipped model"
    if not (OFFICIAL_TRAIN / "xml").is_dir():
        pytest.skip(f"needs the official robots, not found at {OFFICIAL_TRAIN}")
    from unimal_envs.morphology.official import fetch

    fetch(OFFICIAL_TRAIN, ["train"], cache=tmp_path / "unimal-data")
    env = {**os.environ, "UNIMAL_DATA": str(tmp_path / "unimal-data")}
    for code in blocks:
        done = subprocess.run(
            [sys.executable, "-c", "import torch; torch.set_num_threads(1)\n" + code],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert done.returncode == 0, f"a shipped-model block fails on its own:\n{code}\n{done.stderr[-2000:]}"
        if "evaluate(" in code:  # the shipped teacher walks on the robots the block names, in that order
            returns = [float(x) for x in re.findall(r"return (\d+)", done.stdout)]
            assert returns and min(returns) >= 100, done.stdout
            asked = re.findall(r'"([a-z]+-\d{4}[-\d]*)"', code)
            assert re.findall(r"^(\S+): return", done.stdout, flags=re.M) == asked, done.stdout


def _shell_commands() -> list[list[str]]:
    commands = []
    for block in code_blocks("bash"):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split("  #")[0].split(" # ")[0].strip()
            if line and not line.startswith("#"):
                commands.append(shlex.split(line.replace("[", "").replace("]", "")))
    return commands


def test_every_command_in_the_readme_exists(capsys):
    commands = _shell_commands()
    makefile = (REPO / "Makefile").read_text()
    seen = set()
    for words in commands:
        if words[0] == "divmorph":
            with pytest.raises(SystemExit) as exit_:
                cli([words[1], "--help"])
            assert exit_.value.code == 0, words
            seen.add("divmorph " + words[1])
        elif words[0] == "make":
            assert re.search(rf"^{words[1]}:", makefile, flags=re.M), words
            seen.add("make")
        elif words[:2] == ["python", "-m"]:
            assert importlib.util.find_spec(words[2]) is not None, words
            seen.add("python -m")
        elif words[0] == "python":
            assert (REPO / words[1]).is_file(), words
            seen.add("python script")
    capsys.readouterr()
    # the check reads the blocks it is meant to (a parsing slip would make it pass vacuously)
    assert {"make", "python -m", "python script", "divmorph pipeline", "divmorph record", "divmorph export"} <= seen


def test_the_project_is_licensed_citable_and_names_its_sources():
    import yaml

    licence = (REPO / "LICENSE").read_text()
    assert licence.startswith("MIT License") and 'license = "MIT"' in (REPO / "pyproject.toml").read_text()
    citation = yaml.safe_load((REPO / "CITATION.cff").read_text())
    assert citation["cff-version"] == "1.2.0" and citation["license"] == "MIT" and citation["authors"]
    assert citation["preferred-citation"]["title"] == "Knowledge Diversion for Efficient Morphology Control and Policy Transfer"
    assert "## [Unreleased]" in (REPO / "CHANGELOG.md").read_text()
    references = README.split("## Citing, licence and references")[1]
    for source in (
        "DivMorph",
        "KIND",
        "MetaMorph",
        "UNIMAL",
        "ModuMorph",
        "HyperDistill",
        "GRL",
        "DAgger",
        "PPO",
        "MuJoCo Warp",
        "Gymnasium",
        "Stable-Baselines3",
    ):
        assert source in references, source


@pytest.mark.shipped_results
def test_the_zero_shot_page_quotes_its_results_file():
    """Each model's "training -> held-out" mean in the zero-shot claim's table is the one
    ``results/cpu100/zero-shot.md`` (written by ``results/cpu100/zero_shot.py``) holds for that task and model."""
    results = (REPO / "results" / "cpu100" / "zero-shot.md").read_text()
    page = (REPO / "docs" / "claims" / "zero-shot.md").read_text()
    block = page.split("| task | teacher")[1].split("\n\n")[0]
    columns = ["teacher (MetaMorph)", "DivMorph student", "dense MetaMorph⚗ student", "HyperDistill"]
    checked = 0
    for line in block.splitlines()[2:]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        task = cells[0]
        for model, cell in zip(columns, cells[1:5]):
            train, held_out = re.match(r"(-?\d+) -> (-?\d+)", cell).groups()
            row = next(r for r in results.splitlines() if r.startswith(f"| {task} | {model} |"))
            quoted = [c.strip().split(" ")[0] for c in row.strip("|").split("|")[2:4]]
            assert quoted == [train, held_out], (task, model, cell, row)
            checked += 1
    assert checked == 20


#: a figure with its interval, as the claims tables print them: ``573 [446, 709]``, ``+0.26 [+0.04, +0.54]``, ``91% [77, 106]``
_FIGURE = re.compile(r"[-+]?[\d,.]+%? \[[-+]?[\d,.]+%?, [-+]?[\d,.]+%?\]")


@pytest.mark.parametrize("table", ["README.md", "docs/claims/index.md"])
def test_every_headline_figure_is_the_one_on_its_claim_page(table):
    """Each figure with an interval in a claims table (README's, the claims index) is written, digit for
    digit, on the claim page its row links to: one number per claim (break: change 573 [446, 709] to
    573 [448, 708] in the README -> fails)."""
    text = (REPO / table).read_text()
    rows = [line for line in text.splitlines() if line.startswith("|")]
    checked = 0
    for row in rows:
        link = re.search(r"\]\((?:docs/claims/)?(\w+)\.md\)", row)
        if link is None:
            continue
        page = " ".join((REPO / "docs" / "claims" / f"{link.group(1)}.md").read_text().split())  # a figure may wrap
        for figure in _FIGURE.findall(row):
            assert figure in page, f"{table}: {figure!r} is not on docs/claims/{link.group(1)}.md"
            checked += 1
    assert checked >= 4, checked
