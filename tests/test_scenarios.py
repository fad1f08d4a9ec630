"""Every task's world does what the task says, on both backends: physical scenarios.

Each test moves one robot by hand (:class:`scenario_probe.Probe`: set the torso's position or
velocity, step with zero action) and asserts what a user would observe -- a robot dropped on a
block rests on it, a pushed box moves, a new cell pays once -- on the single env and on the
batched backend (MuJoCo Warp on CPU Warp), and that the batched world reported no contact or
constraint overflow while doing it.

How each was checked to fail on a broken world (once, by hand): blocks as world-body geoms moved
through ``geom_pos`` (the old Obstacle; the drop and the push tests fail on both backends); the
batched height-field variant not selected per world (the rest-on-terrain test fails on the
batched backend); the incline's slab tilted the other way; the push, reach, progress and cell
rewards with their signs flipped; the fall ratio off by 0.1.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scenario_probe import BACKENDS, Probe

from unimal_envs.arenas.heightfield import FORWARD_CELLS, LATERAL_CELLS

pytest.importorskip("mujoco_warp", reason="the batched scenarios need the mujoco-warp extra")

#: A robot upside down (180 degrees about x): legs in the air, so the torso height is what we set.
UPSIDE_DOWN = (0.0, 1.0, 0.0, 0.0)


def _quiet(results, probe: Probe) -> None:
    """No step of ``results`` ended the episode, and the batched world never overflowed."""
    reasons = [reason for _, _, terminated, reason in results if terminated]
    assert not reasons, f"the episode ended ({reasons[0]})"
    if probe.batched:
        assert probe.benv.overflow_report() == {}, probe.benv.overflow_report()


def _clear_block(probe: Probe, clearance: float = 2.5) -> np.ndarray:
    """A placed block with ``clearance`` m of free ground before its -x face (no other block there)."""
    blocks = probe.blocks()
    placed = blocks[blocks[:, 2] > 0]
    for bx, by, bz, sx, sy, sz in placed:
        x0, x1, y0, y1 = bx - sx - clearance, bx - sx, by - 1.0, by + 1.0
        others = [b for b in placed if not (b[0] == bx and b[1] == by)]
        if all(o[0] + o[3] < x0 or o[0] - o[3] > x1 or o[1] + o[4] < y0 or o[1] - o[4] > y1 for o in others):
            return np.array([bx, by, bz, sx, sy, sz])
    raise AssertionError("no block with free ground before it")


# ---------------------------------------------------------------------- Obstacle
@pytest.mark.parametrize("backend", BACKENDS)
def test_a_robot_dropped_onto_an_obstacle_block_rests_on_it(backend):
    probe = Probe("Obstacle", backend)
    bx, by, bz, sx, sy, sz = _clear_block(probe)
    top = bz + sz
    assert top == pytest.approx(4.0)
    probe.place((bx, by, top + probe.standing_height + 0.3), still=True)
    results = probe.run(75)  # 1.5 s: the drop and the settling
    _quiet(results, probe)
    assert probe.lowest_robot_point() == pytest.approx(top, abs=0.05), "the robot does not stand on the block's top"
    assert probe.torso[2] > top + 0.3 * probe.standing_height


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_torso_pushed_into_an_obstacle_block_stops_at_its_face(backend):
    probe = Probe("Obstacle", backend)
    bx, by, bz, sx, sy, sz = _clear_block(probe)
    face = bx - sx
    probe.place((face - 1.5, by, probe.standing_height), still=True)
    results = probe.carry(60, velocity=(2.0, 0.0, 0.0))  # 2.4 m of travel if nothing stopped it
    _quiet(results, probe)
    x = probe.torso[0]
    assert x < face, "the torso went into the block"
    assert x > face - 1.0, "the torso did not reach the block"
    # The height map's samples straight ahead that lie inside the block read +2 m (the reference's value).
    forward = FORWARD_CELLS * 0.1
    inside = (forward > face - x + 0.15) & (forward < face - x + 2 * sx - 0.15)
    ahead = probe.obs["hfield"].reshape(len(LATERAL_CELLS), len(FORWARD_CELLS))[list(LATERAL_CELLS).index(0), inside]
    assert inside.any() and np.allclose(ahead, 2.0), "the height map does not show the block the robot is pushing against"


# ---------------------------------------------------------------------- terrain
def _smooth_raised_spot(probe: Probe, task: str, flatness: float) -> tuple[float, float]:
    """A point of the current terrain at least 0.3 m high whose surroundings (+-0.5 m) are within
    ``flatness`` of its height, so a robot resting there has its feet at that height."""
    if task == "VT":
        candidates = [(x, y) for x in np.arange(4.0, 100.0, 0.5) for y in (0.0, -5.0, 5.0)]
    else:  # the bowl rises with the radius, 1.3 m at 25 m
        candidates = [(r * math.cos(a), r * math.sin(a)) for r in np.arange(12.0, 30.0, 1.0) for a in np.arange(0, 2 * math.pi, 0.5)]
    offsets = [(dx, dy) for dx in (-0.5, -0.25, 0.0, 0.25, 0.5) for dy in (-0.5, -0.25, 0.0, 0.25, 0.5)]
    for x, y in candidates:
        h = probe.ground(x, y)
        if h >= 0.3 and all(abs(probe.ground(x + dx, y + dy) - h) <= flatness for dx, dy in offsets):
            return float(x), float(y)
    raise AssertionError("no smooth raised spot on this terrain")


@pytest.mark.parametrize("backend, robot", [("single", 0), ("batched", 0), ("batched", 1)])
@pytest.mark.parametrize("task, flatness", [("VT", 0.02), ("Escape", 0.06)])
def test_a_resting_robot_stands_at_the_height_its_terrain_map_shows_and_follows_a_redraw(task, flatness, backend, robot):
    """Robot 1 of a batched env reads robot 0's copy of the terrain pool (one copy per task)."""
    probe = Probe(task, backend, robot=robot)
    heights = []
    for draw in range(2):
        if draw:
            probe.redraw()
        x, y = _smooth_raised_spot(probe, task, flatness)
        ground = probe.ground(x, y)
        heights.append(ground)
        probe.place((x, y, ground + probe.robot.morphology.torso_height + 0.2), still=True)
        results = probe.run(50)
        _quiet(results, probe)
        assert probe.lowest_robot_point() == pytest.approx(ground, abs=flatness + 0.03), (
            f"draw {draw}: the robot rests at {probe.lowest_robot_point():.3f} m, its terrain map says {ground:.3f} m"
        )


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("task", ["VT", "Escape", "Obstacle"])
def test_the_height_map_changes_when_the_terrain_is_redrawn(task, backend):
    probe = Probe(task, backend)
    pose = (20.0, 3.0, 1.5) if task != "Escape" else (18.0, 6.0, 2.5)
    maps = []
    for draw in range(2):
        if draw:
            probe.redraw()
        probe.place(pose, still=True)
        probe.step()
        maps.append(probe.obs["hfield"].copy())
    assert np.ptp(maps[0]) > 0.1 and np.abs(maps[0] - maps[1]).max() > 0.1


