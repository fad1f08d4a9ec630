"""The ablation race's tables and reading (``results/transfer-ablations/collect.py``, ``read.py``) on a made-up race."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

STUDY = Path(__file__).resolve().parents[1] / "results" / "transfer-ablations"
#: a study's scripts of results/: the evidence's suite (`make test-results`), not the library's
pytestmark = pytest.mark.shipped_results
ROBOTS = [f"robot-{i}" for i in range(12)]


def load(name: str):
    spec = importlib.util.spec_from_file_location(f"transfer_ablations_{name}", STUDY / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def make_race(race: Path, student: str, task: str, climb: float, kl: float) -> None:
    """Three finished seeds of a student on a task that start at 1.0 (per robot) and end ``climb`` higher, with
    updates of approximate KL ``kl``, and its many-draw start in ``baseline.json``."""
    rng = np.random.default_rng(len(student))
    branch = race / f"{task}-{student}"
    for seed in range(3):
        run = branch / "transfer" / task / student / f"seed-{seed}"
        (run / "logs" / "run-1").mkdir(parents=True)
        rows = [
            (steps, split, robot, episode, 1.0 + climb * steps / 600_000 + rng.normal(0, 0.1))
            for steps in (0, 300_000, 600_000)
            for split in ("train", "novel")
            for robot in ROBOTS
            for episode in range(2)
        ]
        pd.DataFrame(rows, columns=["timesteps", "split", "robot", "episode", "return"]).to_csv(run / "eval.csv", index=False)
        updates = np.arange(2048, 600_001, 2048)
        log = pd.DataFrame(
            {
                "time/total_timesteps": updates,
                "rollout/ep_rew_mean": np.linspace(1, 1 + climb, len(updates)),
                "train/approx_kl": kl,
                "train/clip_fraction": 0.1,
                "train/explained_variance": 0.8,
            }
        )
        log.to_csv(run / "logs" / "run-1" / "progress.csv", index=False)
        # resumed from a checkpoint 20 updates back: those updates are logged again, by the attempt that counts
        (run / "logs" / "run-2").mkdir()
        log.iloc[-20:].assign(**{"train/approx_kl": kl * 1.5}).to_csv(run / "logs" / "run-2" / "progress.csv", index=False)
        (run / "done.json").write_text("{}")
    starts = {str(s): {robot: 1.0 + rng.normal(0, 0.05) for robot in ROBOTS} for s in range(5)}
    (branch / "baseline.json").write_text(json.dumps({student: starts}))


def test_the_reading_names_a_part_only_where_an_ablated_student_learns_escape_at_the_dense_kl(tmp_path):
    """Made-up Escape runs: the decoder ablation climbs by 2 at MetaMorph⚗'s KL per update, the Transformer
    ablation stays flat at it, the orthogonality ablation climbs by 2 at a KL 5x too large (each seed resumed once:
    the updates after its checkpoint are counted once, by the last attempt). The rule names the
    decoder, says the Transformer's does not free the block, gives the third no reading; the table goes into
    the README between its markers, and the figure is written. The DivMorph student, raced alike, stays flat: the
    block."""
    race = tmp_path / "race"
    make_race(race, "divmorph", "Escape", climb=0.0, kl=0.012)
    make_race(race, "no-kdiv-decoder", "Escape", climb=2.0, kl=0.012)
    make_race(race, "no-kdiv-transformer", "Escape", climb=0.0, kl=0.012)
    make_race(race, "no-orthogonality", "Escape", climb=2.0, kl=0.06)
    out = tmp_path / "study"
    out.mkdir()
    load("collect").collect(race, out)
    starts = pd.read_csv(out / "starts.csv")
    assert (
        set(starts.student) == {"divmorph", "no-kdiv-decoder", "no-kdiv-transformer", "no-orthogonality"} and (starts.eval_seeds == 5).all()
    )
    training = pd.read_csv(out / "training.csv.gz")
    assert not training.duplicated(["student", "seed", "timesteps"]).any() and len(training) == 4 * 3 * 292
    assert (training[training.timesteps > 292 * 2048 - 20 * 2048].approx_kl > 0.0121).all()  # the resumed attempt's
    (out / "README.md").write_text(
        "before\n<!-- transfer-ablations-reading -->\nSTALE TABLE\n<!-- /transfer-ablations-reading -->\nafter\n"
    )

    table = load("read").main(out)
    rows = {line.split(" | ")[1]: line for line in table.splitlines()[2:] if line.startswith("| Escape")}
    decoder = rows["no diversion in the decoder"]
    assert "| learns |" in decoder and "names the decoder's fixed selection" in decoder
    assert "neither, within noise" in rows["no diversion in the Transformer"]
    assert "does not free it" in rows["no diversion in the Transformer"]
    assert "no reading: KL per update off" in rows["no orthogonality (free square factors)"]
    assert "| neither, within noise |" in rows["DivMorph (comparator)"] and rows["DivMorph (comparator)"].endswith("| the block |")
    # against the comparator, paired by robot: the decoder ablation gains ~2 more, the Transformer's no more
    against = {
        student: [float(x) for x in line.split(" | ")[7].replace("[", "").replace("]", "").replace(",", "").split()]
        for student, line in rows.items()
        if "comparator" not in student
    }
    assert 1.5 < against["no diversion in the decoder"][0] and against["no diversion in the decoder"][1] > 0
    assert against["no diversion in the Transformer"][1] <= 0 <= against["no diversion in the Transformer"][2]
    assert all("not run" in line for line in table.splitlines() if line.startswith("| PointNav"))
    assert table.endswith("By the rule: the decoder's fixed selection holds the fixed-gate block.")
    readme = (out / "README.md").read_text()
    assert readme.startswith("before\n") and readme.endswith("after\n") and "STALE TABLE" not in readme and table in readme
    assert (out / "ablations.png").stat().st_size > 10_000


def test_no_part_is_named_where_the_divmorph_student_itself_learns_escape(tmp_path):
    """Made-up Escape runs where the DivMorph student, raced alike, climbs by 2 at the dense KL: there is no block for
    an ablation to free, so the decoder ablation's climb names nothing, and the conclusion says why."""
    race = tmp_path / "race"
    for student, climb in [("divmorph", 2.0), ("no-kdiv-decoder", 2.0), ("no-kdiv-transformer", 0.0), ("no-orthogonality", 0.0)]:
        make_race(race, student, "Escape", climb=climb, kl=0.012)
    out = tmp_path / "study"
    out.mkdir()
    load("collect").collect(race, out)
    table = load("read").main(out)
    assert table.endswith("By the rule: no part named; the DivMorph student itself: DivMorph learns: no block to name.")


