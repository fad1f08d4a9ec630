"""The transfer race's driver (``results/transfer-race/race.py``): every job runs once, in the rule's order, and a
start waits for its arm's first run."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def load_race(monkeypatch):
    spec = importlib.util.spec_from_file_location("transfer_race", ROOT / "results" / "transfer-race" / "race.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "transfer_race", module)  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def race(monkeypatch, tmp_path):
    module = load_race(monkeypatch)
    log = tmp_path / "log.txt"

    def fake_command(job, setting, runs):
        """A job that leaves what the real one leaves: a run's source.json and done.json, or the task's baseline.json."""
        if job.seed is None:
            target = runs / job.task / "baseline.json"
            code = f"import json, pathlib; p = pathlib.Path({str(target)!r}); p.write_text(json.dumps({{{job.arm!r}: {{}}}}))"
        else:
            folder = module.run_folder(runs, job, job.seed)
            code = f"import pathlib; f = pathlib.Path({str(folder)!r}); f.mkdir(parents=True); (f / 'source.json').write_text('{{}}'); (f / 'done.json').write_text('{{}}')"
        return [sys.executable, "-c", f"{code}; open({str(log)!r}, 'a').write({job.name!r} + '\\n')"]

    def fake_keep(job, runs, keep):
        if job.seed is None:
            path = keep / job.task / "baseline.json"
            path.parent.mkdir(parents=True, exist_ok=True)
            old = json.loads(path.read_text()) if path.is_file() else {}
            path.write_text(json.dumps({**old, job.arm: {}}))
        else:
            folder = keep / job.task / "transfer" / job.task / job.arm / f"seed-{job.seed}"
            folder.mkdir(parents=True)
            (folder / "done.json").write_text("{}")

    monkeypatch.setattr(module, "command", fake_command)
    monkeypatch.setattr(module, "keep_finished", fake_keep)
    return module, log


def test_a_worker_runs_every_job_once_in_the_rules_order(race, tmp_path):
    module, log = race
    runs, keep = tmp_path / "runs", tmp_path / "keep"
    (runs / "claims").mkdir(parents=True)
    (runs / "claims" / "Escape-scratch-seed-2").mkdir()  # held by another worker
    for task in module.TASKS:
        (runs / task).mkdir()
    module.work(module.SETTINGS["S2"], runs, keep, poll=0.01)
    order = log.read_text().split()
    expected = [job.name for job in module.jobs() if job.name != "Escape-scratch-seed-2"]
    assert order == expected and len(set(order)) == len(order)
    assert order[: len(module.TASKS) * len(module.ARMS)] == [f"{t}-{a}-seed-0" for t in module.TASKS for a in module.ARMS]
    module.work(module.SETTINGS["S2"], runs, keep, poll=0.01)  # everything done or held: nothing runs again
    assert log.read_text().split() == order


def test_a_start_waits_for_its_arms_first_run(race, tmp_path):
    module, _ = race
    start = module.Job("Escape", "closest", None)
    assert not module.ready(start, tmp_path)
    folder = module.run_folder(tmp_path, start, module.SEEDS[0])
    folder.mkdir(parents=True)
    (folder / "source.json").write_text("{}")
    assert module.ready(start, tmp_path)


def test_every_settings_profile_keys_are_the_profiles(monkeypatch):
    import yaml

    from divmorph.pipeline.config import load_profile

    module = load_race(monkeypatch)
    for setting in module.SETTINGS.values():
        for sets in (setting.sets + module.EVAL, *module.TASKS.values()):
            overrides = {key: yaml.safe_load(value) for key, value in (item.split("=", 1) for item in sets)}
            load_profile("cpu100", overrides=overrides)  # a key or value the profile refuses raises ConfigError