# ---------------------------------------------------------------------- Incline
@pytest.mark.parametrize("backend", BACKENDS)
def test_on_the_incline_a_robot_stays_on_the_slope_and_is_paid_the_distance_along_it(backend):
    probe = Probe("Incline", backend)
    task = probe.single_task
    angle = math.radians(task.angle_deg)
    slope = math.tan(angle)
    settle = probe.run(15)  # dropped from the spawn height onto the slope
    for _ in range(3):  # left alone, it rests, slides or tumbles on the surface, never into or off it
        settle += probe.run(5)
        assert probe.lowest_robot_point() == pytest.approx(slope * probe.torso[0], abs=0.15)
    _quiet(settle, probe)
    before = probe.torso
    up = (1.5 * math.cos(angle), 0.0, 1.5 * math.sin(angle))
    pushed = probe.run(40, velocity=up)  # pushed up the slope, it goes up along the surface
    _quiet(pushed, probe)
    after = probe.torso
    assert after[0] - before[0] > 0.8, "the push did not move the robot up the slope"
    assert probe.lowest_robot_point() == pytest.approx(slope * after[0], abs=0.15), "it left the surface"
    paid = sum(terms["forward"] for _, terms, _, _ in pushed) * 0.02
    assert paid == pytest.approx((after[0] - before[0]) / math.cos(angle), rel=1e-3, abs=1e-3)
    start = task.start_along_slope * math.cos(angle)
    assert probe.info["distance_along_slope"] == pytest.approx((after[0] - start) / math.cos(angle), abs=1e-3)