def test_two_named_parts_are_read_as_holding_the_block_together():
    """Where two ablated students each learn and the comparator does not, each part is needed for the block (without
    either, the student learns): the conclusion says they hold it together, not that either alone does."""
    read = load("read")
    verdicts = {
        "divmorph": "the block",
        "no-kdiv-transformer": "names the Transformer's fixed selection",
        "no-kdiv-decoder": "does not free it",
        "no-orthogonality": "names the Cayley square factors",
    }
    assert read.conclusion(verdicts) == (
        "By the rule: the Transformer's fixed selection and the Cayley square factors hold the fixed-gate block together "
        "(without any one of them the student learns)."
    )


def test_a_race_packed_as_it_is_kept_reads_as_the_race_itself(tmp_path):
    """The race's runs kept as ``tools/pack_transfer_runs.py`` packs them (evaluations with returns to 0.01, the
    updates in a table beside the race folders; no logs) give the reading the full runs give: the same words, and
    each number within one unit of its last printed digit (Escape's returns print to 0.01); a kept run whose updates are missing from its table is an error that names it, not a row without KL."""
    race = tmp_path / "race"
    for student, climb in [("divmorph", 0.0), ("no-kdiv-decoder", 2.0), ("no-kdiv-transformer", 0.0), ("no-orthogonality", 0.0)]:
        make_race(race, student, "Escape", climb=climb, kl=0.012)
    kept = tmp_path / "kept"
    pack = importlib.util.spec_from_file_location("pack_transfer_runs", STUDY.parents[1] / "tools" / "pack_transfer_runs.py")
    packer = importlib.util.module_from_spec(pack)
    pack.loader.exec_module(packer)
    for branch in sorted(race.iterdir()):
        packer.pack(kept, branch, branch.name)
        (kept / branch.name / "baseline.json").write_text((branch / "baseline.json").read_text())
    assert not list(kept.rglob("progress.csv*"))
    tables = {}
    for name, folder in [("full", race), ("kept", kept)]:
        out = tmp_path / f"read-{name}"
        out.mkdir()
        load("collect").collect(folder, out)
        tables[name] = load("read").main(out)
    number = r"[+-]?\d+\.\d+"
    assert re.sub(number, "#", tables["kept"]) == re.sub(number, "#", tables["full"])
    kept_numbers, full_numbers = (np.array(re.findall(number, tables[name]), float) for name in ["kept", "full"])
    assert np.abs(kept_numbers - full_numbers).max() <= 0.0101
    assert "names the decoder's fixed selection" in tables["kept"]

    table = kept / "training-Escape-divmorph.csv.gz"
    rows = pd.read_csv(table)
    rows[rows.seed != 1].to_csv(table, index=False)
    with pytest.raises(SystemExit, match="seed-1: finished, but neither its logs nor"):
        load("collect").collect(kept, tmp_path / "read-kept")


