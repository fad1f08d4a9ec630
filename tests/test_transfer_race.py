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
            target = runs / job.folder / "baseline.json"
            code = f"import json, pathlib; p = pathlib.Path({str(target)!r}); p.parent.mkdir(exist_ok=True); p.write_text(json.dumps({{{job.arm!r}: {{}}}}))"
        else:
            folder = module.run_folder(runs, job, job.seed)
            code = f"import pathlib; f = pathlib.Path({str(folder)!r}); f.mkdir(parents=True); (f / 'source.json').write_text('{{}}'); (f / 'done.json').write_text('{{}}')"
        return [sys.executable, "-c", f"{code}; open({str(log)!r}, 'a').write({job.name!r} + '\\n')"]

    def fake_keep(job, runs, keep):
        if job.seed is None:
            path = keep / job.folder / "baseline.json"
            path.parent.mkdir(parents=True, exist_ok=True)
            old = json.loads(path.read_text()) if path.is_file() else {}
            path.write_text(json.dumps({**old, job.arm: {}}))
        else:
            folder = keep / job.folder / "transfer" / job.task / job.arm / f"seed-{job.seed}"
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
    module.work(module.SETTINGS["S2"], runs, keep, poll=0.01)
    order = log.read_text().split()
    expected = [job.name for job in module.jobs() if job.name != "Escape-scratch-seed-2"]
    assert order == expected and len(set(order)) == len(order)
    assert order[: len(module.TASKS) * len(module.ARMS)] == [f"{t}-{a}-seed-0" for t in module.TASKS for a in module.ARMS]
    assert "Escape-lowstart-closest-seed-0" in order and "Escape-lr0-divmorph-seed-0" in order
    low_start = [order.index(f"Escape-lowstart-closest-seed-{seed}") for seed in module.SEEDS]
    assert max(low_start) < order.index("Escape-divmorph-start")  # the control that alone turns the verdict, early
    kept = {path.relative_to(keep).parts[0] for path in keep.glob("*/transfer/*/*/seed-*/done.json")}
    assert kept == {*module.TASKS, "Escape-lowstart", "Escape-lr0"}  # the freed student races in Escape's own folder
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


def test_a_new_machine_gets_the_finished_first_runs_sources_back_and_no_progress(race, tmp_path):
    """On a new machine RUNS lacks the finished seed-0 runs the starts read: restore_runs puts each packed run's
    source.json back in a task folder branched from the source, writes no done.json, and the start can run
    (break: skip the copy -> the start waits for ever and this fails)."""
    from divmorph.pipeline.retired import RECORD_FORMAT

    module, _ = race
    spec = importlib.util.spec_from_file_location("restore_runs", ROOT / "results" / "transfer-race" / "restore_runs.py")
    assert spec is not None and spec.loader is not None
    restore_runs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(restore_runs)
    runs, keep = tmp_path / "runs", tmp_path / "keep"
    (runs / "source" / "teachers" / "FT").mkdir(parents=True)
    (runs / "source" / "teachers" / "FT" / "done.json").write_text("{}")
    (runs / "source" / "run.json").write_text(json.dumps({"format": RECORD_FORMAT, "history": []}))
    packed = keep / "Escape" / "transfer" / "Escape" / "closest" / "seed-0"
    packed.mkdir(parents=True)
    (packed / "source.json").write_text(json.dumps({"arm": "closest", "seed": 0, "source": "teachers/FT"}))
    (packed / "done.json").write_text("{}")
    start = module.Job("Escape", "closest", None)
    assert not module.ready(start, runs)
    assert restore_runs.restore(runs, keep) == [runs / packed.relative_to(keep) / "source.json"]
    assert module.ready(start, runs)
    folder = module.run_folder(runs, start, 0)
    assert json.loads((folder / "source.json").read_text())["source"] == "teachers/FT"
    assert (runs / "Escape" / "teachers" / "FT" / "done.json").is_file()  # the model the start evaluates
    assert not (folder / "done.json").exists() and module.done(start, runs, keep) is False
    assert restore_runs.restore(runs, keep) == []  # a folder RUNS already has is left alone


def test_every_settings_profile_keys_are_the_profiles(monkeypatch):
    import yaml

    from divmorph.pipeline.config import load_profile

    module = load_race(monkeypatch)
    for setting in module.SETTINGS.values():
        for sets in (setting.sets + module.EVAL, *module.TASKS.values(), *module.SETS.values()):
            overrides = {key: yaml.safe_load(value) for key, value in (item.split("=", 1) for item in sets)}
            load_profile("cpu100", overrides=overrides)  # a key or value the profile refuses raises ConfigError