# ---------------------------------------------------------------------- boxes
def _along(probe: Probe, direction: np.ndarray, speed: float) -> tuple[float, float, float]:
    """A velocity of ``speed`` along horizontal ``direction``, following the slope on inclines."""
    task = probe.single_task
    slope = math.tan(math.radians(task.angle_deg)) if hasattr(task, "angle_deg") else 0.0
    v = np.array([direction[0], direction[1], slope * direction[0]])
    return tuple(speed * v / np.linalg.norm(v))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("task", ["ManipulateBox", "PushBoxIncline"])
def test_a_torso_moved_into_the_box_pushes_it_and_the_reach_and_push_terms_have_the_right_signs(task, backend):
    probe = Probe(task, backend)
    ground = probe.ground
    box, goal = probe.box, probe.goal
    u = (goal[:2] - box[:2]) / np.linalg.norm(goal[:2] - box[:2])  # toward the goal
    x, y = box[:2] - 2.0 * u
    probe.place((x, y, ground(x, y) + probe.standing_height), still=True)
    probe.step()  # the teleport's reach progress is not the robot's
    approach = probe.carry(70, velocity=_along(probe, u, 1.5))
    _quiet(approach, probe)
    reach = [terms["reach"] for _, terms, _, _ in approach]
    assert all(r > 0 for r in reach[:5]), f"approaching the box is not paid: {reach[:5]}"
    assert sum(terms["reached"] for _, terms, _, _ in approach) == 10.0, "the +10 for reaching is paid exactly once"
    moved = probe.box[:2] - box[:2]
    assert moved @ u > 0.2, "the box did not move where it was pushed"
    push = sum(terms["push"] for _, terms, _, _ in approach)
    assert push > 10.0 and push == pytest.approx(
        100 * (np.linalg.norm(goal[:2] - box[:2]) - np.linalg.norm(goal[:2] - probe.box[:2])), rel=0.05
    )
    away = probe.carry(10, velocity=_along(probe, -u, 1.5))
    _quiet(away, probe)
    assert all(terms["reach"] < 0 for _, terms, _, _ in away[2:]), "walking away from the box is not penalised"
    # From the goal side, pushing the box away from the goal costs reward.
    box = probe.box
    x, y = box[:2] + 1.2 * u
    probe.place((x, y, ground(x, y) + probe.standing_height), still=True)
    probe.step()
    back = probe.carry(60, velocity=_along(probe, -u, 1.5))
    _quiet(back, probe)
    further = np.linalg.norm(goal[:2] - probe.box[:2]) - np.linalg.norm(goal[:2] - box[:2])
    assert further > 0.2, "the box was not pushed away from the goal"
    assert sum(terms["push"] for _, terms, _, _ in back) == pytest.approx(-100 * further, rel=0.05)


