"""The UNIMAL MJCF loader: official files load unchanged, bad files get clear errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import unimal_xml

from unimal_envs import contract as C
from unimal_envs.morphology.loader import (
    MorphologyError,
    load_morphologies,
    load_morphology,
    morphology_files,
    parse_morphology,
)


def test_official_set_loads_unchanged(official_train):
    robots = load_morphologies(official_train)
    assert len(robots) == 100
    for robot in robots:
        meta = json.loads((official_train / "metadata" / f"{robot.name}.json").read_text())
        assert robot.tokens[0] == "torso/0"
        assert robot.num_limbs == meta["num_limbs"]
        assert robot.dof == meta["dof"]
        # The metadata lists mirrored limbs by limb number; we expose token indices.
        token_of_limb = {int(name.split("/")[1]): i for i, name in enumerate(robot.tokens) if name.startswith("limb/")}
        expected = {tuple(sorted((token_of_limb[a], token_of_limb[b]))) for a, b in meta["symmetric_limbs"]}
        assert set(robot.symmetric_limbs) == expected, robot.name
        assert 2 <= robot.depth <= 5


def test_spec_example_robot(official_train):
    robot = load_morphology(official_train / "xml" / "floor-1409-0-12-01-12-30-07.xml")
    assert robot.num_tokens == 9 and robot.dof == 11
    assert robot.tokens[:3] == ("torso/0", "limb/0", "limb/15")  # MuJoCo body order (depth first)
    assert robot.hinges[1] == (None, "limby/0") and robot.hinges[2] == ("limbx/15", "limby/15")
    assert int((robot.act_padding_mask == 0).sum()) == 11
    assert robot.standing_height == pytest.approx(0.55)


def test_masks_agree_with_hinges(write_robot):
    robot = load_morphology(write_robot(unimal_xml(legs=3, hinges="y")))
    assert robot.obs_padding_mask.tolist() == [0.0] * 4 + [1.0] * 8
    expected = np.ones(C.ACTION_DIM)
    for token in (1, 2, 3):
        expected[2 * token + 1] = 0.0  # "y" hinges go to slot 1
    np.testing.assert_array_equal(robot.act_padding_mask, expected)
    # Static hinge features sit in slot 1 of each limb, zeros in slot 0 and in padded tokens.
    assert np.all(robot.proprio_static[1:4, C.HINGE_SLOT_COLUMNS[0]] == 0)
    assert np.all(robot.proprio_static[1:4, C.HINGE_SLOT_COLUMNS[1]][:, -1] == 200.0)  # gear
    assert np.all(robot.proprio_static[4:] == 0) and np.all(robot.context[4:] == 0)
    assert np.all(np.abs(robot.context) <= 1.0)


@pytest.mark.parametrize(
    "xml, message",
    [
        ("<mujoco><worldbody><body name='torso/0'>", "malformed XML"),
        ("<robot name='urdf'/>", "expected <mujoco>"),
        ("<mujoco><worldbody><geom type='sphere' size='0.1'/></worldbody></mujoco>", "no body named 'torso/0'"),
        (unimal_xml(legs=12), "at most 12 tokens"),
        (unimal_xml(joint_type="ball", hinges="x"), "ball joint"),
        (unimal_xml(joint_type="slide", hinges="x"), "slide joint"),
        (unimal_xml(extra_body="<body name='limb/9'><geom type='sphere' size='0.05'/></body>"), "has 0 hinges"),
        (unimal_xml(legs=2).replace('<motor name="limbx/1" joint="limbx/1" gear="200"/>', ""), "hinges without a motor"),
        (unimal_xml(legs=2).replace("fromto", "bogus"), "could not compile"),
    ],
)
def test_bad_mjcf_is_rejected_with_its_name(write_robot, xml, message):
    path = write_robot(xml, name="broken")
    with pytest.raises(MorphologyError, match=message) as err:
        load_morphology(path)
    assert "broken.xml" in str(err.value)


def test_a_robot_that_fits_exactly_loads(write_robot):
    robot = load_morphology(write_robot(unimal_xml(legs=11, hinges="x")))
    assert robot.num_tokens == 12 and robot.dof == 11


def test_bad_morphology_arguments(tmp_path):
    with pytest.raises(MorphologyError, match="unknown morphology set 'trian'.*'train'"):
        morphology_files("trian")
    with pytest.raises(MorphologyError, match="holds no MJCF files"):
        morphology_files(tmp_path)
    with pytest.raises(MorphologyError, match="no such MJCF file"):
        morphology_files([tmp_path / "missing.xml"])
    with pytest.raises(MorphologyError, match="empty"):
        morphology_files([])


def test_parse_from_string_names_the_source():
    with pytest.raises(MorphologyError, match="^my-robot: malformed XML"):
        parse_morphology("<mujoco>", name="my-robot")


def test_torso_context_includes_the_reference_floor_offset(official_train):
    """ModuMorph's context reads the torso's body_pos in MetaMorph's world (floor top at z = 1)."""
    from unimal_envs.morphology.loader import REFERENCE_FLOOR_TOP, load_morphology

    robot = load_morphology(official_train / "xml" / "floor-1409-0-12-01-12-30-07.xml")
    z = robot.proprio_static[0, 15]  # body_pos z of the torso, as in the file
    lo, hi = -0.49, 2.04  # ModuMorph's body_pos z bounds
    assert robot.context[0, 2] == pytest.approx(2 * (z + REFERENCE_FLOOR_TOP - lo) / (hi - lo) - 1, abs=1e-6)
    assert 0.0 < robot.context[0, 2] < 1.0  # inside the bounds only with the offset


def test_a_process_loads_each_robot_file_once_and_again_when_it_changes(tmp_path):
    """Every env of a stage reads the same robots: they share one loaded (read-only) morphology,
    and an edited file is read again."""
    path = tmp_path / "robot.xml"
    path.write_text(unimal_xml())
    first = load_morphology(path)
    assert load_morphology(path) is first
    assert not first.context.flags.writeable
    path.write_text(unimal_xml() + "\n<!-- edited -->\n")
    assert load_morphology(path) is not first
