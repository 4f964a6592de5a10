"""Task-balanced, stage-interleaved batches of trajectory requests.

A batch of B requests is split over S pipeline stages: request ``i`` belongs to stage
``stage_of(i, S)``, and each stage may hold at most ``group_size`` requests of one task (the
job's ``group_size`` is how many envs each task has on each stage, so a sampler with the job's
``group_size`` or less guarantees every request a free env of its task on its stage). :class:`TaskBalancedSampler` draws such batches of dataset indices and is usable as a
``torch.utils.data.DataLoader`` ``batch_sampler``.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from torch.utils.data import Sampler

from vecsim.config import JobSpec
from vecsim.plan import stage_of

logger = logging.getLogger(__name__)

__all__ = ["TaskBalancedSampler", "TaskInstances", "stage_of", "task_ids_of"]


@dataclass(frozen=True)
class TaskInstances(Sequence[tuple[str, int]]):
    """A dataset of task instances: item ``k`` is the request ``(task_id, state_id)``.

    ``task_ids`` is exposed so that :class:`TaskBalancedSampler` reads the tasks without loading
    items.
    """

    requests: tuple[tuple[str, int], ...]

    @classmethod
    def from_tasks(cls, task_ids: Sequence[str], num_states: int | Mapping[str, int]) -> TaskInstances:
        """Return every ``(task_id, state_id)`` with ``state_id < num_states`` (per task if a mapping).

        Raises:
            ValueError: a negative number of states.
        """
        requests = []
        for task_id in task_ids:
            n = num_states[task_id] if isinstance(num_states, Mapping) else num_states
            if n < 0:
                raise ValueError(f"num_states for task {task_id!r} must be >= 0, got {n}")
            requests.extend((task_id, k) for k in range(n))
        return cls(tuple(requests))

    @property
    def task_ids(self) -> list[str]:
        return [task_id for task_id, _ in self.requests]

    def __len__(self) -> int:
        return len(self.requests)

    def __getitem__(self, index):  # type: ignore[override]
        return self.requests[index]


def task_ids_of(dataset: Sequence[str] | Any) -> list[str]:
    """Return the task id of every item of ``dataset``, in index order.

    ``dataset`` is a sequence of task ids, an object with a ``task_ids`` sequence, or a sequence of
    items that are ``(task_id, state_id)`` pairs, mappings with a ``"task_id"`` key or objects
    with a ``task_id`` attribute.

    Raises:
        TypeError: an item whose task id cannot be found (the message names its index).
    """
    if hasattr(dataset, "task_ids"):
        return [str(t) for t in dataset.task_ids]
    ids = []
    for index in range(len(dataset)):
        item = dataset[index]
        if isinstance(item, str):
            ids.append(item)
        elif isinstance(item, Mapping) and "task_id" in item:
            ids.append(str(item["task_id"]))
        elif isinstance(item, (tuple, list)) and item and isinstance(item[0], str):
            ids.append(item[0])
        elif hasattr(item, "task_id"):
            ids.append(str(item.task_id))
        else:
            raise TypeError(
                f"dataset item {index} ({type(item).__name__}) has no task id: expected a str, a "
                "(task_id, state_id) pair, a mapping with 'task_id' or an object with .task_id"
            )
    return ids


class TaskBalancedSampler(Sampler[list[int]]):
    """Batches of dataset indices, balanced over tasks and interleaved over pipeline stages.

    Each full batch holds ``batch_size`` indices; index ``i`` of a batch belongs to stage
    ``stage_of(i, num_stages)``, each stage gets ``batch_size // num_stages`` of them, and no stage
    holds more than ``group_size`` of one task. Batches mix tasks as evenly as the data
    allows: a stage takes a second request of a task only once every task with items left has
    one there, and among those prefers the tasks with the most items left (ties broken at
    random). An epoch visits every index at most once; the order is a pure function of
    ``(seed, epoch)`` (see :meth:`set_epoch`).

    End of an epoch and small datasets: when the items left cannot fill a whole batch (too few
    items, or too few distinct tasks under ``group_size``), ``drop_last=True`` ends the epoch
    and ``drop_last=False`` yields the rest as smaller batches that keep the same rules (request
    ``i`` on stage ``i % num_stages``, at most ``group_size`` of a task per stage). A dataset
    smaller than one batch therefore gives one smaller batch with ``drop_last=False`` and is an
    error with ``drop_last=True``. An empty dataset gives no batches.
    """

    def __init__(
        self,
        dataset_task_ids: Sequence[str] | Any,
        batch_size: int,
        group_size: int,
        num_stages: int = 1,
        seed: int = 0,
        drop_last: bool = False,
    ) -> None:
        """Build the sampler; see the class docstring for what it yields.

        Raises:
            ValueError: a non-positive size, ``batch_size`` not a multiple of ``num_stages``,
                ``group_size`` times the number of tasks too small to fill a stage, or
                ``drop_last=True`` with a dataset smaller than one batch. The message says what
                to change.
            TypeError: a dataset item without a task id.
        """
        for name, value in (("batch_size", batch_size), ("group_size", group_size), ("num_stages", num_stages)):
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        if batch_size % num_stages != 0:
            lower = batch_size - batch_size % num_stages
            upper = lower + num_stages
            hint = f"{lower} or {upper}" if lower > 0 else f"{upper}"
            raise ValueError(
                f"batch_size={batch_size} is not divisible by num_stages={num_stages}: every stage "
                f"must get the same number of requests; use batch_size={hint} or change num_stages"
            )
        self.task_ids = task_ids_of(dataset_task_ids)
        self.batch_size = int(batch_size)
        self.group_size = int(group_size)
        self.num_stages = int(num_stages)
        self.per_stage = self.batch_size // self.num_stages
        self.seed = int(seed)
        self.drop_last = bool(drop_last)
        self.epoch = 0

        # Tasks in first-seen order; items of each task by dataset index.
        self.tasks = list(dict.fromkeys(self.task_ids))
        task_index = {t: k for k, t in enumerate(self.tasks)}
        self._items_by_task: list[list[int]] = [[] for _ in self.tasks]
        for index, task_id in enumerate(self.task_ids):
            self._items_by_task[task_index[task_id]].append(index)

        if self.tasks and self.group_size * len(self.tasks) < self.per_stage:
            raise ValueError(
                f"cannot fill a stage: each stage needs batch_size/num_stages = {self.per_stage} "
                f"requests, but group_size={self.group_size} x {len(self.tasks)} task(s) allows "
                f"at most {self.group_size * len(self.tasks)}; raise group_size (keep it <= the "
                "job's group_size), add tasks, lower batch_size or raise num_stages"
            )
        if self.drop_last and 0 < len(self.task_ids) < self.batch_size:
            raise ValueError(
                f"drop_last=True with {len(self.task_ids)} dataset items and batch_size="
                f"{self.batch_size}: no batch would ever be drawn; lower batch_size or use "
                "drop_last=False (one smaller batch)"
            )
        self._plan_cache: tuple[int, list[list[int]]] | None = None

    @classmethod
    def for_job(
        cls, dataset: Sequence[str] | Any, job: JobSpec, batch_size: int, seed: int = 0, drop_last: bool = False
    ) -> TaskBalancedSampler:
        """Return a sampler whose limits fit ``job``: the job's ``group_size`` and ``num_stages``.

        Raises:
            ValueError: as the constructor.
        """
        return cls(
            dataset, batch_size, group_size=job.group_size, num_stages=job.num_stages, seed=seed, drop_last=drop_last
        )

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch whose order the next iteration yields (like ``DistributedSampler``)."""
        self.epoch = int(epoch)

    def __iter__(self) -> Iterator[list[int]]:
        yield from (list(batch) for batch in self._plan())

    def __len__(self) -> int:
        return len(self._plan())

    def _plan(self) -> list[list[int]]:
        if self._plan_cache is None or self._plan_cache[0] != self.epoch:
            self._plan_cache = (self.epoch, self._draw_epoch(self.epoch))
        return self._plan_cache[1]

    def _draw_epoch(self, epoch: int) -> list[list[int]]:
        rng = np.random.default_rng([self.seed, epoch])
        pools = [list(rng.permutation(items)) for items in self._items_by_task]
        remaining = np.array([len(p) for p in pools], dtype=np.int64)
        batches: list[list[int]] = []
        while remaining.sum() > 0:
            batch = self._draw_batch(rng, pools, remaining)
            if len(batch) < self.batch_size and self.drop_last:
                break
            batches.append(batch)
        return batches

    def _draw_batch(self, rng: np.random.Generator, pools: list[list[int]], remaining: np.ndarray) -> list[int]:
        """Fill one batch request by request; stop at the first request whose stage can take no task."""
        num_tasks = len(pools)
        priority = rng.permutation(num_tasks)
        taken = np.zeros((self.num_stages, num_tasks), dtype=np.int64)
        batch: list[int] = []
        for i in range(self.batch_size):
            stage = stage_of(i, self.num_stages)
            allowed = (remaining > 0) & (taken[stage] < self.group_size)
            if not allowed.any():
                break
            # Fewest of this task on this stage first spreads tasks over the stage; then most items
            # left first keeps the pools even, so later batches stay fillable.
            span = (int(remaining.max()) + 1) * num_tasks
            score = np.where(allowed, (self.group_size - taken[stage]) * span + remaining * num_tasks + priority, -1)
            task = int(np.argmax(score))
            batch.append(int(pools[task].pop()))
            remaining[task] -= 1
            taken[stage, task] += 1
        return batch
