"""TaskBalancedSampler and stage_of: the batch rules the client and the rollout rely on."""

from __future__ import annotations

from collections import Counter

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from torch.utils.data import DataLoader

from vecsim.config import JobSpec
from vecsim.rollout.sampler import TaskBalancedSampler, TaskInstances, stage_of, task_ids_of


@st.composite
def sampler_cases(draw):
    """A dataset of task ids plus sampler arguments that the constructor accepts."""
    num_tasks = draw(st.integers(1, 6))
    sizes = draw(st.lists(st.integers(0, 12), min_size=num_tasks, max_size=num_tasks))
    dataset = [f"task{t}" for t, n in enumerate(sizes) for _ in range(n)]
    order = draw(st.permutations(range(len(dataset))))
    dataset = [dataset[k] for k in order]
    present = max(1, len(set(dataset)))
    num_stages = draw(st.integers(1, 3))
    group_size = draw(st.integers(1, 4))
    per_stage = draw(st.integers(1, group_size * present))
    return dict(
        dataset_task_ids=dataset,
        batch_size=per_stage * num_stages,
        group_size=group_size,
        num_stages=num_stages,
        seed=draw(st.integers(0, 2**31)),
    )


def _stage_task_counts(batch: list[int], task_ids: list[str], num_stages: int) -> Counter:
    return Counter((stage_of(i, num_stages), task_ids[index]) for i, index in enumerate(batch))


def test_stage_of_is_index_modulo_num_stages():
    assert [stage_of(i, 3) for i in range(7)] == [0, 1, 2, 0, 1, 2, 0]


@pytest.mark.parametrize("i, num_stages", [(0, 0), (-1, 2)])
def test_stage_of_rejects_bad_arguments(i, num_stages):
    with pytest.raises(ValueError):
        stage_of(i, num_stages)


@settings(max_examples=150, deadline=None)
@given(sampler_cases())
def test_no_stage_holds_more_than_group_size_of_one_task(case):
    sampler = TaskBalancedSampler(**case)
    for batch in sampler:
        counts = _stage_task_counts(batch, case["dataset_task_ids"], case["num_stages"])
        assert max(counts.values()) <= case["group_size"]


@settings(max_examples=150, deadline=None)
@given(sampler_cases())
def test_an_epoch_without_drop_last_visits_every_index_exactly_once(case):
    sampler = TaskBalancedSampler(**case, drop_last=False)
    seen = [index for batch in sampler for index in batch]
    assert sorted(seen) == list(range(len(case["dataset_task_ids"])))


@settings(max_examples=150, deadline=None)
@given(sampler_cases())
def test_full_batches_give_every_stage_the_same_number_of_requests(case):
    sampler = TaskBalancedSampler(**case)
    for batch in sampler:
        assert 0 < len(batch) <= case["batch_size"]
        per_stage = Counter(stage_of(i, case["num_stages"]) for i in range(len(batch)))
        # Request i is on stage i % S, so stage sizes differ by at most one, and not at all when full.
        assert max(per_stage.values()) - min(per_stage.values()) <= (0 if len(batch) == case["batch_size"] else 1)


@settings(max_examples=100, deadline=None)
@given(sampler_cases())
def test_drop_last_yields_only_full_batches(case):
    if 0 < len(case["dataset_task_ids"]) < case["batch_size"]:
        return
    sampler = TaskBalancedSampler(**case, drop_last=True)
    assert all(len(batch) == case["batch_size"] for batch in sampler)


@settings(max_examples=100, deadline=None)
@given(sampler_cases())
def test_same_seed_and_epoch_give_the_same_batches(case):
    first = TaskBalancedSampler(**case)
    second = TaskBalancedSampler(**case)
    first.set_epoch(3)
    second.set_epoch(3)
    assert list(first) == list(second)
    assert len(first) == len(list(first))


def test_epochs_reorder_the_batches():
    dataset = [f"task{t}" for t in range(4) for _ in range(10)]
    sampler = TaskBalancedSampler(dataset, batch_size=8, group_size=2, num_stages=2, seed=7)
    orders = []
    for epoch in range(3):
        sampler.set_epoch(epoch)
        orders.append(list(sampler))
    assert orders[0] != orders[1] != orders[2]


