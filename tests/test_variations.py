"""Variations of any robot set: robots read back into their design-space parameters, DERL's
mutations applied to them, the validity checks, and reproducible variation sets."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import mujoco
import numpy as np
import pytest
from conftest import OFFICIAL_TRAIN

from unimal_envs.morphology import variations as V
from unimal_envs.morphology.cli import main as cli_main
from unimal_envs.morphology.errors import MorphologyError
from unimal_envs.morphology.generator import finalize
from unimal_envs.morphology.loader import load_morphology, morphology_files


def physics(model: mujoco.MjModel) -> dict[str, np.ndarray]:
    """What a variation may change, in an order that does not depend on the file's sibling order."""
    return {
        "masses": np.sort(model.body_mass),
        "ranges": np.sort(model.jnt_range[1:].ravel()),
        "gears": np.sort(model.actuator_gear[:, 0]),
        "lengths": np.sort(model.geom_size[:, 1]),
    }


def same_physics(a: mujoco.MjModel, b: mujoco.MjModel) -> bool:
    pa, pb = physics(a), physics(b)
    return all(pa[k].shape == pb[k].shape and np.allclose(pa[k], pb[k], atol=1e-6) for k in pa)


def official_robots(count: int) -> list[Path]:
    if not (OFFICIAL_TRAIN / "xml").is_dir():
        pytest.skip(f"official unimals_100 set not found at {OFFICIAL_TRAIN}")
    return sorted((OFFICIAL_TRAIN / "xml").glob("*.xml"))[::33][:count]


@pytest.fixture(scope="module")
def robots() -> list[Path]:
    """Two shipped generated robots and, when the official set is here, three official ones."""
    files = morphology_files("train")[:2]
    if (OFFICIAL_TRAIN / "xml").is_dir():
        files += sorted((OFFICIAL_TRAIN / "xml").glob("*.xml"))[::40]
    return files


def test_a_robot_reads_back_into_parameters_that_rebuild_it(robots):
    for path in robots:
        genome = V.read_genome(path)
        rebuilt = finalize(genome, path.stem, "read back")
        assert same_physics(mujoco.MjModel.from_xml_path(str(path)), mujoco.MjModel.from_xml_string(rebuilt.xml)), path.stem
        assert load_morphology(path).num_limbs == genome.num_limbs


def test_a_robot_outside_the_design_space_is_refused(robots):
    xml = robots[0].read_text()
    # a capsule of a length the design space does not have (h = 0.33, not 0.2 / 0.3 / 0.4)
    first = xml.index('fromto="0 0 0 ')
    end = xml.index('"', first + 8)
    stretched = xml[:first] + 'fromto="0 0 0 0 0 -0.38' + xml[end:]
    with pytest.raises(MorphologyError, match="length|design space"):
        V.genome_from_xml(stretched, "stretched")


@pytest.mark.parametrize("kind", list(V.KINDS))
def test_variants_change_what_their_kind_changes_and_are_valid(robots, kind):
    for i, path in enumerate(robots):
        variant, op = V.vary(path, kind, [7, i, 0], f"{path.stem}-{kind}-0")
        assert op in V.KINDS[kind]
        parent, child = mujoco.MjModel.from_xml_path(str(path)), mujoco.MjModel.from_xml_string(variant.xml)
        assert not same_physics(parent, child), (path.stem, op)  # something changed
        before, after = physics(parent), physics(child)
        if kind == "dynamic":  # the shape stays: same limbs, lengths and ranges; masses or gears move
            assert np.array_equal(before["lengths"], after["lengths"]) and np.array_equal(before["ranges"], after["ranges"])
        else:  # the masses and gears move only with the shape (densities stay)
            assert op != "density" and op != "gear"
        check = V.check_variant(variant)
        assert check.loads and check.inside_envelope, check.problem
        assert variant.torso_height <= max(V.MAX_TORSO_HEIGHT, finalize(V.read_genome(path), "p", "").torso_height)


def test_a_variant_that_falls_where_its_parent_stands_is_refused():
    upright = V.read_genome(morphology_files("train")[0])
    tall = finalize(upright, "parent", "")
    assert V.stands(tall.xml)
    check = V.check_variant(tall, parent_stands=True)
    assert check.valid
    # dropped from 3 m it ends far below the height it was placed at: it counts as fallen
    dropped = replace(tall, xml=tall.xml.replace(f'pos="0 0 {tall.torso_height:g}"', 'pos="0 0 3"', 1))
    assert dropped.xml != tall.xml and not V.stands(dropped.xml)
    assert V.check_variant(dropped, parent_stands=True).problem.startswith("falls")
    assert V.check_variant(dropped, parent_stands=False).stands  # a parent that falls does not fail its variants


def test_a_variation_set_is_reproducible_and_named(tmp_path, capsys):
    robots = morphology_files("train")[:3]
    first = V.make_variation_set(robots, "kinematic", tmp_path / "a", per_robot=2, seed=3, progress=False)
    V.make_variation_set(robots, "kinematic", tmp_path / "b", per_robot=2, seed=3, progress=False)
    V.make_variation_set(robots, "kinematic", tmp_path / "c", per_robot=2, seed=4, progress=False)
    assert [p.name for p in first] == [f"train-00{i}-kinematic-{k}.xml" for i in range(3) for k in range(2)]
    same = [(tmp_path / "a" / "xml" / p.name).read_bytes() == (tmp_path / "b" / "xml" / p.name).read_bytes() for p in first]
    other = [(tmp_path / "a" / "xml" / p.name).read_bytes() == (tmp_path / "c" / "xml" / p.name).read_bytes() for p in first]
    assert all(same) and not all(other)
    record = json.loads((tmp_path / "a" / V.RECORD).read_text())
    assert record["variants"]["train-001-kinematic-1"] == {
        "parent": "train-001",
        "operator": record["variants"]["train-001-kinematic-1"]["operator"],
        "seed": [3, 1, 1],
    }
    assert [p.stem for p in morphology_files(tmp_path / "a")] == [p.stem for p in first]  # usable as a robot set
    assert cli_main(["mutate", "train", "--kind", "dynamic", "--out", str(tmp_path / "cli"), "--quiet"]) == 0
    assert "100 dynamic variants of train" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        cli_main(["mutate", "train", "--kind", "sideways", "--out", str(tmp_path / "x")])
    with pytest.raises(MorphologyError, match="per_robot"):
        V.make_variation_set(robots, "dynamic", tmp_path / "d", per_robot=0)


def test_official_robots_vary_too():
    for i, path in enumerate(official_robots(2)):
        for kind in V.KINDS:
            variant, _ = V.vary(path, kind, [0, i, 0], f"{path.stem}-{kind}-0")
            assert V.check_variant(variant).loads
