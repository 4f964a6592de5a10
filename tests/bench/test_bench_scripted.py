"""The scripted pick-and-place bench (``bench/bench_scripted.py``, ``bench/lib/scripted.py``).

Its pure parts against references: the Wilson interval against scipy's, rotations against
scipy's, the waypoints and how the policy walks them, the bookkeeping of episodes and of the
envs' errors. Its episode loop through real pods of the tests' custom gymnasium env: an env that
raises costs only its own episode. Then the bench's ``--smoke`` path (a real CPU pod,
``HTTPVectorEnv``) against LIBERO itself: the same policy on LIBERO's own
``OffScreenRenderEnv``, reset as the published evaluations do, ends each episode at the same
step with the same success, and the carried table holds where LIBERO puts the objects.
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import binomtest
from support import gym_custom_env
from support.bench_scripts import BENCH, bench_import

CUSTOM = f"{gym_custom_env.__name__}:{gym_custom_env.ENV_ID}"


@pytest.fixture(scope="module")
def scripted():
    with bench_import("lib.scripted") as module:
        yield module


@pytest.fixture(scope="module")
def bench_module():
    with bench_import("bench_scripted") as module:
        yield module


ROW = {
    "pairs": [
        {
            "object": "can",
            "goal": "basket_region",
            "pick": [0.1, -0.2, 0.47],
            "top": 0.51,
            "bottom": 0.43,
            "yaw": 0.3,
            "place": [0.0, 0.27, 0.5],
            "place_top": 0.57,
        }
    ]
}


@pytest.mark.parametrize(("successes", "trials"), [(0, 50), (1, 50), (25, 50), (37, 50), (50, 50), (3, 7)])
def test_wilson_interval_is_scipys(scripted, successes: int, trials: int) -> None:
    expected = binomtest(successes, trials).proportion_ci(0.95, method="wilson")
    assert scripted.wilson(successes, trials) == pytest.approx((expected.low, expected.high), abs=1e-9)


def test_wilson_interval_of_no_trials_says_nothing(scripted) -> None:
    assert scripted.wilson(0, 0) == (0.0, 1.0)


def test_agreement_compares_the_states_both_engines_ran(scripted) -> None:
    cpu = {0: True, 1: True, 2: False, 3: False, 4: True}
    gpu = {0: True, 1: False, 2: False, 3: True}  # state 4 not run
    assert scripted.agreement(cpu, gpu) == {
        "states": 4,
        "both_succeed": 1,
        "both_fail": 1,
        "differ": 2,
        "differing_state_ids": [1, 3],
        "errored": 0,
        "errored_state_ids": [],
    }


def test_agreement_counts_states_that_errored_on_either_engine_apart(scripted) -> None:
    cpu = {0: True, 1: None, 2: False, 3: True, 4: None}
    gpu = {0: True, 1: True, 2: None, 3: False, 4: None}
    assert scripted.agreement(cpu, gpu) == {
        "states": 5,
        "both_succeed": 1,
        "both_fail": 0,
        "differ": 1,
        "differing_state_ids": [3],
        "errored": 3,
        "errored_state_ids": [1, 2, 4],
    }


def test_episodes_give_envs_the_states_in_order_and_idle_them_when_none_is_left(scripted) -> None:
    book = scripted.Episodes([5, 6, 7], num_envs=2)
    assert book.assign([0, 1]) == {0: 5, 1: 6} and book.running.tolist() == [True, True]
    assert book.step([0, 1], np.array([False, True]), np.array([False, False])) == [1]
    assert book.outcome == {6: {"success": True, "steps": 1}}
    assert book.assign([1]) == {1: 7}
    assert book.step([0, 1], np.array([False, False]), np.array([True, False])) == [0]
    assert book.assign([0]) == {} and book.running.tolist() == [False, True]  # nothing left: env 0 idles
    assert book.outcome[5] == {"success": False, "steps": 2}


def test_an_env_error_ends_only_its_episode_and_frees_its_env(scripted) -> None:
    book = scripted.Episodes(range(4), num_envs=3)
    book.assign([0, 1, 2])
    book.step([0, 1, 2], np.zeros(3, dtype=bool), np.zeros(3, dtype=bool))
    book.fail([1], "RuntimeError: SimStateError: env 1: not finite")
    assert book.outcome == {1: {"error": "RuntimeError: SimStateError: env 1: not finite", "steps": 1}}
    assert book.running.tolist() == [True, False, True]
    assert book.assign([1]) == {1: 3} and book.steps[1] == 0  # the next state not yet run
    book.fail([1], "ValueError: in its reset")  # a reset that raised: no step taken
    assert book.outcome[3] == {"error": "ValueError: in its reset", "steps": 0}
    assert book.assign([1]) == {} and book.running.tolist() == [True, False, True]


def test_the_rate_and_its_interval_leave_errored_episodes_out(scripted) -> None:
    outcome = {
        0: {"success": True, "steps": 100},
        1: {"error": "ValueError: boom", "steps": 3},
        2: {"success": False, "steps": 520},
        3: {"success": True, "steps": 200},
        4: {"error": "ValueError: boom", "steps": 0},
    }
    done = scripted.summary(outcome)
    assert done == {
        "states": 5,
        "successes": 2,
        "errors": 2,
        "error_state_ids": [1, 4],
        "rate": 2 / 3,
        "wilson95": [round(v, 4) for v in scripted.wilson(2, 3)],
        "mean_steps_to_success": 150.0,
        "failures_by_phase": {},
        "failures_by_empty_grip": {},
    }
    errored_only = scripted.summary({7: {"error": "x", "steps": 1}})
    assert errored_only["rate"] is None and errored_only["wilson95"] == [0.0, 1.0]


def test_episodes_record_the_notes_given_at_their_end(scripted) -> None:
    book = scripted.Episodes(range(3), num_envs=3)
    book.assign([0, 1, 2])
    notes = {0: {"waypoint": 4, "phase": "0:carry"}, 2: {"waypoint": 16, "phase": "done"}}
    assert book.step([0, 1, 2], np.array([False, False, True]), np.array([True, False, False]), notes) == [0, 2]
    book.fail([1], "ValueError: boom", {1: {"waypoint": 9, "phase": "1:reach"}})
    assert book.outcome == {
        0: {"success": False, "steps": 1, "waypoint": 4, "phase": "0:carry"},
        1: {"error": "ValueError: boom", "steps": 1, "waypoint": 9, "phase": "1:reach"},
        2: {"success": True, "steps": 1, "waypoint": 16, "phase": "done"},
    }


def test_failures_are_counted_by_the_phase_they_ended_in(scripted) -> None:
    outcome = {
        0: {"success": False, "steps": 520, "waypoint": 4, "phase": "0:carry"},
        1: {"success": True, "steps": 250, "waypoint": 14, "phase": "1:release"},
        2: {"success": False, "steps": 520, "waypoint": 4, "phase": "0:carry"},
        3: {"success": False, "steps": 520, "waypoint": 16, "phase": "done"},
        4: {"error": "ValueError: boom", "steps": 3, "waypoint": 0, "phase": "0:reach"},
        5: {"success": False, "steps": 520, "waypoint": 10, "phase": "1:grasp"},
    }
    assert scripted.summary(outcome)["failures_by_phase"] == {"0:carry": 2, "1:grasp": 1, "done": 1}


def test_failures_are_counted_by_where_their_grip_was_first_found_empty(scripted) -> None:
    outcome = {
        0: {"success": False, "steps": 520, "phase": "done", "empty_grip": "0:lift"},
        1: {"success": False, "steps": 520, "phase": "done", "empty_grip": None},
        2: {"success": True, "steps": 250, "phase": "1:lower", "empty_grip": None},
        3: {"success": False, "steps": 520, "phase": "1:carry", "empty_grip": "0:lift"},
        4: {"success": False, "steps": 520, "phase": "done", "empty_grip": "1:carry"},
    }
    assert scripted.summary(outcome)["failures_by_empty_grip"] == {"0:lift": 2, "1:carry": 1, "never": 1}


def test_policy_records_where_its_closed_fingers_first_held_nothing(scripted) -> None:
    gains = scripted.Gains()
    policy = scripted.Script([ROW], gains)
    positions = policy.positions[0]

    def at(waypoint: int, gap: float) -> np.ndarray:
        state = state_at(scripted, positions[waypoint], 0.3)
        state[0, 6:8] = gap / 2, -gap / 2
        return state

    policy.act(at(0, 0.08))
    policy.act(at(1, 0.08))
    for _ in range(gains.grip_steps + 1):  # closing on nothing: not counted while it closes
        policy.act(at(2, 0.0))
    assert policy.index[0] == 3 and policy.progress(0)["empty_grip"] == "0:lift"  # lifting, empty
    policy.act(at(3, 0.03))  # reached; then fingers apart again: the first finding stays
    policy.act(at(4, 0.0))
    assert policy.progress(0) == {"waypoint": 5, "phase": "0:lower", "empty_grip": "0:lift"}
    policy.restart(0, ROW)
    assert policy.progress(0)["empty_grip"] is None


def test_policy_holding_something_is_not_found_empty(scripted) -> None:
    gains = scripted.Gains()
    policy = scripted.Script([ROW], scripted.Gains(move_timeout=0))
    held = state_at(scripted, [0.4, 0.4, 0.9], 0.3)
    held[0, 6:8] = 0.01, -0.01  # a 2 cm object between the fingers
    for _ in range(len(policy.positions[0])):
        policy.act(held)
    assert policy.finished.all() and policy.progress(0)["empty_grip"] is None
    assert gains.empty_grip_m < 0.02


def test_phases_name_each_steps_waypoints(scripted) -> None:
    two = {"pairs": [ROW["pairs"][0], ROW["pairs"][0]]}
    names = list(scripted.waypoints(two).phases)
    assert names[:8] == ["0:reach", "0:reach", "0:grasp", "0:lift", "0:carry", "0:lower", "0:release", "0:retreat"]
    assert names[8:] == [f"1:{name[2:]}" for name in names[:8]]
    policy = scripted.Script([two])
    assert [policy.phase(0, w) for w in (0, 11, 15, 16)] == ["0:reach", "1:lift", "1:retreat", "done"]


def test_rotations_are_scipys(scripted) -> None:
    rotations = Rotation.random(64, random_state=0)
    vectors = rotations.as_rotvec()
    # The Panda points down: angles near pi, where axis-angle is ill-conditioned.
    near_pi = Rotation.from_rotvec(np.array([[np.pi - 1e-7, 0, 0], [0, 0.3, np.pi], [3.1406, -0.0024, -0.0907]]))
    vectors = np.concatenate([vectors, near_pi.as_rotvec()])
    matrices = scripted.axis_angle_to_matrix(vectors)
    np.testing.assert_allclose(matrices, Rotation.from_rotvec(vectors).as_matrix(), atol=1e-9)
    back = scripted.matrix_to_axis_angle(matrices)
    np.testing.assert_allclose(Rotation.from_rotvec(back).as_matrix(), matrices, atol=1e-6)


def test_top_down_gripper_closes_along_the_asked_direction(scripted) -> None:
    for direction in ([1.0, 0.0], [0.0, 1.0], [0.6, -0.8]):
        yaw = scripted.closing_yaw(direction, current_yaw=0.2)
        assert abs(yaw - 0.2) <= np.pi / 2
        frame = scripted.top_down(np.array(yaw))
        assert frame[:, 2] == pytest.approx([0, 0, -1])  # the hand points down
        assert abs(frame[:2, 1] @ np.array(direction)) == pytest.approx(1.0)  # fingers close along it


def test_waypoints_pick_above_down_close_up_carry_down_open_up(scripted) -> None:
    gains = scripted.Gains()
    positions, yaws, tilts, grips, holds, carries, _ = scripted.waypoints(ROW, gains)
    carry = 0.57 + gains.hover_m
    grasp = 0.51 - gains.grasp_below_top_m
    release = 0.5 + gains.release_above_m
    expected = [
        (0.1, -0.2, carry),
        (0.1, -0.2, grasp),
        (0.1, -0.2, grasp),
        (0.1, -0.2, carry),
        (0.0, 0.27, carry),
        (0.0, 0.27, release),
        (0.0, 0.27, release),
        (0.0, 0.27, carry),
    ]
    np.testing.assert_allclose(positions, expected)
    assert grips.tolist() == [-1, -1, 1, 1, 1, 1, -1, -1]
    assert holds.tolist() == [0, 0, gains.grip_steps, 0, 0, 0, gains.grip_steps, 0]
    assert carries.tolist() == [False, False, False, True, True, True, False, False]  # lift, carry, lower
    assert (yaws == 0.3).all() and (tilts == 0).all()


def test_a_pair_with_a_grip_and_a_release_is_held_and_let_go_there(scripted) -> None:
    gains = scripted.Gains()
    mug = {"pairs": [{**ROW["pairs"][0], "grip": [0.12, -0.15, 0.52], "release": [0.03, 0.31, 0.55]}]}
    positions = scripted.waypoints(mug, gains)[0]
    carry = 0.57 + gains.hover_m
    np.testing.assert_allclose(
        positions[:4], [(0.12, -0.15, carry), (0.12, -0.15, 0.52), (0.12, -0.15, 0.52), (0.12, -0.15, carry)]
    )
    np.testing.assert_allclose(
        positions[4:], [(0.03, 0.31, carry), (0.03, 0.31, 0.55), (0.03, 0.31, 0.55), (0.03, 0.31, carry)]
    )


def test_a_pair_with_a_place_yaw_turns_while_carried(scripted) -> None:
    book = {"pairs": [{**ROW["pairs"][0], "place_yaw": -1.2}]}
    yaws = scripted.waypoints(book, scripted.Gains())[1]
    assert yaws.tolist() == [0.3] * 4 + [-1.2] * 4  # grasped at its yaw, carried and let go turned


def test_a_flat_object_is_gripped_clear_of_the_table(scripted) -> None:
    gains = scripted.Gains()
    flat = {"pairs": [{**ROW["pairs"][0], "top": 0.455, "bottom": 0.435}]}
    assert scripted.waypoints(flat, gains)[0][1, 2] == pytest.approx(0.435 + gains.floor_clearance_m)


def state_at(scripted, position, yaw: float) -> np.ndarray:
    rotvec = Rotation.from_matrix(scripted.top_down(np.array(yaw))).as_rotvec()
    return np.concatenate([position, rotvec, [0.04, -0.04]])[None]


def test_policy_steers_towards_its_waypoint_within_the_action_range(scripted) -> None:
    policy = scripted.Script([ROW])
    action = policy.act(state_at(scripted, [0.1, -0.2, 0.67], 0.3))[0]
    target = policy.positions[0, 0]
    assert action[:3] == pytest.approx((target - [0.1, -0.2, 0.67]) / scripted.POS_LIMIT_M, abs=1e-6)
    assert action[3:6] == pytest.approx(0, abs=1e-6) and action[6] == -1
    far = policy.act(state_at(scripted, [-0.5, 0.5, 0.6], -1.2))[0]
    assert np.abs(far).max() == 1.0  # clipped to robosuite's range
    assert far[0] == 1.0 and far[1] == -1.0 and far[5] > 0  # towards the waypoint, turning the yaw up


def test_policy_advances_on_reaching_and_after_holding(scripted) -> None:
    gains = scripted.Gains()
    policy = scripted.Script([ROW, ROW], gains)
    positions = policy.positions[0]
    far = state_at(scripted, [0.4, 0.4, 0.9], 0.3)
    policy.act(np.concatenate([state_at(scripted, positions[0], 0.3), far]))
    assert policy.index.tolist() == [1, 0]  # env 0 reached waypoint 0; env 1 is far
    policy.act(np.concatenate([state_at(scripted, positions[1], 0.3), far]))
    assert policy.index.tolist() == [2, 0]
    for _ in range(gains.grip_steps):  # closing: it stays at the object
        assert policy.act(np.concatenate([state_at(scripted, positions[2], 0.3), far]))[0, 6] == 1
        assert policy.index[0] == 2
    policy.act(np.concatenate([state_at(scripted, positions[2], 0.3), far]))
    assert policy.index.tolist() == [3, 0] and not policy.finished.any()
    assert policy.progress(0) == {"waypoint": 3, "phase": "0:lift", "empty_grip": None}
    assert policy.progress(1) == {"waypoint": 0, "phase": "0:reach", "empty_grip": None}


def test_policy_gives_up_on_a_waypoint_after_its_timeout(scripted) -> None:
    policy = scripted.Script([ROW], scripted.Gains(move_timeout=5))
    blocked = state_at(scripted, [0.4, 0.4, 0.9], 0.3)
    for _ in range(5):
        policy.act(blocked)
    assert policy.index[0] == 0
    policy.act(blocked)
    assert policy.index[0] == 1


def test_a_restarted_env_walks_its_new_script_from_the_start(scripted) -> None:
    other = {"pairs": [{**ROW["pairs"][0], "pick": [0.2, 0.1, 0.47], "yaw": -0.4}]}
    policy = scripted.Script([ROW, ROW], scripted.Gains(move_timeout=0))
    far = state_at(scripted, [0.4, 0.4, 0.9], 0.3)
    for _ in range(3):
        policy.act(np.concatenate([far, far]))
    policy.restart(1, other)
    fresh = scripted.Script([other], scripted.Gains(move_timeout=0))
    assert policy.index.tolist() == [3, 0]
    np.testing.assert_array_equal(policy.act(np.concatenate([far, far]))[1], fresh.act(far)[0])


def test_policy_finishes_after_the_last_waypoint(scripted) -> None:
    policy = scripted.Script([ROW], scripted.Gains(move_timeout=0))
    for _ in range(len(policy.positions[0])):
        policy.act(state_at(scripted, [0.4, 0.4, 0.9], 0.3))
    assert policy.finished.all() and policy.progress(0) == {"waypoint": 8, "phase": "done", "empty_grip": None}
    action = policy.act(state_at(scripted, [0.4, 0.4, 0.9], 0.3))[0]
    assert action[6] == -1  # it stays over the goal, open


KNOB = {"joint": "stove_button", "grip": [-0.19, 0.2, 0.937], "top": 0.955, "yaw": 0.0, "turn": 1.3}
DRAWER = {"joint": "drawer", "path": [[-0.01, 0.03, 0.946], [-0.01, 0.24, 0.946]], "yaws": [-np.pi / 2, -np.pi / 2]}


def test_a_script_turns_knobs_then_places_objects_then_closes_doors(scripted) -> None:
    row = {"closes": [DRAWER], "pairs": ROW["pairs"], "turns": [KNOB]}
    assert [kind for kind, _ in scripted.steps(row)] == ["turn", "place", "close"]
    phases = scripted.waypoints(row).phases
    assert [p for p in phases if p.startswith("0:")] == [
        "0:reach", "0:reach", "0:grasp", "0:turn", "0:release", "0:retreat"
    ]  # fmt: skip
    assert [p for p in phases if p.startswith("1:")][3] == "1:lift"
    assert [p for p in phases if p.startswith("2:")] == ["2:reach", "2:reach", "2:push", "2:retreat", "2:retreat"]


def test_a_turn_grips_the_knob_on_its_axis_and_turns_the_wrist(scripted) -> None:
    gains = scripted.Gains()
    turn = scripted.waypoints({"pairs": [], "turns": [KNOB]}, gains)
    above = 0.955 + gains.hover_m
    np.testing.assert_allclose(turn.positions[:, :2], [[-0.19, 0.2]] * 6)
    np.testing.assert_allclose(turn.positions[:, 2], [above, 0.937, 0.937, 0.937, 0.937, above])
    np.testing.assert_allclose(turn.yaws, [0.0, 0.0, 0.0, 1.3, 1.3, 1.3])  # turned while closed, let go turned
    assert turn.grips.tolist() == [-1, -1, 1, 1, -1, -1]
    assert turn.holds.tolist() == [0, 0, gains.grip_steps, 0, gains.grip_steps, 0]
    assert turn.carries.tolist() == [False, False, False, True, False, False]  # the knob is held while it turns


def test_a_close_pushes_along_its_path_then_backs_off_and_rises(scripted) -> None:
    gains = scripted.Gains()
    close = scripted.waypoints({"pairs": [], "closes": [DRAWER]}, gains)
    above = 0.946 + gains.hover_m
    back = 0.24 - gains.back_off_m  # the way it came, from the path's end
    np.testing.assert_allclose(
        close.positions,
        [(-0.01, 0.03, above), (-0.01, 0.03, 0.946), (-0.01, 0.24, 0.946), (-0.01, back, 0.946), (-0.01, back, above)],
    )
    assert (close.grips == 1).all() and not close.carries.any()  # fingers closed, holding nothing
    np.testing.assert_allclose(close.yaws, -np.pi / 2)
    assert (close.tilts == 0).all()


def test_a_hinged_close_turns_the_hand_with_the_door(scripted) -> None:
    arc = {"path": [[0.0, 0.0, 1.0], [0.1, 0.02, 1.0], [0.18, 0.08, 1.0]], "yaws": [0.0, 0.2, 0.4]}
    close = scripted.waypoints({"pairs": [], "closes": [arc]})
    np.testing.assert_allclose(close.yaws, [0.0, 0.0, 0.2, 0.4, 0.4, 0.4])  # reach, reach, push, push, back, up
    with pytest.raises(ValueError, match="a yaw each"):
        scripted.waypoints({"pairs": [], "closes": [{**arc, "yaws": [0.0, 0.2]}]})
    with pytest.raises(ValueError, match="two or more points"):
        scripted.waypoints({"pairs": [], "closes": [{"path": [[0.0, 0.0, 1.0]], "yaws": [0.0]}]})


def test_a_leaning_close_tilts_the_fingertips_into_the_push(scripted) -> None:
    for yaw in (-np.pi / 2, np.pi / 2):  # the fingers close along x either way; the push is +y
        close = scripted.waypoints({"pairs": [], "closes": [{**DRAWER, "yaws": [yaw, yaw], "lean": 0.35}]})
        approach = scripted.gripper_frame(close.yaws, close.tilts)[:, :, 2]  # where the fingertips point
        np.testing.assert_allclose(approach, [[0.0, np.sin(0.35), -np.cos(0.35)]] * 5, atol=1e-9)
        np.testing.assert_allclose(scripted.gripper_frame(close.yaws, 0 * close.tilts), scripted.top_down(close.yaws))


def test_a_step_after_another_turns_the_wrist_the_least(scripted) -> None:
    pair = {**ROW["pairs"][0], "yaw": 1.5}
    script = scripted.waypoints({"pairs": [pair], "closes": [{**DRAWER, "lean": 0.35}]})
    closing = [i for i, p in enumerate(script.phases) if p.startswith("1:")]
    np.testing.assert_allclose(script.yaws[closing], np.pi / 2)  # -pi/2 closes alike, a half turn away
    approach = scripted.gripper_frame(script.yaws[closing], script.tilts[closing])[:, :, 2]
    assert (approach[:, 1] > 0.3).all()  # still leaning along the push (+y)


def test_pushing_closed_fingers_is_no_empty_grip_and_waits_longer(scripted) -> None:
    gains = scripted.Gains(move_timeout=3, push_timeout=7)
    policy = scripted.Script([{"pairs": [], "closes": [DRAWER]}], gains)
    positions = policy.positions[0]
    yaw = -np.pi / 2

    def at(point) -> np.ndarray:
        state = state_at(scripted, point, yaw)
        state[0, 6:8] = 0.0, 0.0  # fingers shut on nothing
        return state

    policy.act(at(positions[0]))
    policy.act(at(positions[1]))
    assert policy.progress(0)["phase"] == "0:push"
    blocked = at([-0.01, 0.15, 0.946])  # the drawer resists: the push's point is not reached
    for _ in range(7):
        policy.act(blocked)
    assert policy.progress(0)["phase"] == "0:push"
    policy.act(blocked)
    assert policy.progress(0) == {"waypoint": 3, "phase": "0:retreat", "empty_grip": None}


MUG_IN = {**ROW["pairs"][0], "grip": [0.12, -0.15, 0.48], "release": [0.03, 0.22, 0.5], "approach": [0.0, 0.1]}
NUDGE = {"path": [[0.03, 0.18, 0.49], [0.03, 0.29, 0.49]], "yaws": [np.pi / 2, np.pi / 2], "lean": 0.785}


def test_an_approached_place_goes_down_in_front_then_in_level_and_backs_out(scripted) -> None:
    gains = scripted.Gains()
    script = scripted.waypoints({"pairs": [MUG_IN]}, gains)
    carry = 0.57 + gains.hover_m
    outside = (0.03, 0.12)  # short of the release by the approach
    np.testing.assert_allclose(
        script.positions[4:],
        [(*outside, carry), (*outside, 0.5), (0.03, 0.22, 0.5), (0.03, 0.22, 0.5), (*outside, 0.5), (*outside, carry)],
    )
    assert script.phases[4:] == ("0:carry", "0:lower", "0:insert", "0:release", "0:retreat", "0:retreat")
    assert script.grips[4:].tolist() == [1, 1, 1, -1, -1, -1]  # let go only once in
    assert script.carries[4:].tolist() == [True, True, True, False, False, False]
    with pytest.raises(ValueError, match=r"approach \[0.1\] of can: not \[x, y\]"):
        scripted.waypoints({"pairs": [{**MUG_IN, "approach": [0.1]}]})


def test_a_push_takes_a_placed_object_deeper_before_the_door_closes(scripted) -> None:
    gains = scripted.Gains()
    row = {"pairs": [MUG_IN], "pushes": [NUDGE], "closes": [DRAWER]}
    assert [kind for kind, _ in scripted.steps(row)] == ["place", "push", "close"]
    script = scripted.waypoints(row, gains)
    pushing = [i for i, p in enumerate(script.phases) if p.startswith("1:")]
    assert [script.phases[i] for i in pushing] == ["1:reach", "1:reach", "1:push", "1:retreat", "1:retreat"]
    np.testing.assert_allclose(script.positions[pushing[2]], (0.03, 0.29, 0.49))
    assert (script.grips[pushing] == 1).all() and not script.carries[pushing].any()  # closed, holding nothing
    tips = scripted.gripper_frame(script.yaws[pushing], script.tilts[pushing])[:, :, 2]
    np.testing.assert_allclose(tips[:, 1], np.sin(0.785), atol=1e-9)  # leaning into the push (+y)
    assert scripted.pushing(script.phases)[pushing].tolist() == [False, False, True, False, False]


def test_a_step_takes_the_yaws_that_turn_the_wrist_least_on_average(scripted) -> None:
    # A door's arc from yaw -0.1 to 1.5 after a place at 1.5: its first yaw is nearer 1.5 a half
    # turn on (3.04), but the arc as a whole is nearer as it is (mean 0.7), and stays so.
    arc = {"path": [[0.0, 0.0, 1.0], [0.1, 0.02, 1.0], [0.18, 0.08, 1.0]], "yaws": [-0.1, 0.7, 1.5]}
    script = scripted.waypoints({"pairs": [{**ROW["pairs"][0], "yaw": 1.5}], "closes": [arc]})
    closing = [i for i, p in enumerate(script.phases) if p.startswith("1:")]
    np.testing.assert_allclose(script.yaws[closing], [-0.1, -0.1, 0.7, 1.5, 1.5, 1.5])
    script = scripted.waypoints({"pairs": [{**ROW["pairs"][0], "yaw": -1.5}], "closes": [arc]})
    np.testing.assert_allclose(script.yaws[closing], np.array([-0.1, -0.1, 0.7, 1.5, 1.5, 1.5]) - np.pi)


def test_rows_of_unlike_scripts_are_refused(scripted) -> None:
    with pytest.raises(ValueError, match="not one task's"):
        scripted.Script([ROW, {**ROW, "closes": [DRAWER]}])
    policy = scripted.Script([ROW])
    with pytest.raises(ValueError, match="env 0: a row of 13 waypoints, not 8"):
        policy.restart(0, {**ROW, "closes": [DRAWER]})


class Push:
    """A policy for the custom env: every action 0.2, so its level climbs to an ending; the env
    running ``boom_state`` gets the action the env refuses (42) at its second step."""

    def __init__(self, num_envs: int, boom_state: int | None = None) -> None:
        self.boom_state = boom_state
        self.state = np.full(num_envs, -1)
        self.steps = np.zeros(num_envs, dtype=np.int64)

    def restart(self, env_index: int, state_id: int) -> None:
        self.state[env_index], self.steps[env_index] = state_id, 0

    def act(self, obs) -> np.ndarray:
        actions = np.full((len(self.state), 2, 1), 0.2)
        actions[(self.state == self.boom_state) & (self.steps == 1), 0, 0] = gym_custom_env.BOOM
        self.steps += 1
        return actions


class Counted(Push):
    """:class:`Push` that tells where each env is: its state and the actions it was given."""

    def progress(self, env_index: int) -> dict[str, int]:
        return {"state": int(self.state[env_index]), "acted": int(self.steps[env_index])}


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    from support.service_procs import PodSpec, standalone_pods

    spec = PodSpec("sim-0", 0, [(f"gym/{CUSTOM}", 2)], max_episode_steps=None, envs_per_worker=2)
    with bench_import("bench_scripted") as module, standalone_pods([spec], tmp_path_factory.mktemp("pods")) as running:
        yield module, running[0].url


def test_an_env_error_costs_the_bench_only_its_episode(bench) -> None:
    from vecsim.client import HTTPVectorEnv

    bench_scripted, url = bench
    states = list(range(6))
    with contextlib.closing(HTTPVectorEnv(pod_urls=[url], autoreset_mode="disabled")) as env:
        reference = bench_scripted.run_episodes(env, states, Push(env.num_envs))
    with contextlib.closing(HTTPVectorEnv(pod_urls=[url], autoreset_mode="disabled")) as env:
        env.set_attr("refuse_resets", [0, 1])  # env 1's first reset raises
        outcome = bench_scripted.run_episodes(env, states, Push(env.num_envs, boom_state=2))
    assert {o["success"] for o in reference.values()} == {True, False}  # both endings happen
    assert set(outcome) == set(states)
    # State 1 was env 1's first: its reset raised; env 1 took state 2, whose second step raised.
    assert outcome[1] == {"error": "ValueError: the custom env refuses this reset", "steps": 0}
    assert outcome[2] == {"error": "ValueError: the custom env refuses 42", "steps": 1}
    assert {k: outcome[k] for k in (0, 3, 4, 5)} == {k: reference[k] for k in (0, 3, 4, 5)}
    summary = bench_scripted.summary(outcome)
    assert (summary["states"], summary["errors"], summary["error_state_ids"]) == (6, 2, [1, 2])


@pytest.mark.libero
@pytest.mark.slow
@pytest.mark.timeout(300)
def test_smoke_run_through_a_pod_ends_as_on_libero_itself(tmp_path: Path, scripted) -> None:
    from support.bench_scripts import bench_result
    from support.service_procs import loopback_socket

    from vecsim.engine.tasks import get_task
    from vecsim.engine.tasks._libero import (
        SETTLE_ACTION,
        ensure_config,
        init_states,
        libero_benchmark,
        quat_to_axis_angle,
    )

    with loopback_socket() as sock:
        port = sock.getsockname()[1]
    result = bench_result(tmp_path, "bench_scripted.py", "run", "--smoke", "--port", str(port), timeout=280)
    assert result["complete"] and set(result["tasks"]) == {"libero_10/0"}
    record = json.loads((tmp_path / "out" / "bench" / "bench_scripted.json").read_text())
    served = record["tasks"]["libero_10/0"]["cpu"]["per_state"]
    assert set(served) == {"0", "1"}
    table = json.loads((BENCH / "lib" / "scripted_table.json").read_text())["libero_10/0"]

    with bench_import("bench_scripted") as module:
        scene_row = module.scene_row
    # LIBERO's published loop: one env, seeded once, reset and set_init_state per episode, 10
    # settle steps, then the policy until `done` (success) or the suite's 520 steps. No camera
    # observations: the policy reads none.
    ensure_config()
    from libero.libero.envs import OffScreenRenderEnv

    bddl = libero_benchmark("libero_10").get_task_bddl_file_path(0)
    env = OffScreenRenderEnv(bddl_file_name=bddl, use_camera_obs=False)
    try:
        env.seed(0)
        states = init_states(get_task("libero_10/0"))
        for k in (0, 1):
            env.reset()
            env.set_init_state(states[k])
            for _ in range(10):
                obs, _, _, _ = env.step(SETTLE_ACTION.tolist())
            row = scene_row(env.env)
            for mine, carried in zip(row["pairs"], table[k]["pairs"]):
                for key in ("pick", "top", "bottom", "place", "place_top", "yaw"):
                    np.testing.assert_allclose(mine[key], carried[key], atol=1e-4, err_msg=f"state {k} {key}")
            policy = scripted.Script([table[k]])
            done, steps = False, 0
            while not done and steps < 520:
                state = np.concatenate(
                    [obs["robot0_eef_pos"], quat_to_axis_angle(obs["robot0_eef_quat"]), obs["robot0_gripper_qpos"]]
                )
                obs, _, done, _ = env.step(policy.act(state[None])[0].tolist())
                steps += 1
            assert served[str(k)] == {"success": bool(done), "steps": steps, **policy.progress(0)}
    finally:
        env.close()


def test_the_bench_records_the_policys_progress_at_each_episodes_end(bench) -> None:
    from vecsim.client import HTTPVectorEnv

    bench_scripted, url = bench
    states = list(range(6))
    with contextlib.closing(HTTPVectorEnv(pod_urls=[url], autoreset_mode="disabled")) as env:
        env.set_attr("refuse_resets", [0, 1])  # env 1's first reset raises
        outcome = bench_scripted.run_episodes(env, states, Counted(env.num_envs, boom_state=2))
    assert "acted" not in outcome[1]  # its reset raised: no episode to tell of
    assert outcome[2]["error"] and outcome[2]["state"] == 2 and outcome[2]["acted"] == 2  # raised on its 2nd
    for k in (0, 3, 4, 5):  # read before the env took its next state: its own episode's
        assert outcome[k]["state"] == k and outcome[k]["acted"] == outcome[k]["steps"]


def test_rows_of_each_protocol_have_their_own_key(bench_module) -> None:
    from vecsim.config import LiberoProtocol

    protocols = bench_module.PROTOCOLS
    assert bench_module.row_key("libero_10/0", protocols["published"]) == "libero_10/0"
    rlinf = bench_module.row_key("libero_10/5", protocols["rlinf"])
    assert rlinf == "libero_10/5@fixture_rule=first_reset,settle_steps=15"
    seeded = bench_module.row_key("libero_10/5", LiberoProtocol(fixture_seed=7))
    assert len({rlinf, seeded, "libero_10/5"}) == 3


def test_a_run_refuses_a_task_without_rows_under_its_protocol(bench_module, tmp_path: Path) -> None:
    import argparse

    table = tmp_path / "table.json"
    table.write_text(json.dumps({"libero_10/5": [ROW]}))  # published rows only
    args = argparse.Namespace(
        table=table, libero="rlinf", budget_s=60.0, machine="test", tasks=["libero_10/5"], out=tmp_path / "out.json"
    )
    with pytest.raises(SystemExit, match=r"libero_10/5 has no row under --libero rlinf \(libero_10/5@fixture_rule"):
        bench_module.run(args)
    assert not args.out.exists()  # refused before any pod


@pytest.mark.libero
@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    ("task", "libero"),
    [
        ("libero_10/4", "published"),
        ("libero_10/8", "rlinf"),
        ("libero_10/2", "rlinf"),
        ("libero_10/3", "rlinf"),
        ("libero_10/9", "rlinf"),
    ],
)
def test_carried_rows_are_what_the_table_measures(bench_module, task: str, libero: str) -> None:
    from vecsim.config import CameraConfig
    from vecsim.engine.tasks import make_env

    protocol = bench_module.PROTOCOLS[libero]
    carried = json.loads((BENCH / "lib" / "scripted_table.json").read_text())[bench_module.row_key(task, protocol)]
    env = make_env(task, CameraConfig(names=()), libero=protocol)
    try:
        env.reset(options={"state_id": 3})
        row = bench_module.scene_row(env.inner, bench_module.SHARED_GOAL_SPACING_M.get(task, 0.0))
    finally:
        env.close()
    assert set(row) == set(carried[3])  # a knob to turn (2), a drawer (3) or door (9) to close, a mug to push (9)
    assert all("grip" in pair and "release" in pair for pair in row["pairs"])  # mugs, moka pots, a bowl: held
    for entries in row:
        assert [set(entry) for entry in row[entries]] == [set(entry) for entry in carried[3][entries]]
        for mine, theirs in zip(row[entries], carried[3][entries]):
            for key, value in theirs.items():
                if isinstance(value, str):
                    assert mine[key] == value
                else:
                    np.testing.assert_allclose(mine[key], value, atol=1e-4, err_msg=f"{task} {entries} {key}")