def test_batches_mix_tasks_evenly_when_the_data_allows():
    dataset = [f"task{t}" for t in range(4) for _ in range(8)]
    sampler = TaskBalancedSampler(dataset, batch_size=8, group_size=4, num_stages=2, seed=0)
    for batch in sampler:
        counts = _stage_task_counts(batch, dataset, 2)
        assert sorted(counts.values()) == [1] * 8


def test_batch_size_not_divisible_by_num_stages_says_what_to_change():
    with pytest.raises(ValueError, match=r"batch_size=5 is not divisible by num_stages=2.*4 or 6"):
        TaskBalancedSampler(["a"] * 10, batch_size=5, group_size=4, num_stages=2)


def test_too_few_tasks_to_fill_a_stage_is_an_error_naming_the_limits():
    with pytest.raises(ValueError, match=r"needs batch_size/num_stages = 4.*group_size=1 x 2 task"):
        TaskBalancedSampler(["a", "b"] * 10, batch_size=8, group_size=1, num_stages=2)


@pytest.mark.parametrize(
    "field, kwargs",
    [
        ("batch_size", dict(batch_size=0, group_size=1)),
        ("group_size", dict(batch_size=2, group_size=0)),
        ("num_stages", dict(batch_size=2, group_size=1, num_stages=0)),
    ],
)
def test_non_positive_sizes_are_errors_naming_the_field(field, kwargs):
    with pytest.raises(ValueError, match=field):
        TaskBalancedSampler(["a", "b"], **kwargs)


def test_dataset_smaller_than_a_batch_gives_one_smaller_batch():
    dataset = ["a", "b", "a"]
    batches = list(TaskBalancedSampler(dataset, batch_size=8, group_size=2, num_stages=2))
    assert len(batches) == 1
    assert sorted(batches[0]) == [0, 1, 2]


def test_dataset_smaller_than_a_batch_with_drop_last_is_an_error():
    with pytest.raises(ValueError, match="drop_last=True with 3 dataset items"):
        TaskBalancedSampler(["a", "b", "a"], batch_size=8, group_size=4, num_stages=2, drop_last=True)


def test_empty_dataset_gives_no_batches():
    sampler = TaskBalancedSampler([], batch_size=4, group_size=1, num_stages=2)
    assert len(sampler) == 0
    assert list(sampler) == []


def test_works_as_a_dataloader_batch_sampler():
    dataset = TaskInstances.from_tasks(["tiny/lift", "tiny/stack"], num_states=4)
    sampler = TaskBalancedSampler(dataset, batch_size=4, group_size=1, num_stages=2, seed=1)
    loader = DataLoader(dataset, batch_sampler=sampler, collate_fn=list)
    batches = list(loader)
    assert len(batches) == 2
    assert sorted(req for batch in batches for req in batch) == sorted(dataset.requests)
    for batch in batches:
        assert {task for task, _ in batch[0::2]} == {"tiny/lift", "tiny/stack"}


def test_for_job_takes_group_size_and_num_stages_from_the_job():
    job = JobSpec(tasks=("tiny/lift", "tiny/stack"), group_size=3, num_stages=2)
    dataset = TaskInstances.from_tasks(job.tasks, num_states=6)
    sampler = TaskBalancedSampler.for_job(dataset, job, batch_size=12)
    assert (sampler.group_size, sampler.num_stages, sampler.per_stage) == (3, 2, 6)


@pytest.mark.parametrize(
    "dataset",
    [
        ["x", "y"],
        [("x", 0), ("y", 5)],
        [{"task_id": "x", "state_id": 0}, {"task_id": "y", "state_id": 1}],
        TaskInstances((("x", 0), ("y", 1))),
    ],
)
def test_task_ids_are_read_from_every_supported_dataset_shape(dataset):
    assert task_ids_of(dataset) == ["x", "y"]


def test_item_without_a_task_id_is_an_error_naming_its_index():
    with pytest.raises(TypeError, match="dataset item 1"):
        task_ids_of(["x", 3])