KEPT_RACE = "results/transfer-ablations/kept/race"


@pytest.fixture(scope="module")
def kept_race(archived_study) -> Path:
    """The race's kept runs and starts: in the tree while it runs, afterwards restored out of the archive."""
    if (STUDY / "kept" / "race").is_dir():
        return STUDY / "kept" / "race"
    return archived_study(KEPT_RACE)


def test_every_kept_run_reads_with_its_updates_and_at_the_race_terms(kept_race, tmp_path):
    """The runs the race has kept (``kept/race``) collect whole: each with its evaluations at the race's points (0
    and every 200,704 steps to 602,112) on 20 training and 20 held-out robots, and its ~294 updates."""
    if not any(kept_race.glob("*/transfer/*/*/seed-*/done.json")):
        pytest.skip("no race run kept yet")
    load("collect").collect(kept_race, tmp_path)
    curves, training = pd.read_csv(tmp_path / "curves.csv.gz"), pd.read_csv(tmp_path / "training.csv.gz")
    for (task, student, seed), run in curves.groupby(["task", "student", "seed"]):
        assert sorted(run.timesteps.unique()) == [0, 200_704, 401_408, 602_112], (task, student, seed)
        assert run.groupby("split").robot.nunique().to_dict() == {"novel": 20, "train": 20}
        updates = training[(training.task == task) & (training.student == student) & (training.seed == seed)]
        assert len(updates) >= 290 and updates.approx_kl.notna().all()


def test_the_archived_tables_and_the_reading_are_what_the_kept_race_collects_to(kept_race, tmp_path, archived_study):
    """The race's tables (``curves.csv.gz``, ``training.csv.gz``, ``starts.csv``; the first two archived with its
    raw runs) hold all 24 runs and 8 starts, are what its kept runs collect to, and ``reading.md`` is what
    ``read.py`` reads from them."""
    load("collect").collect(kept_race, tmp_path)
    archived = archived_study("results/transfer-ablations")
    for name in ["curves.csv.gz", "training.csv.gz", "starts.csv"]:
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / name), pd.read_csv(archived / name), obj=name)
    curves, starts = pd.read_csv(archived / "curves.csv.gz"), pd.read_csv(archived / "starts.csv")
    assert curves.groupby(["task", "student"]).seed.nunique().to_dict() == {key: 3 for key in starts.groupby(["task", "student"]).groups}
    assert len(starts.groupby(["task", "student"])) == 8
    assert load("read").main(tmp_path) + "\n" == (STUDY / "reading.md").read_text()


KEPT = "results/transfer-ablations/kept/students"


@pytest.fixture(scope="module")
def kept_students(archived_study) -> Path:
    """The four students, restored out of the archive as the README says (skips where the history is absent)."""
    return archived_study(KEPT)


@pytest.mark.parametrize("name", ["divmorph", "no-kdiv-transformer", "no-kdiv-decoder", "no-orthogonality"])
def test_a_kept_student_is_the_student_it_is_named_for_distilled_400k_steps(name, kept_students, official_cache):
    """Each student the race kept loads by its path, with its statistics and its run's robots; its policy is built
    as ``STUDENTS[name]`` builds it from the settings kept beside it (the ablation's switch included); it was
    distilled for 400k DAgger steps, as those settings say; and it acts on a training robot."""
    from divmorph.pipeline.provenance import recorded_profile
    from divmorph.pipeline.students import STUDENTS
    from divmorph.pretrained import load_pretrained

    profile = recorded_profile(kept_students / name / "run.json")
    assert profile.distill.n_timesteps == 400_000
    student = load_pretrained(kept_students / name / "student")
    assert isinstance(student.model.policy, STUDENTS[name].policy) and student.normalizer is not None
    assert student.model.policy_kwargs.items() >= STUDENTS[name].policy_kwargs(profile).items()
    assert 400_000 <= student.model.num_timesteps < 400_000 + 8 * 256
    (row,) = student.evaluate(student.robots[:1], task="FT", episodes=1, seed=0, max_episode_steps=50)
    assert np.isfinite(row["return"]) and row["length"] > 0
