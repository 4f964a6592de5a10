"""The task catalogue: which task ids exist and which share their spaces, known without a simulator.

The controller checks a job with it (it installs without mujoco, robosuite or torch); a pod's
engine builds the tasks (``vecsim.engine.tasks``), and a test holds the two to one list.

- LIBERO: ``<suite>/<index>``, LIBERO's own order; every LIBERO task has one pair of spaces.
- robosuite and ``tiny``: named scenes; all share one pair of spaces (another than LIBERO's).
- ``gym/<id>`` (``gym:<id>`` normalised): any gymnasium id, judged by the pod that makes it;
  its spaces are its own.

    >>> suite_task_ids("tiny")
    ['tiny/lift', 'tiny/stack', 'tiny/door']
    >>> space_family("libero_10/3") == space_family("libero_90/0"), space_family("robosuite/Lift")
    (True, 'robosuite')
"""

from __future__ import annotations

from typing import NamedTuple

__all__ = [
    "LIBERO_SUITES",
    "ROBOSUITE_SUITES",
    "LiberoSuite",
    "is_known",
    "normalize_task_id",
    "space_family",
    "suite_names",
    "suite_task_ids",
]


class LiberoSuite(NamedTuple):
    num_tasks: int  # as LIBERO's benchmark lists them
    # The default episode length: the step budget of LIBERO's published evaluations (the longest
    # training demonstration of the suite plus a margin), settle steps not counted.
    max_episode_steps: int


LIBERO_SUITES: dict[str, LiberoSuite] = {
    "libero_10": LiberoSuite(10, 520),
    "libero_spatial": LiberoSuite(10, 220),
    "libero_object": LiberoSuite(10, 280),
    "libero_goal": LiberoSuite(10, 300),
    "libero_90": LiberoSuite(90, 400),
}
ROBOSUITE_SUITES: dict[str, tuple[str, ...]] = {
    "robosuite": (
        "Lift",
        "Stack",
        "PickPlace",
        "PickPlaceMilk",
        "PickPlaceBread",
        "PickPlaceCereal",
        "PickPlaceCan",
        "NutAssembly",
        "NutAssemblySquare",
        "NutAssemblyRound",
        "Door",
    ),
    "tiny": ("lift", "stack", "door"),
}


def normalize_task_id(task_id: str) -> str:
    """Return ``task_id`` with a ``gym:`` prefix written as ``gym/``; anything else unchanged."""
    if task_id.startswith("gym:"):
        return "gym/" + task_id[len("gym:") :]
    return task_id


def suite_names() -> list[str]:
    """The suites' names (gymnasium ids are tasks of no suite)."""
    return [*LIBERO_SUITES, *ROBOSUITE_SUITES]


def suite_task_ids(suite: str) -> list[str]:
    """The task ids of ``suite`` in the suite's order.

    Raises:
        KeyError: no suite of that name.
    """
    if suite in LIBERO_SUITES:
        return [f"{suite}/{index}" for index in range(LIBERO_SUITES[suite].num_tasks)]
    if suite in ROBOSUITE_SUITES:
        return [f"{suite}/{name}" for name in ROBOSUITE_SUITES[suite]]
    raise KeyError(suite)


def is_known(task_id: str) -> bool:
    """Whether ``task_id`` names a task of a suite, or a gymnasium id (which the pod judges)."""
    suite, _, name = normalize_task_id(task_id).partition("/")
    if suite == "gym":
        return bool(name)
    if suite in LIBERO_SUITES:
        return name.isdigit() and int(name) < LIBERO_SUITES[suite].num_tasks and str(int(name)) == name
    return name in ROBOSUITE_SUITES.get(suite, ())


def space_family(task_id: str) -> str:
    """What decides a known task's spaces under one camera config: ``libero``, ``robosuite`` (its
    and ``tiny``'s scenes) or, for a gymnasium task, its own normalised id. Tasks of one family
    share one observation space and one action space."""
    normalized = normalize_task_id(task_id)
    suite = normalized.partition("/")[0]
    if suite in LIBERO_SUITES:
        return "libero"
    if suite in ROBOSUITE_SUITES:
        return "robosuite"
    return normalized
