"""The client's pure parts, without I/O: the route book, the stages' state machine, a call's
actions, observation trees."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.error import AlreadyPendingCallError

from vecsim import trees, wire
from vecsim.client.calls import check_actions, step_actions
from vecsim.client.errors import RoutingChangedError
from vecsim.client.routebook import RouteBook
from vecsim.client.routing import TrajRoute
from vecsim.client.stagestate import StageState, StageStates
from vecsim.config import RoutedPod, RoutedStage, RoutingTable, TaskBlock


def _pod(name: str, *blocks: tuple[str, int], url: str | None = None) -> RoutedPod:
    tasks, start = [], 0
    for task_id, n in blocks:
        tasks.append(TaskBlock(task_id=task_id, env_start=start, num_envs=n))
        start += n
    return RoutedPod(pod=name, url=url or f"http://{name}:8000", num_envs=start, tasks=tuple(tasks))


def _table(*stages: list[RoutedPod], generation: int = 1) -> RoutingTable:
    return RoutingTable(
        generation=generation,
        job_id="t",
        ready=True,
        stages=tuple(RoutedStage(stage_id=s, pods=tuple(pods)) for s, pods in enumerate(stages)),
    )


TWO_STAGES = _table([_pod("sim-0", ("a", 2))], [_pod("sim-1", ("a", 2))])


# -- the route book ------------------------------------------------------------------------------


def test_placed_routes_are_live_only_once_replaced():
    book = RouteBook(TWO_STAGES)
    routes = book.place([("a", 3), ("a", 4)], ["k0", "k1"])
    assert book.routes() == {}
    book.replace(routes)
    assert book.routes() == routes
    assert book.stage_keys(0) == ["k0"] and book.stage_keys(1) == ["k1"]
    assert (routes["k0"].pod, routes["k1"].pod) == ("sim-0", "sim-1")


def test_a_key_on_another_stage_is_refused_naming_it():
    book = RouteBook(TWO_STAGES)
    book.replace(book.place([("a", 0), ("a", 0)], ["k0", "k1"]))
    with pytest.raises(ValueError, match="'k1' runs on stage 1, not stage 0"):
        book.check_on_stage(["k0", "k1"], 0)
    with pytest.raises(ValueError, match="'nope' is not a live trajectory"):
        book.live(["k0", "nope"])


def test_a_stage_not_in_the_table_is_refused():
    with pytest.raises(ValueError, match="stage 2 is not in the routing table"):
        RouteBook(TWO_STAGES).check_stage(2)


def test_state_ids_are_recorded_for_live_keys_only():
    book = RouteBook(TWO_STAGES)
    book.replace(book.place([("a", 0), ("a", 0)], ["k0", "k1"]))
    book.set_state_ids(["k0", "gone"], [7, 9])
    assert book.routes()["k0"].state_id == 7
    assert book.routes()["k1"].state_id == 0


def test_a_new_table_loses_the_trajectories_of_pods_that_changed():
    book = RouteBook(TWO_STAGES)
    book.replace(book.place([("a", 0), ("a", 0)], ["k0", "k1"]))
    moved_pod = _table([_pod("sim-0", ("a", 2))], [_pod("sim-1", ("a", 2), url="http://elsewhere:8000")], generation=2)
    assert book.take_table(moved_pod) == ["k1"]
    assert book.generation == 2
    assert list(book.routes()) == ["k0"]
    with pytest.raises(RoutingChangedError) as info:
        book.check_lost(["k0", "k1"])
    assert info.value.traj_keys == ["k1"] and info.value.generation == 2


def test_a_rebuilt_pod_loses_its_trajectories():
    book = RouteBook(TWO_STAGES)
    book.replace(book.place([("a", 0), ("a", 0), ("a", 0)], ["k0", "k1", "k2"]))
    assert book.lose_pod("sim-0") == ["k0", "k2"]
    assert book.holders() == ["sim-1"]
    with pytest.raises(RoutingChangedError):
        book.check_on_stage(["k2"], 0)


def test_a_new_batch_forgets_the_lost_trajectories():
    book = RouteBook(TWO_STAGES)
    book.replace(book.place([("a", 0)], ["k0"]))
    book.lose_pod("sim-0")
    book.replace(book.place([("a", 0)], ["k0"]))
    book.check_lost(["k0"])  # no error: k0 is a new trajectory


def test_a_malformed_new_table_changes_nothing():
    book = RouteBook(TWO_STAGES)
    book.replace(book.place([("a", 0)], ["k0"]))
    one_pod_twice = _table([_pod("sim-0", ("a", 2))], [_pod("sim-0", ("a", 2))], generation=2)
    with pytest.raises(ValueError, match="pod sim-0 is in stages 0 and 1"):
        book.take_table(one_pod_twice)
    assert book.generation == 1 and list(book.routes()) == ["k0"]


def test_a_part_of_a_batch_is_placed_on_the_stages_given():
    book = RouteBook(TWO_STAGES)
    routes = book.place([("a", 0), ("a", 1)], ["k0", "k1"], stages=[1, 1])
    assert [(r.pod, r.env_index, r.stage_id) for r in routes.values()] == [("sim-1", 0, 1), ("sim-1", 1, 1)]


def test_admit_takes_the_lowest_free_env_of_the_task_on_the_first_pod_that_has_one():
    table = _table([_pod("p0", ("a", 1), ("b", 1)), _pod("p1", ("a", 2))])
    book = RouteBook(table)
    book.replace({"k0": TrajRoute("p0", 0, "a", 0, 0)})
    route = book.admit("k1", ("a", 7), 0, ["p0", "p1"])
    assert (route.pod, route.env_index, route.state_id) == ("p1", 0, 7)
    assert book.admit("k2", ("b", 0), 0, ["p1"]) is None  # p1 has no env of b: nothing changes
    assert list(book.routes()) == ["k0", "k1"]


def test_a_retired_trajectory_frees_its_env_for_the_next():
    book = RouteBook(TWO_STAGES)
    book.replace(book.place([("a", 0), ("a", 1)], ["k0", "k1"], stages=[0, 0]))
    assert book.admit("k2", ("a", 2), 0, ["sim-0"]) is None
    book.retire(["k0"])
    assert (book.admit("k2", ("a", 2), 0, ["sim-0"]).env_index, list(book.routes())) == (0, ["k1", "k2"])
    with pytest.raises(ValueError, match=r"traj_keys \['k0'\] are not live"):
        book.retire(["k0"])


def test_an_ended_trajectory_stays_ended_until_reset_retired_readmitted_or_moved():
    book = RouteBook(TWO_STAGES)
    book.replace(book.place([("a", 0), ("a", 1)], ["k0", "k1"], stages=[0, 0]))
    book.note_ended([], {"k0": "first end", "k1": "end"})
    book.note_ended([], {"k0": "second end"})  # the first record stays
    assert book.ended() == {"k0": "first end", "k1": "end"}
    book.note_ended(["k1"], {})  # reset
    assert list(book.ended()) == ["k0"]
    same_env = dict(book.routes())
    book.replace(same_env)
    assert list(book.ended()) == ["k0"]
    book.replace({"k0": TrajRoute("sim-0", 1, "a", 0, 0)})  # k0 moved to another env
    assert book.ended() == {}
    book.note_ended([], {"k0": "end"})
    book.retire(["k0"])
    assert book.ended() == {}


def test_admit_refuses_pods_of_another_stage_and_malformed_requests():
    book = RouteBook(TWO_STAGES)
    with pytest.raises(ValueError, match=r"pods \['sim-1'\] are not pods of stage 0"):
        book.admit("k0", ("a", 0), 0, ["sim-1"])
    with pytest.raises(ValueError):
        book.admit("k0", ("a", -1), 0)
    assert book.admit("k0", ("a", 0), 0).pod == "sim-0"  # no pods given: the stage's, in table order


# -- a call's actions ----------------------------------------------------------------------------

BOX = spaces.Box(-1.0, 1.0, (3,), np.float32)


def test_one_axis_more_than_one_action_per_env_is_a_chunk():
    assert wire.chunk_length((5, 3), (3,)) is None
    assert wire.chunk_length((5, 4, 3), (3,)) == 4
    assert wire.chunk_length((5,), ()) is None  # a Discrete action each
    assert wire.chunk_length((5, 2), ()) == 2


def test_one_array_and_a_mapping_of_the_same_actions_are_one_call():
    chunks = np.arange(2 * 4 * 3, dtype=np.float32).reshape(2, 4, 3) / 100
    from_array = step_actions(BOX, ["a", "b"], chunks)
    from_mapping = check_actions(BOX, {"a": chunks[0], "b": chunks[1]})
    assert from_array.traj_keys == from_mapping.traj_keys == ["a", "b"]
    assert from_array.chunk == from_mapping.chunk == 4
    np.testing.assert_array_equal(from_array.array, from_mapping.array)
    one_each = step_actions(BOX, ["a", "b"], chunks[:, 0])
    assert one_each.chunk is None and one_each.array.shape == (2, 3)


def test_a_calls_rows_keep_its_form_and_cut_chunks_to_a_horizon():
    actions = step_actions(BOX, ["a", "b", "c"], np.zeros((3, 4, 3), np.float32))
    cut = actions.rows([2, 0], at_most=2)
    assert (cut.traj_keys, cut.chunk, cut.array.shape) == (["c", "a"], 2, (2, 2, 3))
    assert actions.rows([1], at_most=9).chunk == 4
    one_each = step_actions(BOX, ["a", "b"], np.zeros((2, 3), np.float32))
    assert one_each.rows([1], at_most=1).array.shape == (1, 3)


@pytest.mark.parametrize(
    ("space", "actions", "named"),
    [
        (BOX, np.zeros((2, 4, 2), np.float32), r"shape \[2, 4, 2\], expected \[2, 4, 3\]"),
        (BOX, np.zeros((3, 3), np.float32), r"expected \[2, 3\] for 2 traj_keys"),
        (BOX, np.array([[0, 0, 0], [0, np.nan, 0]], np.float32), r"traj_key 'b': action holds NaN"),
        (spaces.Discrete(3), np.zeros((2, 4), np.int64), "chunks of actions are for Box action spaces"),
    ],
)
def test_a_bad_array_of_actions_is_refused_naming_what_is_wrong(space, actions, named):
    with pytest.raises(ValueError, match=named):
        step_actions(space, ["a", "b"], actions)


# -- the stages' state machine -----------------------------------------------------------------


def test_stages_begin_idle():
    states = StageStates()
    assert states.state(0) is StageState.IDLE and states.busy() == []


def test_the_waiting_state_says_what_the_stage_waits_on():
    assert StageState.waiting_for(resets=True, steps=False) is StageState.WAITING_RESET
    assert StageState.waiting_for(resets=False, steps=True) is StageState.WAITING_STEP
    assert StageState.waiting_for(resets=True, steps=True) is StageState.WAITING_CALL


def test_a_call_holds_all_its_stages_and_its_end_frees_them():
    states, call = StageStates(), object()
    started = states.begin({0: StageState.WAITING_RESET, 2: StageState.WAITING_STEP}, call, lambda: "sent")
    assert started == "sent"
    assert states.state(0) is StageState.WAITING_RESET and states.state(2) is StageState.WAITING_STEP
    assert states.busy() == [0, 2] and states.busy([1, 2]) == [2]
    states.end([0, 2], call)
    assert states.busy() == []


def test_a_second_call_on_a_waiting_stage_changes_no_stage_and_sends_nothing():
    states, first = StageStates(), object()
    states.begin({1: StageState.WAITING_STEP}, first)
    sent = []
    with pytest.raises(AlreadyPendingCallError, match=r"stage\(s\) \[1\] already wait on a call"):
        states.begin({0: StageState.WAITING_STEP, 1: StageState.WAITING_STEP}, object(), lambda: sent.append(1))
    assert sent == [] and states.state(0) is StageState.IDLE and states.state(1) is StageState.WAITING_STEP


def test_a_late_end_of_an_older_call_leaves_the_newer_call_alone():
    states, old, new = StageStates(), object(), object()
    states.begin({0: StageState.WAITING_STEP}, old)
    states.end([0], old)
    states.begin({0: StageState.WAITING_RESET}, new)
    states.end([0], old)
    assert states.state(0) is StageState.WAITING_RESET
    states.end([0], old)  # ending twice is harmless
    states.end([0], new)
    assert states.state(0) is StageState.IDLE


def test_no_call_moves_a_stage_to_idle():
    with pytest.raises(ValueError, match="cannot move a stage to IDLE"):
        StageStates().begin({0: StageState.IDLE}, object())


def test_placing_a_batch_needs_every_stage_idle():
    states = StageStates()
    assert states.while_idle("placing a new batch", lambda: "placed") == "placed"
    states.begin({3: StageState.WAITING_STEP}, object())
    with pytest.raises(AlreadyPendingCallError, match=r"stages \[3\] have calls in flight"):
        states.while_idle("placing a new batch", lambda: pytest.fail("ran while a call was in flight"))


def test_end_all_frees_every_stage_and_names_each_call_once():
    states, a, b = StageStates(), object(), object()
    states.begin({0: StageState.WAITING_STEP, 1: StageState.WAITING_STEP}, a)
    states.begin({2: StageState.WAITING_RESET}, b)
    assert {id(c) for c in states.end_all()} == {id(a), id(b)}
    assert states.busy() == []


def test_calls_on_different_pods_of_a_stage_wait_side_by_side():
    states, a, b = StageStates(), object(), object()
    states.begin({0: StageState.WAITING_STEP}, a, pod="p0")
    states.begin({0: StageState.WAITING_RESET}, b, pod="p1")
    assert states.state(0) is StageState.WAITING_CALL and states.pod_busy(0, "p0") and not states.pod_busy(0, "p2")
    states.end([0], a)
    assert states.state(0) is StageState.WAITING_RESET and not states.pod_busy(0, "p0")


def test_a_pod_call_conflicts_with_a_call_on_its_pod_or_its_whole_stage():
    states = StageStates()
    states.begin({0: StageState.WAITING_STEP}, object(), pod="p0")
    with pytest.raises(AlreadyPendingCallError, match=r"pod p0 of stage\(s\) \[0\] already wait"):
        states.begin({0: StageState.WAITING_STEP}, object(), pod="p0")
    with pytest.raises(AlreadyPendingCallError, match=r"stage\(s\) \[0\] already wait"):
        states.begin({0: StageState.WAITING_STEP}, object())
    whole = StageStates()
    whole.begin({1: StageState.WAITING_STEP}, object())
    with pytest.raises(AlreadyPendingCallError):
        whole.begin({1: StageState.WAITING_STEP}, object(), pod="p3")


# -- observation trees ------------------------------------------------------------------------


def _tree(n: int) -> dict:
    return {"images": {"cam": np.zeros((n, 2, 2, 3), np.uint8)}, "pair": (np.zeros(n), np.zeros((n, 2), np.int64))}


def test_fill_rows_writes_a_wire_answer_into_the_given_rows():
    dst = _tree(4)
    src = {"images": {"cam": np.ones((2, 2, 2, 3), np.uint8)}, "pair": {"0": np.full(2, 5.0), "1": np.full((2, 2), 7)}}
    trees.fill_rows(dst, src, np.array([1, 3]), "obs")
    assert dst["images"]["cam"][[1, 3]].all() and not dst["images"]["cam"][[0, 2]].any()
    assert dst["pair"][0].tolist() == [0, 5, 0, 5] and dst["pair"][1][3].tolist() == [7, 7]


def test_fill_rows_names_the_key_path_at_fault():
    dst = _tree(2)
    with pytest.raises(
        trees.TreeMismatchError, match=r"answer obs.images.cam has shape \[2, 2, 2\], expected \[2, 2, 2, 3\]"
    ):
        trees.fill_rows(dst, {"images": {"cam": np.zeros((2, 2, 2))}, "pair": {}}, np.arange(2), "obs")
    with pytest.raises(
        trees.TreeMismatchError, match=r"answer obs has keys \['images'\], expected \['images', 'pair'\]"
    ):
        trees.fill_rows(dst, {"images": {}}, np.arange(2), "obs")


def test_row_take_rows_stack_and_leaves_keep_the_structure():
    tree = _tree(3)
    tree["pair"][0][:] = [0, 1, 2]
    one = trees.row(tree, 2)
    assert one["pair"][0] == 2 and one["images"]["cam"].shape == (2, 2, 3)
    assert trees.take_rows(tree, np.array([2, 0]))["pair"][0].tolist() == [2, 0]
    stacked = trees.stack([one, one])
    assert stacked["images"]["cam"].shape == (2, 2, 2, 3) and stacked["pair"][1].shape == (2, 2)
    assert [leaf.shape for leaf in trees.leaves(tree)] == [(3, 2, 2, 3), (3,), (3, 2)]
    dst = _tree(3)
    trees.put_rows(dst, tree, np.array([0]), np.array([2]))
    assert dst["pair"][0].tolist() == [2, 0, 0]
