"""The trainers' numbering and naming conventions, as pure functions (no I/O).

VLA-RL trainers name a job's things their own way: a LIBERO task by its int index in the suite
(``"libero_spatial/3"`` is task 3), an initial state by one suite-global id (RLinf and verl-vla
count task 0's states first, then task 1's: ``task * 50 + row`` for LIBERO's 50 states a task),
and the cameras by their policy's input keys. This module maps vecsim's names to theirs::

    suite_task_index("libero_spatial/3")                  # 3
    numbering = StateNumbering([50] * 10)
    numbering.global_state_id(3, 7)                       # 157
    numbering.split_global_state_id(157)                  # (3, 7)
    camera_key_map("verl_vla")["agentview"]               # 'observation.images.image'
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

__all__ = ["CAMERA_KEYS", "StateNumbering", "camera_key_map", "env_indices", "suite_of", "suite_task_index"]

# vecsim camera name -> the key each trainer's LIBERO policy reads the image under.
CAMERA_KEYS: dict[str, dict[str, str]] = {
    # verl-vla src/verl_vla/envs/libero/libero_env.py:290-291 (LiberoEnv._make_observations).
    "verl_vla": {"agentview": "observation.images.image", "robot0_eye_in_hand": "observation.images.wrist_image"},
    # LeRobot's LiberoEnv default camera_name_mapping (agentview_image -> image, eye in hand ->
    # image2), under its "observation.images." prefix.
    "lerobot": {"agentview": "observation.images.image", "robot0_eye_in_hand": "observation.images.image2"},
    # RLinf 0.3.0 LiberoEnv observation keys (rlinf/envs/libero/libero_env.py).
    "rlinf": {"agentview": "main_images", "robot0_eye_in_hand": "wrist_images"},
}


def camera_key_map(camera_keys: str | Mapping[str, str]) -> dict[str, str]:
    """Return the camera-name -> key mapping that ``camera_keys`` names: a preset of
    :data:`CAMERA_KEYS` or a user's mapping of camera names to distinct string keys.

    Raises:
        ValueError: an unknown preset name, or a mapping whose keys or values are not strings or
            whose values repeat (names the offender).
    """
    if isinstance(camera_keys, str):
        if camera_keys not in CAMERA_KEYS:
            raise ValueError(f"camera_keys: unknown preset {camera_keys!r}; presets are {sorted(CAMERA_KEYS)}")
        return dict(CAMERA_KEYS[camera_keys])
    if not isinstance(camera_keys, Mapping):
        raise ValueError(f"camera_keys must be a preset name or a mapping, got {type(camera_keys).__name__}")
    mapping = dict(camera_keys)
    for camera, key in mapping.items():
        if not isinstance(camera, str) or not isinstance(key, str) or not key:
            raise ValueError(f"camera_keys: {camera!r} -> {key!r} is not a camera name to a non-empty key")
    keys = list(mapping.values())
    repeated = sorted({k for k in keys if keys.count(k) > 1})
    if repeated:
        raise ValueError(f"camera_keys: keys {repeated} are given to more than one camera")
    return mapping


def env_indices(env_ids: object, num_envs: int, field: str = "env_ids") -> np.ndarray:
    """``env_ids`` as an int64 array of env indices, checked against ``num_envs`` envs.

    Raises:
        ValueError: ids that are not ints, or not distinct indices ``0..num_envs-1`` (names
            ``field`` and the ids).
    """
    ids = np.asarray(env_ids).reshape(-1)
    if ids.size and ids.dtype.kind not in "iu":
        raise ValueError(f"{field} must be ints, got {ids.tolist()}")
    ids = ids.astype(np.int64)
    if ((ids < 0) | (ids >= num_envs)).any() or len(set(ids.tolist())) != ids.size:
        raise ValueError(f"{field} must be distinct env indices 0..{num_envs - 1}, got {ids.tolist()}")
    return ids


def suite_of(task_id: str) -> str:
    """Return the suite part of a task id (``"libero_spatial/3"`` -> ``"libero_spatial"``)."""
    return task_id.rpartition("/")[0]


def suite_task_index(task_id: str) -> int:
    """Return the task's int index in its suite: ``"libero_spatial/3"`` -> 3.

    Raises:
        ValueError: the id has no ``/<non-negative integer>`` ending (names the id).
    """
    suite, slash, index = str(task_id).rpartition("/")
    if not slash or not suite or not index.isdigit():
        raise ValueError(f"task id {task_id!r} has no integer task index (expected '<suite>/<n>')")
    return int(index)


class StateNumbering:
    """Suite-global state ids: task ``t``'s rows come after the rows of tasks ``0..t-1``.

    ``counts[t]`` is how many initial states task ``t`` has (``/v1/info``'s ``num_states``), so
    with LIBERO's 50 each, task ``t`` row ``r`` is ``t * 50 + r``; tasks with other counts shift
    the ids after them, as the trainers' own cumulative numbering does.

    Raises:
        ValueError: a count that is not a non-negative integer (names the task index).
    """

    def __init__(self, counts: Sequence[int]) -> None:
        for task, count in enumerate(counts):
            if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 0:
                raise ValueError(f"state count of task {task} must be a non-negative int, got {count!r}")
        self.counts = tuple(int(c) for c in counts)
        self.starts = tuple(int(s) for s in np.concatenate([[0], np.cumsum(self.counts, dtype=np.int64)]))

    @classmethod
    def from_num_states(cls, num_states: Mapping[str, int], suite: str) -> StateNumbering:
        """The numbering of ``suite`` from per-task counts keyed by task id (``/v1/info``'s).

        Tasks of the suite that ``num_states`` leaves out below its highest index take the count
        the others share when they all have one (LIBERO's 50), else the numbering is undefined.

        Raises:
            ValueError: no task of ``suite``, or a task missing below the highest index while
                the known counts differ (names the missing task ids).
        """
        known = {suite_task_index(t): int(n) for t, n in num_states.items() if suite_of(t) == suite}
        if not known:
            raise ValueError(f"no task of suite {suite!r} among {sorted(num_states)}")
        missing = [t for t in range(max(known) + 1) if t not in known]
        if missing and len(set(known.values())) != 1:
            raise ValueError(
                f"suite {suite!r}: the state counts of tasks {[f'{suite}/{t}' for t in missing]} are not known "
                "and the known tasks' counts differ, so suite-global state ids are undefined"
            )
        fill = next(iter(known.values()))
        return cls([known.get(t, fill) for t in range(max(known) + 1)])

    @property
    def size(self) -> int:
        """How many suite-global ids there are (``0..size-1``)."""
        return self.starts[-1]

    def global_state_id(self, task_index: int, row: int) -> int:
        """Return the suite-global id of row ``row`` of task ``task_index``.

        Raises:
            ValueError: a task index or row out of range (names it and the range).
        """
        task, row = int(task_index), int(row)
        if not 0 <= task < len(self.counts):
            raise ValueError(f"task index {task} is outside 0..{len(self.counts) - 1}")
        if not 0 <= row < self.counts[task]:
            raise ValueError(f"state row {row} of task {task} is outside 0..{self.counts[task] - 1}")
        return self.starts[task] + row

    def split_global_state_id(self, global_state_id: int) -> tuple[int, int]:
        """Return ``(task_index, row)`` of a suite-global state id.

        Raises:
            ValueError: the id is outside ``0..size-1`` (names it).
        """
        gid = int(global_state_id)
        if not 0 <= gid < self.size:
            raise ValueError(f"global state id {gid} is outside 0..{self.size - 1}")
        task = int(np.searchsorted(self.starts, gid, side="right")) - 1
        return task, gid - self.starts[task]