def test_the_low_start_diagnosis_changes_one_knob_of_the_low_start_per_run_folder(monkeypatch, tmp_path):
    """Every variant runs MetaMorph-> told Incline's instruction, with the low start's settings and one more, in a run
    folder of its own, seeds 0-2 of every variant in turn."""
    module = load_race(monkeypatch)
    found = module.jobs("lowstart-diagnosis")
    assert [job.seed for job in found] == [seed for seed in module.SEEDS for _ in module.DIAGNOSIS]
    low_start = module.CONTROLS["lowstart"][0]
    folders = set()
    for job in found:
        line = module.command(job, module.SETTINGS["S2"], tmp_path)
        sets = [line[i + 1] for i, item in enumerate(line) if item == "--set"]
        extra = [item for item in sets if item not in (*module.SETTINGS["S2"].sets, *module.EVAL, *low_start)]
        assert job.arm == "closest" and all(item in sets for item in low_start) and len(extra) == 1, sets
        folders.add(job.folder)
    assert folders == {f"Escape-{name}" for name in module.DIAGNOSIS}


def load_reader(monkeypatch):
    spec = importlib.util.spec_from_file_location("transfer_race_read", ROOT / "results" / "transfer-race" / "read.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "transfer_race_read", module)
    spec.loader.exec_module(module)
    return module


def made_up_race(
    keep: Path, task: str, curves: dict[str, object], seeds: int = 3, noise: float = 2.0, folder: str | None = None, held_out: float = 0.0
) -> None:
    """Kept runs of ``task`` (in its own run folder, or ``folder``: a control's) whose 8 training robots follow
    ``curves[arm](step fraction)`` plus noise, the held-out robots the same shifted by ``held_out``; the fine-tuned
    arms' many-draw starts at their curves' step 0."""
    import numpy as np
    import pandas as pd

    rng = np.random.default_rng(1)
    folder = folder or task
    steps = [i * 100_352 for i in range(7)]
    starts = {}
    for arm, curve in curves.items():
        for seed in range(seeds):
            run = keep / folder / "transfer" / task / arm / f"seed-{seed}"
            run.mkdir(parents=True)
            rows = [
                dict(
                    timesteps=s,
                    split=split,
                    robot=f"r{r}",
                    episode=0,
                    **{"return": curve(s / steps[-1]) + rng.normal(0, noise) + (held_out if split == "novel" else 0.0)},
                    length=1,
                )
                for s in steps
                for split in ("train", "novel")
                for r in range(8)
            ]
            pd.DataFrame(rows).to_csv(run / "eval.csv.gz", index=False)
            (run / "done.json").write_text("{}")
        if arm not in ("scratch", "divmorph-finetuned"):
            starts[arm] = {str(e): {f"r{r}": curve(0.0) + rng.normal(0, noise) for r in range(8)} for e in range(5)}
    (keep / folder / "baseline.json").write_text(json.dumps(starts))


def test_the_race_reading_holds_fails_or_has_no_reference_as_the_curves_say(monkeypatch, tmp_path):
    """Made-up races: DivMorph at MetaMorph->'s final return by a seventh of the budget (holds); DivMorph flat below
    it (does not hold); MetaMorph-> flat (no reference). Broken once: the ratio turned upside down -> the first task
    reads ~1/7 and fails."""
    reader = load_reader(monkeypatch)
    fast = {
        "closest": lambda f: 100 + 100 * f,
        "divmorph": lambda f: 100 + 700 * min(f, 1 / 6),
        "scratch": lambda f: 200 * f,
        "distilled": lambda f: 100 + 50 * f,
    }
    made_up_race(tmp_path, "Escape", fast)
    flat = {**fast, "divmorph": lambda f: 90 + 0 * f}
    made_up_race(tmp_path, "Exploration", flat)
    no_reference = {**fast, "closest": lambda f: 150 + 0 * f}
    made_up_race(tmp_path, "PointNav", no_reference)
    found = {task: reader.read_task(tmp_path, task) for task in reader.TASKS}
    assert found["Escape"]["readings"]["direct"][3] == "holds"
    assert found["Escape"]["readings"]["direct"][0] >= 5
    assert found["Exploration"]["readings"]["direct"][3] == "does not hold"
    assert found["PointNav"]["readings"]["direct"][3].startswith("no reference")
    text = reader.main(["--keep", str(tmp_path)])
    assert "not decidable at this scale" in text.split("Against direct fine-tuning")[1].splitlines()[0]
    assert (tmp_path / "curves.png").stat().st_size > 0


def test_held_out_robots_are_reported_beside_and_decide_nothing(monkeypatch, tmp_path):
    """The same made-up race with its held-out robots 1000 higher: the same ratios and verdicts, and a held-out table
    whose starts carry the shift. Broken once: the reading's curves taken from the held-out split -> MetaMorph->'s
    level moves with it and the table's starts do not differ, fails."""
    reader = load_reader(monkeypatch)
    curves = {"closest": lambda f: 100 + 100 * f, "divmorph": lambda f: 100 + 700 * min(f, 1 / 6), "scratch": lambda f: 200 * f}
    made_up_race(tmp_path / "plain", "Escape", curves)
    made_up_race(tmp_path / "shifted", "Escape", curves, held_out=1000.0)
    plain, shifted = (reader.read_task(tmp_path / name, "Escape") for name in ("plain", "shifted"))
    assert plain["readings"] == shifted["readings"]
    text = reader.main(["--keep", str(tmp_path / "shifted")])
    held_out = text.split("Held-out robots")[1].split("Controls")[0]
    row = next(line for line in held_out.splitlines() if "MetaMorph→" in line)
    assert 1050 < float(row.split("|")[4]) < 1150  # MetaMorph->'s own step 0 on the held-out robots: 100 + 1000


def test_steps_to_a_level_is_the_first_crossing_linear_between_evaluations(monkeypatch):
    import numpy as np

    reader = load_reader(monkeypatch)
    steps = np.array([0.0, 100.0, 200.0])
    assert reader.steps_to(steps, np.array([0.0, 10.0, 20.0]), 15.0) == 150.0
    assert reader.steps_to(steps, np.array([16.0, 10.0, 20.0]), 15.0) == 0.0
    assert reader.steps_to(steps, np.array([0.0, 10.0, 12.0]), 15.0) == float("inf")


def test_the_controls_are_read_first_and_a_failed_one_names_our_setup(monkeypatch, tmp_path):
    """Made-up controls on Escape: the fine-tuned arms flat at learning rate 0 (hold still), MetaMorph-> from the low
    start rising (recovers), the freed student above the fixed gates -- no failure, the verdicts stand. Then a start
    that moves at rate 0, and a low start that stays flat where scratch climbs: each fails, and both verdicts become
    "not decided: our setup" naming it (broken once: the failures not carried into the verdict -> the second
    reading still says "not decidable at this scale")."""
    reader = load_reader(monkeypatch)
    escape = {
        "closest": lambda f: 100 + 100 * f,
        "divmorph": lambda f: 100 + 50 * f,
        "scratch": lambda f: 200 * f,
        "distilled": lambda f: 100 + 50 * f,
        "divmorph-finetuned": lambda f: 100 + 150 * f,
    }
    made_up_race(tmp_path, "Escape", escape)
    made_up_race(tmp_path, "Escape", {arm: (lambda f: 100 + 0 * f) for arm in ("divmorph", "closest", "distilled")}, folder="Escape-lr0")
    made_up_race(tmp_path, "Escape", {"closest": lambda f: 1 + 80 * f}, folder="Escape-lowstart")
    rows = {(row["control"], row["arm"]): row for row in reader.read_controls(tmp_path)}
    assert len(rows) == 5 and not any(row["failed"] for row in rows.values())
    assert all(row["reading"] == "holds still" for (control, _), row in rows.items() if control == "learning rate 0")
    assert next(row for (c, _), row in rows.items() if c == "the dense low start")["reading"] == "recovers from its low start"
    assert "freed gains more" in next(row for (c, _), row in rows.items() if c == "the selection freed")["reading"]
    text = reader.main(["--keep", str(tmp_path)])
    assert "our setup" not in text.split("Against direct")[1]

    made_up_race(tmp_path / "moving", "Escape", escape)
    made_up_race(tmp_path / "moving", "Escape", {"divmorph": lambda f: 100 + 60 * f}, folder="Escape-lr0")
    made_up_race(tmp_path / "moving", "Escape", {"closest": lambda f: 1 + 0 * f}, folder="Escape-lowstart")
    failed = [row["control"] for row in reader.read_controls(tmp_path / "moving") if row["failed"]]
    assert failed == ["learning rate 0", "the dense low start"]
    text = reader.main(["--keep", str(tmp_path / "moving")])
    assert "not decided: our setup (failed: learning rate 0, the dense low start)" in text.split("Against scratch")[1]


def test_the_low_start_diagnosis_names_the_first_variant_that_recovers(monkeypatch, tmp_path):
    """Made-up variants: statistics learning (L) and scratch's rate (S) climb, the critic first (W) stays flat -> L,
    the first in the rule's order that recovers, is named; with every variant flat none is. Broken once: the order
    ignored (the last recovering variant named) -> names S, fails."""
    reader = load_reader(monkeypatch)
    climbs, flat = (lambda f: 1 + 2 * f), (lambda f: 1 + 0 * f)
    for name, curve in (("lowstart-W", flat), ("lowstart-L", climbs), ("lowstart-S", climbs)):
        made_up_race(tmp_path / "some", "Escape", {"closest": curve}, noise=0.2, folder=f"Escape-{name}")
        made_up_race(tmp_path / "none", "Escape", {"closest": flat}, noise=0.2, folder=f"Escape-{name}")
    rows, block = reader.read_diagnosis(tmp_path / "some")
    assert [row["reading"] for row in rows] == ["does not recover", "recovers", "recovers"]
    assert block == reader.DIAGNOSIS["lowstart-L"]
    assert reader.read_diagnosis(tmp_path / "none")[1] is None


def test_a_variant_is_read_against_the_low_starts_step_0_not_its_own(monkeypatch, tmp_path):
    """Made-up runs: the low start and a variant both sit at 1, but the variant's first evaluation reads 0 (statistics
    learning changes a model during its first rollout) -> it does not recover against the low start's step 0. Broken
    once: each variant read against its own first evaluation -> "recovers", fails."""
    reader = load_reader(monkeypatch)
    flat, dips_first = (lambda f: 1 + 0 * f), (lambda f: 0.0 if f == 0 else 1.0)
    made_up_race(tmp_path, "Escape", {"closest": flat}, noise=0.05, folder="Escape-lowstart")
    (tmp_path / "Escape-lowstart" / "baseline.json").unlink()  # its many-draw start not measured yet
    made_up_race(tmp_path, "Escape", {"closest": dips_first}, noise=0.05, folder="Escape-lowstart-L")
    rows, block = reader.read_diagnosis(tmp_path)
    assert [row["reading"] for row in rows] == ["does not recover"] and block is None
    assert abs(rows[0]["gain"][0] - 1.0) < 0.1  # the start: the low start's step 0


def test_a_complete_diagnosis_where_nothing_recovers_reads_not_decidable_at_this_scale(monkeypatch, tmp_path):
    """The low start fails (flat where scratch climbs) and the rate-0 control holds. With every variant flat on 2 seeds
    the verdict stays "not decided: our setup"; on its 3 seeds it becomes lowstart-rule.md's last branch, "not
    decidable at this scale", naming the low start; a variant that recovers names the block instead. Broken once:
    the variants' seeds not counted -> 2 seeds already read "not decidable", fails."""
    reader = load_reader(monkeypatch)
    escape = {arm: (lambda f: 100 + 0 * f) for arm in ("divmorph", "closest", "distilled")} | {"scratch": lambda f: 200 * f}
    flat, climbs = (lambda f: 1 + 0 * f), (lambda f: 1 + 2 * f)
    for case, seeds, l_curve in (("two", 2, flat), ("three", 3, flat), ("block", 3, climbs)):
        keep = tmp_path / case
        made_up_race(keep, "Escape", escape)
        made_up_race(keep, "Escape", {arm: (lambda f: 100 + 0 * f) for arm in ("divmorph", "closest", "distilled")}, folder="Escape-lr0")
        made_up_race(keep, "Escape", {"closest": flat}, noise=0.2, folder="Escape-lowstart")
        for name in reader.DIAGNOSIS:
            curve = l_curve if name == "lowstart-L" else flat
            made_up_race(keep, "Escape", {"closest": curve}, seeds=seeds, noise=0.2, folder=f"Escape-{name}")
    verdicts = {case: reader.main(["--keep", str(tmp_path / case)]).split("Against direct")[1] for case in ("two", "three", "block")}
    assert "not decided: our setup (failed: the dense low start)" in verdicts["two"]
    assert "not decidable at this scale (the control that stops it: the dense low start)" in verdicts["three"]
    assert "not decided: our setup" in verdicts["block"] and "not decidable" not in verdicts["block"]
