"""vecsim.plan: slots, task ranges, stable holders, generations, adoption and validation."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vecsim.config import Assignment, CameraConfig, JobSpec, PodCapacity, PodRecord
from vecsim.plan import Plan, adopt, plan, pod_sort_key, slot_contents, split_tasks, validate_job

TASKS = [f"tiny/t{i}" for i in range(10)]


def job(**overrides) -> JobSpec:
    fields = dict(job_id="j", tasks=tuple(TASKS), group_size=2, num_stages=2, pods_per_stage=1)
    fields.update(overrides)
    return JobSpec(**fields)


def pods(*names: str, max_envs: int = 64) -> list[PodRecord]:
    return [PodRecord(pod=n, url=f"http://{n}:8100", capacity=PodCapacity(max_envs=max_envs)) for n in names]


def holders(p: Plan) -> dict[tuple[int, int], str | None]:
    return {slot.key: slot.pod for slot in p.slots}


@pytest.mark.parametrize(
    ("n", "parts", "sizes"),
    [(10, 3, [4, 3, 3]), (3, 3, [1, 1, 1]), (2, 3, [1, 1, 0]), (0, 2, [0, 0]), (7, 1, [7]), (11, 4, [3, 3, 3, 2])],
)
def test_split_tasks_gives_contiguous_ranges_with_remainders_first(n, parts, sizes):
    tasks = [str(i) for i in range(n)]
    ranges = split_tasks(tasks, parts)
    assert [len(r) for r in ranges] == sizes
    assert [t for r in ranges for t in r] == tasks


def test_split_tasks_rejects_zero_parts():
    with pytest.raises(ValueError, match="pods_per_stage"):
        split_tasks(["a"], 0)


def test_pod_names_order_by_ordinal_not_by_text():
    assert sorted(["sim-10", "sim-2", "sim-0", "sim-1"], key=pod_sort_key) == ["sim-0", "sim-1", "sim-2", "sim-10"]


def test_first_plan_fills_slots_stage_major_in_ordinal_order():
    p = plan(job(pods_per_stage=2), pods("sim-3", "sim-10", "sim-0", "sim-1"), None, TASKS)
    assert p.generation == 1
    assert holders(p) == {(0, 0): "sim-0", (0, 1): "sim-1", (1, 0): "sim-3", (1, 1): "sim-10"}


def test_every_stage_runs_every_task_with_group_size_envs():
    p = plan(job(num_stages=3, pods_per_stage=3, group_size=4), pods(*[f"sim-{i}" for i in range(9)]), None, TASKS)
    for stage_id in range(3):
        blocks = [b for s in p.slots if s.stage_id == stage_id for b in s.tasks]
        assert [b.task_id for b in blocks] == TASKS
        assert all(b.num_envs == 4 for b in blocks)
    assert [s.num_envs for s in p.slots if s.stage_id == 0] == [16, 12, 12]


def test_assignment_carries_the_jobs_settings_and_contiguous_blocks():
    spec = job(
        camera=CameraConfig(names=("agentview",), height=32, width=32), render="fast", seed=7, max_episode_steps=50
    )
    p = plan(spec, pods("sim-0", "sim-1"), None, TASKS[:3])
    a = p.assignments["sim-1"]
    assert (a.generation, a.job_id, a.pod, a.stage_id) == (1, "j", "sim-1", 1)
    assert [(b.task_id, b.env_start, b.num_envs) for b in a.tasks] == [
        ("tiny/t0", 0, 2),
        ("tiny/t1", 2, 2),
        ("tiny/t2", 4, 2),
    ]
    assert (a.camera, a.render, a.seed, a.max_episode_steps) == (spec.camera, "fast", 7, 50)


def test_more_slots_than_tasks_leaves_spare_slots_with_zero_envs():
    p = plan(job(pods_per_stage=3), pods(*[f"sim-{i}" for i in range(6)]), None, TASKS[:2])
    assert [s.task_ids for s in p.slots if s.stage_id == 1] == [("tiny/t0",), ("tiny/t1",), ()]
    assert p.assignments["sim-2"].tasks == () and p.assignments["sim-2"].num_envs == 0


def test_zero_group_size_gives_a_valid_plan_with_zero_envs():
    p = plan(job(group_size=0), pods("sim-0", "sim-1"), None, TASKS)
    assert [s.num_envs for s in p.slots] == [0, 0]
    assert [b.task_id for b in p.assignments["sim-0"].tasks] == TASKS


def test_pods_beyond_the_slots_hold_nothing():
    p = plan(job(), pods("sim-0", "sim-1", "sim-2"), None, TASKS)
    assert p.slot_of("sim-2") is None
    assert set(p.pods) == {"sim-0", "sim-1"}


def test_too_few_pods_leaves_slots_unfilled():
    p = plan(job(), pods("sim-0"), None, TASKS)
    assert [s.key for s in p.unfilled] == [(1, 0)]


def test_replanning_the_same_inputs_keeps_the_generation():
    first = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    again = plan(job(), pods("sim-0", "sim-1"), first, TASKS)
    assert again == first


def test_holders_stay_when_pods_arrive_in_another_order():
    first = plan(job(), pods("sim-1"), None, TASKS)
    second = plan(job(), pods("sim-0", "sim-1"), first, TASKS)
    assert holders(second) == {(0, 0): "sim-1", (1, 0): "sim-0"}


def test_a_missing_pod_leaves_its_slot_unfilled_and_moves_the_generation():
    first = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    gone = plan(job(), pods("sim-0"), first, TASKS)
    assert holders(gone) == {(0, 0): "sim-0", (1, 0): None}
    assert gone.generation == first.generation + 1


def test_a_returning_pod_gets_its_own_slot_back():
    first = plan(job(pods_per_stage=2), pods("sim-0", "sim-1", "sim-2", "sim-3"), None, TASKS)
    gone = plan(job(pods_per_stage=2), pods("sim-0", "sim-2", "sim-3"), first, TASKS)
    back = plan(job(pods_per_stage=2), pods("sim-0", "sim-1", "sim-2", "sim-3"), gone, TASKS)
    assert holders(back) == holders(first)
    assert back.generation == gone.generation + 1


def test_a_spare_pod_takes_a_missing_pods_slot():
    first = plan(job(), pods("sim-0", "sim-1", "sim-2"), None, TASKS)
    moved = plan(job(), pods("sim-0", "sim-2"), first, TASKS)
    assert holders(moved) == {(0, 0): "sim-0", (1, 0): "sim-2"}
    assert moved.generation == first.generation + 1


def test_the_spare_keeps_the_slot_when_the_old_pod_returns():
    first = plan(job(), pods("sim-0", "sim-1", "sim-2"), None, TASKS)
    moved = plan(job(), pods("sim-0", "sim-2"), first, TASKS)
    back = plan(job(), pods("sim-0", "sim-1", "sim-2"), moved, TASKS)
    assert holders(back) == holders(moved)
    assert back.generation == moved.generation


def test_a_restarted_holder_keeps_its_slot_and_moves_the_generation():
    first = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    again = plan(job(), pods("sim-0", "sim-1"), first, TASKS, restarted={"sim-1"})
    assert holders(again) == holders(first)
    assert again.generation == first.generation + 1


def test_a_restarted_spare_does_not_move_the_generation():
    first = plan(job(), pods("sim-0", "sim-1", "sim-2"), None, TASKS)
    assert (
        plan(job(), pods("sim-0", "sim-1", "sim-2"), first, TASKS, restarted={"sim-2"}).generation == first.generation
    )


@pytest.mark.parametrize(
    "change", [dict(group_size=3), dict(seed=1), dict(render="full"), dict(tasks=tuple(TASKS[:4])), dict(job_id="k")]
)
def test_a_job_change_keeps_holders_and_moves_the_generation(change):
    first = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    spec = job(**change)
    changed = plan(spec, pods("sim-0", "sim-1"), first, list(spec.tasks))
    assert holders(changed) == holders(first)
    assert changed.generation == first.generation + 1


def test_growing_a_stage_gives_new_slots_to_spares_and_keeps_old_holders():
    first = plan(job(), pods("sim-0", "sim-1", "sim-2", "sim-3"), None, TASKS)
    grown = plan(job(pods_per_stage=2), pods("sim-0", "sim-1", "sim-2", "sim-3"), first, TASKS)
    assert holders(grown) == {(0, 0): "sim-0", (0, 1): "sim-2", (1, 0): "sim-1", (1, 1): "sim-3"}


def test_a_pod_too_small_for_a_slot_is_not_given_one():
    small = pods("sim-0", max_envs=4)
    p = plan(job(group_size=2), small + pods("sim-1", "sim-2"), None, TASKS)
    assert p.slot_of("sim-0") is None
    assert holders(p) == {(0, 0): "sim-1", (1, 0): "sim-2"}


def test_routing_table_lists_each_stages_pods_with_urls_and_envs():
    p = plan(job(pods_per_stage=2), pods("sim-0", "sim-1", "sim-2"), None, TASKS[:3])
    table = p.routing_table({f"sim-{i}": f"http://10.0.0.{i}:8100" for i in range(3)}, ready=True)
    assert (table.generation, table.job_id, table.ready) == (1, "j", True)
    assert [[(r.pod, r.url, r.num_envs) for r in s.pods] for s in table.stages] == [
        [("sim-0", "http://10.0.0.0:8100", 4), ("sim-1", "http://10.0.0.1:8100", 2)],
        [("sim-2", "http://10.0.0.2:8100", 4)],
    ]
    assert table.num_envs == 10


def test_routing_table_without_a_pods_url_names_the_pod():
    p = plan(job(), pods("sim-0", "sim-1"), None, TASKS)
    with pytest.raises(KeyError, match="sim-1"):
        p.routing_table({"sim-0": "http://a"})


def test_adopting_what_pods_report_rebuilds_the_same_plan():
    first = plan(job(pods_per_stage=2), pods("sim-0", "sim-1", "sim-2", "sim-3"), None, TASKS)
    first = plan(job(pods_per_stage=2), pods("sim-1", "sim-2", "sim-3"), first, TASKS)
    first = plan(job(pods_per_stage=2), pods("sim-0", "sim-1", "sim-2", "sim-3"), first, TASKS)
    reports = dict(first.assignments)
    adopted = adopt(job(pods_per_stage=2), TASKS, reports)
    assert adopted is not None and adopted.generation == first.generation
    rebuilt = plan(job(pods_per_stage=2), pods("sim-0", "sim-1", "sim-2", "sim-3"), adopted, TASKS)
    assert (holders(rebuilt), rebuilt.generation) == (holders(first), first.generation)


def test_adopting_keeps_a_layout_that_is_not_in_ordinal_order():
    swapped = {
        "sim-0": Assignment(
            generation=4, job_id="j", pod="sim-0", stage_id=1, tasks=slot_contents(job(), TASKS)[1].tasks
        ),
        "sim-1": Assignment(
            generation=4, job_id="j", pod="sim-1", stage_id=0, tasks=slot_contents(job(), TASKS)[0].tasks
        ),
    }
    rebuilt = plan(job(), pods("sim-0", "sim-1"), adopt(job(), TASKS, swapped), TASKS)
    assert holders(rebuilt) == {(0, 0): "sim-1", (1, 0): "sim-0"}
    assert rebuilt.generation == 4


def test_adopting_with_no_reports_gives_nothing():
    assert adopt(job(), TASKS, {"sim-0": None}) is None


def test_adopting_a_stale_layout_starts_above_the_newest_reported_generation():
    other = Assignment(generation=9, job_id="old-job", pod="sim-0", stage_id=0)
    adopted = adopt(job(), TASKS, {"sim-0": other, "sim-1": None})
    assert adopted is not None and adopted.unfilled == adopted.slots
    assert plan(job(), pods("sim-0", "sim-1"), adopted, TASKS).generation == 10


def test_adopting_gives_a_slot_claimed_twice_to_the_newer_generation():
    content = slot_contents(job(), TASKS)[0].tasks
    reports = {
        "sim-0": Assignment(generation=2, job_id="j", pod="sim-0", stage_id=0, tasks=content),
        "sim-1": Assignment(generation=3, job_id="j", pod="sim-1", stage_id=0, tasks=content),
    }
    adopted = adopt(job(), TASKS, reports)
    assert adopted is not None and holders(adopted) == {(0, 0): "sim-1", (1, 0): None}


def test_validate_accepts_a_job_that_fits():
    assert validate_job(job(pods_per_stage=4), TASKS, pods("sim-0", max_envs=6)) == []


def test_validate_accepts_more_slots_than_tasks():
    assert validate_job(job(pods_per_stage=5), TASKS[:2], pods("sim-0")) == []


def test_validate_names_a_pod_without_capacity_and_what_to_change():
    problems = validate_job(job(group_size=4, pods_per_stage=3), TASKS, pods("sim-0", max_envs=8))
    assert len(problems) == 1
    assert "sim-0" in problems[0] and "16" in problems[0] and "pods_per_stage" in problems[0]


def test_validate_names_unknown_tasks():
    problems = validate_job(job(), ["tiny/t0", "nope/x"], [], known_tasks={"tiny/t0"})
    assert problems == ["tasks: unknown task 'nope/x'; use a task id of a known suite (e.g. 'tiny/lift')"]


def test_validate_rejects_a_job_without_tasks():
    problems = validate_job(JobSpec(suite="empty"), [], [])
    assert len(problems) == 1 and "suite 'empty' has no tasks" in problems[0]


def test_validate_rejects_a_task_listed_twice_after_resolution():
    assert any("more than once" in p for p in validate_job(job(), ["gym/X", "gym/X"], []))


# Properties over random jobs and pod sets.

jobs = st.builds(
    lambda n, stages, per_stage, group: (
        JobSpec(job_id="p", suite="s", group_size=group, num_stages=stages, pods_per_stage=per_stage),
        [f"s/{i}" for i in range(n)],
    ),
    st.integers(0, 12),
    st.integers(1, 3),
    st.integers(1, 4),
    st.integers(0, 3),
)
pod_sets = st.sets(st.integers(0, 15), max_size=14).map(lambda ids: pods(*[f"sim-{i}" for i in ids]))


@settings(max_examples=200, deadline=None)
@given(jobs, pod_sets)
def test_every_stage_with_all_slots_filled_runs_every_task_exactly_once(job_and_tasks, live):
    spec, tasks = job_and_tasks
    p = plan(spec, live, None, tasks)
    for stage_id in range(spec.num_stages):
        stage = [s for s in p.slots if s.stage_id == stage_id]
        assert [t for s in stage for t in s.task_ids] == tasks
        sizes = [len(s.tasks) for s in stage]
        assert max(sizes) - min(sizes) <= 1 and sizes == sorted(sizes, reverse=True)


@settings(max_examples=200, deadline=None)
@given(jobs, pod_sets)
def test_env_ranges_of_each_pod_are_disjoint_and_cover_its_envs(job_and_tasks, live):
    spec, tasks = job_and_tasks
    for a in plan(spec, live, None, tasks).assignments.values():
        covered = [i for b in a.tasks for i in range(b.env_start, b.env_start + b.num_envs)]
        assert covered == list(range(a.num_envs))


@settings(max_examples=200, deadline=None)
@given(jobs, pod_sets)
def test_each_pod_holds_at_most_one_slot_and_slots_fill_while_pods_last(job_and_tasks, live):
    spec, tasks = job_and_tasks
    p = plan(spec, live, None, tasks)
    held = [s.pod for s in p.slots if s.pod is not None]
    assert len(held) == len(set(held)) == min(len(live), spec.pods_needed)


@settings(max_examples=200, deadline=None)
@given(jobs, pod_sets, st.data())
def test_replanning_keeps_every_live_holder_and_the_generation_only_when_nothing_changed(job_and_tasks, live, data):
    spec, tasks = job_and_tasks
    first = plan(spec, live, None, tasks)
    assert plan(spec, live, first, tasks) == first
    survivors = data.draw(st.lists(st.sampled_from(live), unique=True) if live else st.just([]))
    second = plan(spec, survivors, first, tasks)
    alive = {record.pod for record in survivors}
    for before, after in zip(first.slots, second.slots):
        if before.pod in alive:
            assert after.pod == before.pod
    moved = holders(second) != holders(first)
    assert second.generation == first.generation + (1 if moved else 0)
