"""The fine-tuning study's report (``results/finetune-known-task/finetune_known_task.py --report``) on the runs a queue leaves behind."""

from __future__ import annotations

import importlib.util
import json
import os
import signal
from pathlib import Path

import pytest

import pandas as pd

SCRIPT = Path(__file__).resolve().parents[1] / "results" / "finetune-known-task" / "finetune_known_task.py"
#: a study's script of results/: the evidence's suite (`make test-results`), not the library's
pytestmark = pytest.mark.shipped_results


def load_study():
    spec = importlib.util.spec_from_file_location("finetune_known_task", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def finished_run(folder: Path) -> None:
    """A run cut off two minutes in (an empty ``logs/run-0``), resumed to the end in ``logs/run-1``."""
    folder.mkdir(parents=True)
    (folder / "done.json").write_text(json.dumps({"finished": "now"}))
    pd.DataFrame(
        {"split": "train", "timesteps": [0, 0, 100, 100], "robot": ["a", "b", "a", "b"], "return": [10.0, 20.0, 30.0, 40.0]}
    ).to_csv(folder / "eval.csv", index=False)
    (folder / "logs" / "run-0").mkdir(parents=True)
    (folder / "logs" / "run-0" / "progress.csv").write_text("")
    (folder / "logs" / "run-1").mkdir()
    pd.DataFrame({"rollout/ep_rew_mean": [5.0, 7.0], "train/explained_variance": [0.25, 0.75]}).to_csv(
        folder / "logs" / "run-1" / "progress.csv", index=False
    )


def test_the_report_of_a_resumed_run_reads_the_attempt_that_finished_it(tmp_path, capsys):
    # Broken once by reading only logs/run-0 again: pandas raises EmptyDataError on the cut-off attempt.
    study = load_study()
    finished_run(tmp_path / "transfer" / "PointNav" / "divmorph" / "seed-0")
    study.main(["--out", str(tmp_path), "--task", "PointNav", "--steps", "100", "--eval-every", "100", "--seeds", "0", "--report"])
    printed = capsys.readouterr().out
    assert "| DivMorph student | 1 | 15 [" in printed and "| +20 [" in printed  # the curve: 15 -> 35 over the two robots
    assert "| DivMorph student | 5 / 7 | 0.25 / 0.75 |" in printed  # the resumed attempt's training log, halves
    assert (tmp_path / "README.md").is_file()


class _RecordingModel:
    """Stands for a loaded student: remembers the instruction each evaluation is told."""

    def __init__(self):
        self.told = []

    def evaluate(self, robots, task, episodes, seed, max_episode_steps, instruction=None, **env_kwargs):
        self.told.append(instruction)
        return [{"robot": "a", "return": 1.0}, {"robot": "b", "return": 3.0}]


@pytest.mark.parametrize(
    "source, configured, expected",
    [
        ({"instruction": "Walk forward as fast as possible on flat ground."}, {}, "Walk forward as fast as possible on flat ground."),
        ({}, {"transfer.instructions.Escape": "Walk up a slope."}, "Walk up a slope."),
        ({}, {}, None),
    ],
    ids=["closest-task-gates", "configured-instruction", "own-instruction"],
)
def test_the_many_draw_start_is_measured_with_the_instruction_the_runs_are_told(tmp_path, monkeypatch, source, configured, expected):
    # Broken once by reading the instruction from source.json only: the configured one is then not told (None).
    import divmorph.pipeline.robots
    import divmorph.pretrained
    from divmorph.pipeline.config import load_profile

    study = load_study()
    model = _RecordingModel()
    monkeypatch.setattr(divmorph.pretrained, "load_pretrained", lambda path: model)
    monkeypatch.setattr(divmorph.pipeline.robots, "transfer_eval_robots", lambda profile, split: ["a", "b"])
    run = tmp_path / "transfer" / "Escape" / "divmorph" / "seed-0"
    run.mkdir(parents=True)
    (run / "source.json").write_text(json.dumps({"arm": "divmorph", "seed": 0, "source": "student", **source}))
    args = study.argparse.Namespace(out=tmp_path, arms=["divmorph"], task="Escape", seeds=[0], baseline_seeds=2)
    found = study.evaluate_baselines(args, load_profile("demo", overrides=configured))
    assert model.told == [expected, expected]
    assert found == {"divmorph": {"0": {"a": 1.0, "b": 3.0}, "1": {"a": 1.0, "b": 3.0}}}


def _fake_study(study, monkeypatch, tmp_path, run_calls):
    """The study on a made-up run folder: the model, robots and profile stand-ins; transfer_run records its calls."""
    import divmorph.pipeline.robots
    import divmorph.pretrained
    from divmorph.pipeline.config import load_profile

    monkeypatch.setattr(divmorph.pretrained, "load_pretrained", lambda path: _RecordingModel())
    monkeypatch.setattr(divmorph.pipeline.robots, "transfer_eval_robots", lambda profile, split: ["a", "b"])
    monkeypatch.setattr(study, "recorded_profile", lambda path, overrides: load_profile("demo"))
    monkeypatch.setattr(study, "branch", lambda *args, **kwargs: (tmp_path / "run.json").write_text("{}"))

    class Run:
        def run(self):
            run_calls.append(1)
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(study, "transfer_run", lambda *args, **kwargs: Run())
    seed = tmp_path / "transfer" / "Escape" / "divmorph" / "seed-0"
    seed.mkdir(parents=True)
    (seed / "source.json").write_text(json.dumps({"arm": "divmorph", "seed": 0, "source": "student"}))
    return ["--out", str(tmp_path), "--task", "Escape", "--arms", "divmorph", "--seeds", "0"]


def test_baseline_only_measures_the_starts_and_starts_no_run(tmp_path, monkeypatch):
    """``--baseline-seeds 2 --baseline-only`` (the ablation race's start jobs) writes baseline.json and neither
    trains nor reports (broken once by ignoring the flag: a run starts)."""
    study, calls, previous = load_study(), [], signal.getsignal(signal.SIGTERM)
    try:
        study.main([*_fake_study(study, monkeypatch, tmp_path, calls), "--baseline-seeds", "2", "--baseline-only"])
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert calls == [] and set(json.loads((tmp_path / "baseline.json").read_text())["divmorph"]) == {"0", "1"}


def test_sigterm_stops_a_run_as_ctrl_c_does(tmp_path, monkeypatch):
    """SIGTERM during a run reaches it as KeyboardInterrupt, on which a transfer run saves a checkpoint (a session's
    end or a `kill` then loses no training; broken once with SIGTERM ignored instead: no interrupt)."""
    study, calls, previous = load_study(), [], signal.getsignal(signal.SIGTERM)
    try:
        with pytest.raises(KeyboardInterrupt):
            study.main(_fake_study(study, monkeypatch, tmp_path, calls))
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert calls == [1]
