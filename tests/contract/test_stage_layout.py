"""The job's stage layout, pure: ``slices`` (a stage is a slice of every pod) against ``pods``.

The plan, the pods' assignments, the routing table and the client's routing rules (no I/O).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from vecsim.client.routebook import RouteBook
from vecsim.client.routing import (
    TrajRoute,
    changed_routes,
    place_requests,
    routed_envs,
    routing_from_pod_infos,
    stage_by_id,
    validate_routes,
)
from vecsim.config import ConfigError, JobSpec, PodCapacity, PodRecord, load_job_config
from vecsim.plan import Plan, adopt, plan, validate_job

TASKS = [f"tiny/t{i}" for i in range(5)]
URLS = {f"sim-{i}": f"http://127.0.0.1:{8100 + i}" for i in range(8)}


def job(**overrides) -> JobSpec:
    fields = dict(job_id="j", tasks=tuple(TASKS), group_size=2, num_stages=2, pods_per_stage=2, stage_layout="slices")
    fields.update(overrides)
    return JobSpec(**fields)


def pods(*names: str, max_envs: int = 64) -> list[PodRecord]:
    return [PodRecord(pod=n, url=URLS[n], capacity=PodCapacity(max_envs=max_envs)) for n in names]


def stage_envs(p: Plan, pod: str) -> dict[int, list[int]]:
    """Env ids of ``pod`` per stage, as the routing table has them."""
    table = p.routing_table(URLS)
    return {
        stage.stage_id: [
            env
            for r in stage.pods
            if r.pod == pod
            for b in r.tasks
            for env in range(b.env_start, b.env_start + b.num_envs)
        ]
        for stage in table.stages
    }


# -- the plan -----------------------------------------------------------------------------------


def test_slices_needs_pods_per_stage_pods_in_all_each_holding_every_stage():
    p = plan(job(), pods("sim-0", "sim-1", "sim-2"), None, TASKS)
    assert job().pods_needed == 2
    assert {slot.key: slot.pod for slot in p.slots} == {(None, 0): "sim-0", (None, 1): "sim-1"}
    assert p.slot_of("sim-2") is None
    for name in ("sim-0", "sim-1"):
        assert sorted(stage_envs(p, name)) == [0, 1]
        assert all(stage_envs(p, name).values())


def test_pods_layout_needs_a_pod_per_stage_and_slot():
    assert job(stage_layout="pods").pods_needed == 4


def test_every_stage_runs_every_task_with_group_size_envs_in_slices():
    p = plan(job(num_stages=3, group_size=4), pods("sim-0", "sim-1"), None, TASKS)
    table = p.routing_table(URLS)
    for stage in table.stages:
        per_task: dict[str, int] = {}
        for routed in stage.pods:
            for block in routed.tasks:
                per_task[block.task_id] = per_task.get(block.task_id, 0) + block.num_envs
        assert per_task == {task: 4 for task in TASKS}


def test_a_tasks_envs_alternate_stages_so_every_run_of_consecutive_envs_holds_each_stage():
    p = plan(job(num_stages=3, group_size=2), pods("sim-0", "sim-1"), None, TASKS)
    a = p.assignments["sim-0"]
    stage_of_env = [a.stage_of_block(b) for b in a.tasks for _ in range(b.num_envs)]
    # A worker hosts consecutive envs: any 3 of them hold one env of each of the 3 stages.
    assert all(sorted(stage_of_env[i : i + 3]) == [0, 1, 2] for i in range(0, len(stage_of_env), 3))
    # One task stays in consecutive envs (its scene shared in a worker).
    tasks_in_order = [b.task_id for b in a.tasks]
    assert tasks_in_order == sorted(tasks_in_order)


def test_a_slices_assignment_has_no_stage_of_its_own_and_every_block_names_one():
    a = plan(job(), pods("sim-0", "sim-1"), None, TASKS).assignments["sim-1"]
    assert a.stage_id is None
    assert {b.stage_id for b in a.tasks} == {0, 1}
    assert a.num_envs == 2 * 2 * 2  # 2 tasks x group_size 2 x 2 stages
    with pytest.raises(ValidationError, match="stage_id"):
        type(a)(generation=1, pod="sim-1", stage_id=None, tasks=[{"task_id": "tiny/t0", "env_start": 0, "num_envs": 1}])


def test_one_stage_in_slices_gives_one_block_per_task():
    a = plan(job(num_stages=1, pods_per_stage=1), pods("sim-0"), None, TASKS).assignments["sim-0"]
    assert [(b.task_id, b.num_envs, b.stage_id) for b in a.tasks] == [(t, 2, 0) for t in TASKS]


def test_routing_table_of_slices_lists_every_pod_in_every_stage_with_disjoint_env_ids():
    p = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    table = p.routing_table(URLS, ready=True)
    assert [[r.pod for r in stage.pods] for stage in table.stages] == [["sim-0", "sim-1"], ["sim-0", "sim-1"]]
    stage_by_id(table)  # accepted: a pod in two stages, each env in one
    for name, slot in (("sim-0", p.slot_of("sim-0")), ("sim-1", p.slot_of("sim-1"))):
        envs = stage_envs(p, name)
        assert not set(envs[0]) & set(envs[1])
        assert sorted(envs[0] + envs[1]) == list(range(slot.num_envs))
    assert table.num_envs == len(TASKS) * 2 * 2


def test_zero_group_size_in_slices_gives_zero_env_stages_that_still_list_their_tasks():
    p = plan(job(group_size=0), pods("sim-0", "sim-1"), None, TASKS)
    table = p.routing_table(URLS)
    assert [stage.num_envs for stage in table.stages] == [0, 0]
    assert {b.task_id for stage in table.stages for r in stage.pods for b in r.tasks} == set(TASKS)
    assert place_requests(table, [], []) == {}


# -- pods coming and going ----------------------------------------------------------------------


def test_a_missing_slices_pod_leaves_its_slot_unfilled_and_a_spare_takes_it():
    first = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    gone = plan(job(), pods("sim-0"), first, TASKS)
    assert [s.key for s in gone.unfilled] == [(None, 1)] and gone.generation == first.generation + 1
    spare = plan(job(), pods("sim-0", "sim-5"), gone, TASKS)
    assert spare.slot_of("sim-5").key == (None, 1)
    assert spare.assignments["sim-5"].same_envs(first.assignments["sim-1"].model_copy(update={"pod": "sim-5"}))


def test_a_returning_slices_pod_gets_its_own_slot_back_and_its_stages_with_it():
    first = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    gone = plan(job(), pods("sim-0"), first, TASKS)
    back = plan(job(), pods("sim-0", "sim-1"), gone, TASKS)
    assert back.slot_of("sim-1").key == (None, 1)
    assert stage_envs(back, "sim-1") == stage_envs(first, "sim-1")


def test_replanning_slices_with_the_same_pods_keeps_the_generation():
    first = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    assert plan(job(), pods("sim-1", "sim-0"), first, TASKS).generation == first.generation


def test_switching_the_layout_moves_the_generation_and_rebuilds_the_slots():
    first = plan(job(stage_layout="pods"), pods("sim-0", "sim-1", "sim-2", "sim-3"), None, TASKS)
    switched = plan(job(), pods("sim-0", "sim-1", "sim-2", "sim-3"), first, TASKS)
    assert switched.generation == first.generation + 1
    assert [s.key for s in switched.slots] == [(None, 0), (None, 1)]


def test_adopting_what_slices_pods_report_rebuilds_the_same_plan():
    first = plan(job(), pods("sim-0", "sim-1", "sim-2"), None, TASKS)
    first = plan(job(), pods("sim-0", "sim-2"), first, TASKS)  # sim-2 takes slot 1
    adopted = adopt(job(), TASKS, dict(first.assignments))
    assert adopted is not None
    rebuilt = plan(job(), pods("sim-0", "sim-2"), adopted, TASKS)
    assert {s.key: s.pod for s in rebuilt.slots} == {(None, 0): "sim-0", (None, 1): "sim-2"}
    assert rebuilt.generation == first.generation


# -- validation ---------------------------------------------------------------------------------


def test_validate_counts_every_stage_of_a_slices_slot_against_capacity():
    problems = validate_job(job(), TASKS, pods("sim-0", max_envs=8))
    # 3 tasks x group_size 2 x 2 stages = 12 envs on the first slot.
    assert len(problems) == 1 and "needs 12" in problems[0] and "stage_layout 'slices'" in problems[0]
    assert validate_job(job(), TASKS, pods("sim-0", max_envs=12)) == []


def test_an_unknown_layout_is_refused_naming_the_field():
    with pytest.raises(ValidationError, match="stage_layout"):
        job(stage_layout="rows")


def test_a_config_file_with_an_unknown_layout_names_the_file_and_the_field(tmp_path: Path):
    path = tmp_path / "job.yaml"
    path.write_text("job:\n  tasks: [tiny/lift]\n  stage_layout: stages\n")
    with pytest.raises(ConfigError, match=r"job\.stage_layout"):
        load_job_config(path)


# -- the client's routing over a slices table ---------------------------------------------------


def slices_table():
    return plan(job(), pods("sim-0", "sim-1"), None, TASKS).routing_table(URLS, ready=True)


def test_requests_of_a_stage_go_only_to_that_stages_env_ids():
    table = slices_table()
    requests = [(task, i) for i in range(2) for task in TASKS for _ in range(2)]  # 2 per task per stage
    routes = place_requests(table, requests, [str(i) for i in range(len(requests))])
    mine = {(e.stage_id, e.pod, e.env_index) for e in routed_envs(table)}
    assert all((r.stage_id, r.pod, r.env_index) in mine for r in routes.values())
    assert len({(r.pod, r.env_index) for r in routes.values()}) == len(routes)
    validate_routes(table, routes)


def test_a_route_onto_another_stages_env_is_refused():
    table = slices_table()
    env_of_stage_1 = next(e for e in routed_envs(table) if e.stage_id == 1)
    wrong = {"k": TrajRoute(env_of_stage_1.pod, env_of_stage_1.env_index, env_of_stage_1.task_id, 0, 0)}
    with pytest.raises(ValueError, match="is not one of stage 0's envs"):
        validate_routes(table, wrong)


def test_a_table_putting_one_env_in_two_stages_is_refused():
    table = slices_table()
    stage0 = table.stages[0]
    clash = table.model_copy(update={"stages": (stage0, stage0.model_copy(update={"stage_id": 1}))})
    with pytest.raises(ValueError, match="in stages 0 and 1"):
        stage_by_id(clash)


def test_a_pod_that_left_a_slices_table_loses_its_trajectories_of_every_stage():
    first = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    table = first.routing_table(URLS, ready=True)
    requests = [(task, 0) for _ in range(2) for task in TASKS]
    book = RouteBook(table)
    routes = book.place(requests, [str(i) for i in range(len(requests))])
    book.replace(routes)
    lost = book.take_table(plan(job(), pods("sim-0"), first, TASKS).routing_table(URLS))
    assert sorted(lost) == sorted(k for k, r in routes.items() if r.pod == "sim-1")
    assert {routes[k].stage_id for k in lost} == {0, 1}
    assert book.routes() == {k: r for k, r in routes.items() if r.pod == "sim-0"}


def test_unchanged_slices_table_moves_no_trajectory():
    table = slices_table()
    requests = [(task, 0) for _ in range(2) for task in TASKS]
    routes = place_requests(table, requests, [str(i) for i in range(len(requests))])
    assert changed_routes(table, table.model_copy(update={"generation": 9}), routes) == []


def test_standalone_slices_pods_make_the_same_table_from_their_infos():
    p = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    table = p.routing_table(URLS)
    infos = []
    for name in ("sim-0", "sim-1"):
        a = p.assignments[name]
        tasks = [
            dict(task_id=b.task_id, env_start=b.env_start, num_envs=b.num_envs, stage_id=b.stage_id) for b in a.tasks
        ]
        infos.append(
            (URLS[name], dict(pod=name, stage_id=None, generation=1, ready=True, num_envs=a.num_envs, tasks=tasks))
        )
    rebuilt = routing_from_pod_infos(infos)
    assert rebuilt.stages == table.stages