# ---------------------------------------------------------------------- goals
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("task", ["PointNav", "Patrol"])
def test_moving_toward_the_goal_pays_and_reaching_it_does_what_the_docs_say(task, backend):
    probe = Probe(task, backend)
    goal = probe.goal.copy()
    u = np.array([1.0, 0.0]) if task == "Patrol" else (goal[:2] - probe.torso[:2]) / np.linalg.norm(goal[:2] - probe.torso[:2])
    x, y = goal[:2] - 3.0 * u
    h = probe.robot.morphology.torso_height + 0.05
    probe.place((x, y, h), still=True)
    probe.step()
    toward = probe.run(10, velocity=(1.5 * u[0], 1.5 * u[1], 0.0))
    away = probe.run(10, velocity=(-1.5 * u[0], -1.5 * u[1], 0.0))
    _quiet(toward + away, probe)
    assert all(terms["progress"] > 0 for _, terms, _, _ in toward[1:])
    assert all(terms["progress"] < 0 for _, terms, _, _ in away[2:])
    assert all(terms["at_goal"] == 0 for _, terms, _, _ in toward + away)
    probe.place((goal[0] - 0.2 * u[0], goal[1] - 0.2 * u[1], h), still=True)
    reward, terms, terminated, _ = probe.step()
    assert terms["at_goal"] == 10.0 and not terminated
    if task == "PointNav":  # +10 on every step within 0.5 m, no end on success
        reward, terms, terminated, _ = probe.step()
        assert terms["at_goal"] == 10.0 and not terminated and probe.info["steps_at_goal"] == 2
    else:  # the goal toggles to the other end; the next step observes it 10 m behind
        assert probe.info["goals_reached"] == 1 and probe.goal[0] == -goal[0]
        probe.step()
        assert np.linalg.norm(probe.obs["goal"][:2]) > 9.0


@pytest.mark.parametrize("backend", BACKENDS)
def test_exploration_pays_a_new_cell_once(backend):
    probe = Probe("Exploration", backend)
    h = probe.robot.morphology.torso_height + 0.05
    paid = []
    for x, y in ((5.5, 5.5), (5.5, 5.5), (7.5, 5.5), (5.5, 5.5), (5.7, 5.2)):
        probe.place((x, y, h), still=True)
        paid.append(probe.step()[1]["new_cell"])
    assert paid == [1.0, 0.0, 1.0, 0.0, 0.0]


# ---------------------------------------------------------------------- ends
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("task", ["VT", "Obstacle", "Incline"])
def test_corridor_edges_end_the_episode_at_19_m(task, backend):
    probe = Probe(task, backend)
    ground = probe.ground
    for y, ends in ((18.9, False), (-18.9, False), (19.05, True), (-19.05, True)):
        x = probe.torso[0]
        probe.place((x, y, ground(x, y) + probe.robot.morphology.torso_height + 0.05), still=True)
        _, _, terminated, reason = probe.step()
        assert terminated == ends and (reason == "edge") == ends, (y, reason)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(
    "task, wall", [("PointNav", (50.0, 0.0)), ("Exploration", (0.0, -50.0)), ("ManipulateBox", (-3.0, 0.0)), ("Obstacle", (-3.0, 0.0))]
)
def test_walls_stop_a_pushed_robot_without_ending_the_episode(task, wall, backend):
    probe = Probe(task, backend)
    direction = np.sign(wall)
    start = np.array(wall) - 2.0 * direction
    probe.place((start[0], start[1], probe.standing_height), still=True)
    results = probe.carry(60, velocity=(2.0 * direction[0], 2.0 * direction[1], 0.0))
    _quiet(results, probe)
    reached = probe.torso[:2] @ direction
    limit = np.abs(wall).sum()
    assert limit - 1.0 < reached < limit, f"the torso is at {reached:.2f} m, the wall's face at {limit} m"


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize(
    "task, ratio", [("FT", 0.5), ("VT", 0.3), ("Incline", 0.2), ("Obstacle", 0.5), ("Escape", 0.5), ("PushBoxIncline", 0.2)]
)
def test_a_fall_ends_the_episode_at_the_documented_height(task, ratio, backend):
    """Falls end the episode when the torso is at most ``fall_height_ratio`` x standing height above
    the ground under it (0.5; VT 0.3; Incline and PushBoxIncline 0.2), measured with the robot
    upside down in the air so that the torso height is exactly what the test sets."""
    probe = Probe(task, backend)
    threshold = ratio * probe.standing_height
    ground = probe.ground
    x, y = probe.torso[:2]
    for above, falls in ((threshold + 0.03, False), (threshold - 0.01, True)):
        probe.place((x, y, ground(x, y) + above), quat=UPSIDE_DOWN, still=True)
        _, _, terminated, reason = probe.step()
        assert terminated == falls and (reason == "fall") == falls, (above, reason)
