"""Run gymnasium's own ``tests/vector`` with vecsim's HTTPVectorEnv in place of its vector envs.

Copied by ``scripts/gym_vector_tests/run.sh`` beside a copy of gymnasium's ``tests/`` (taken from
a Gymnasium checkout at the installed release's tag, never committed here). ``AsyncVectorEnv``
and ``SyncVectorEnv`` become a factory, in ``gymnasium.vector`` before the test modules import them, that
calls each env factory once to learn the env (as ``AsyncVectorEnv`` makes a dummy env): a
registered id with its make kwargs, or one of gymnasium's test envs (registered for the pods by
``gymtests_shim``), becomes a task of a standalone vecsim pod (one per id, kwargs and env count,
kept for the session) and the test gets ``HTTPVectorEnv(pod_urls=[pod])`` with its autoreset
mode, reset with the seeds the factories reset their envs with, its spaces the first env's (as
``AsyncVectorEnv`` and ``SyncVectorEnv`` take them). Options of local processes are dropped;
custom workers and envs made from local functions get gymnasium's own class. The summary counts
the tests that reached HTTPVectorEnv and names each failure. ``VECSIM_REPO`` names the vecsim
checkout under test.
"""

from __future__ import annotations

import atexit
import contextlib
import json
import os
import signal
import sys
import weakref
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = Path(os.environ["VECSIM_REPO"]).resolve()
sys.path[:0] = [str(REPO), str(REPO / "tests")]
# The pods import the test envs (gymtests_shim, tests.vector.testing_utils) from here.
os.environ["PYTHONPATH"] = os.pathsep.join([str(HERE), str(REPO), str(REPO / "tests"), os.environ.get("PYTHONPATH", "")])

import gymnasium  # noqa: E402
import gymnasium.vector  # noqa: E402
from gymnasium.vector import AutoresetMode  # noqa: E402
from gymnasium.vector.utils import batch_space  # noqa: E402
from support.service_procs import PodSpec, standalone_pods  # noqa: E402

from vecsim.client import HTTPVectorEnv  # noqa: E402

# (id, kwargs, env count) -> [[pod url, the vector env using it now, the pod's ExitStack]]: two
# vector envs open at once (a test comparing two) get a pod each. At most MAX_PODS run at once:
# idle ones are stopped, oldest first, to make room.
MAX_PODS = 6
_pods: dict[tuple[str, str, int], list[list]] = {}


def _stop_all() -> None:
    for pool in _pods.values():
        for slot in pool:
            slot[2].close()
    _pods.clear()


atexit.register(_stop_all)
signal.signal(signal.SIGTERM, signal.default_int_handler)  # pytest stops; atexit stops the pods


_SHIM_IDS = {"SlowEnv": "gymtests_shim:SlowEnv-v0", "CustomSpaceEnv": "gymtests_shim:CustomSpaceEnv-v0"}


def _served(env: gymnasium.Env) -> tuple[str, dict] | None:
    """The gymnasium id a pod makes ``env`` as, and its make kwargs (None: it cannot)."""
    spec = env.spec
    name = type(env.unwrapped).__name__
    if name in _SHIM_IDS:
        kwargs = {"slow_reset": env.unwrapped.slow_reset} if name == "SlowEnv" else {}
        return _SHIM_IDS[name], kwargs
    if spec is None or not isinstance(spec.entry_point, str) or spec.id not in gymnasium.registry:
        return None  # made by local functions: not a gymnasium id a pod can make
    kwargs = {k: v for k, v in spec.kwargs.items() if gymnasium.registry[spec.id].kwargs.get(k, object()) != v}
    return spec.id, kwargs


def _idle(slot: list) -> bool:
    user = slot[1]()
    return user is None or user.closed


def _pod(gym_id: str, kwargs: dict, num_envs: int) -> list:
    """A pod serving ``num_envs`` envs of the id that no open vector env uses: [url, user, stack]."""
    pool = _pods.setdefault((gym_id, json.dumps(kwargs, sort_keys=True, default=str), num_envs), [])
    for slot in pool:
        if _idle(slot):
            return slot
    running = [(key, slot) for key, slots in _pods.items() for slot in slots]
    for key, slot in running[: max(0, len(running) + 1 - MAX_PODS)]:
        if _idle(slot):
            slot[2].close()
            _pods[key].remove(slot)
    task = f"gym/{gym_id}"
    spec = PodSpec(
        "gym", 0, [(task, num_envs)], max_episode_steps=None, envs_per_worker=num_envs,  # one worker: quick to start
        make_kwargs={task: kwargs} if kwargs else {},
    )
    stack = contextlib.ExitStack()
    pool.append([stack.enter_context(standalone_pods([spec]))[0].url, lambda: None, stack])
    return pool[-1]


_reached: set[str] = set()  # test ids that got an HTTPVectorEnv
_outcomes: dict[str, tuple[str, str]] = {}  # test id -> (outcome, first line of its failure)


def _vecsim_instead_of(local_class: type):
    """A stand-in for ``local_class`` giving an HTTPVectorEnv where the envs can be served, and
    ``local_class`` itself where they cannot (envs of local functions, custom workers)."""

    def make(env_fns, *args, autoreset_mode=AutoresetMode.NEXT_STEP, **kwargs):
        if kwargs.get("worker") is not None or kwargs.get("observation_mode") not in (None, "same"):
            return local_class(env_fns, *args, autoreset_mode=autoreset_mode, **kwargs)
        envs = [fn() for fn in env_fns]
        served = [_served(env) for env in envs]
        if None in served or len({json.dumps(one, sort_keys=True, default=str) for one in served}) != 1:
            for env in envs:
                env.close()
            return local_class(env_fns, *args, autoreset_mode=autoreset_mode, **kwargs)
        gym_id, make_kwargs = served[0]
        seeds = [env.np_random_seed if env.unwrapped._np_random is not None else None for env in envs]
        _reached.add(os.environ.get("PYTEST_CURRENT_TEST", "?").rsplit(" ", 1)[0])
        slot = _pod(gym_id, make_kwargs, len(envs))
        vector = HTTPVectorEnv(pod_urls=[slot[0]], autoreset_mode=autoreset_mode, timeout_s=30)
        slot[1] = weakref.ref(vector)
        if any(seed is not None for seed in seeds):
            vector.reset(seed=seeds)  # what each factory did to its env
        # AsyncVectorEnv (its dummy env) and SyncVectorEnv (envs[0]) take the first env's spaces.
        vector.single_action_space = envs[0].action_space
        vector.action_space = batch_space(vector.single_action_space, vector.num_envs)
        for env in envs:
            env.close()
        return vector

    return make


# Before the test modules import them (parametrized partials capture the class at import).
for _name in ("AsyncVectorEnv", "SyncVectorEnv"):
    setattr(gymnasium.vector, _name, _vecsim_instead_of(getattr(gymnasium.vector, _name)))


def pytest_runtest_logreport(report):
    if report.when == "call" or report.outcome != "passed":
        message = str(report.longrepr).strip().splitlines()[-1][:160] if report.failed and report.longrepr else ""
        if report.nodeid not in _outcomes or report.outcome != "passed":
            _outcomes[report.nodeid] = (report.outcome, message)


def pytest_terminal_summary(terminalreporter):
    reached = {nodeid: _outcomes.get(nodeid, ("?", "")) for nodeid in _reached}
    counts: dict[str, int] = {}
    for outcome, _ in reached.values():
        counts[outcome] = counts.get(outcome, 0) + 1
    terminalreporter.write_line(f"tests that reached HTTPVectorEnv: {len(reached)} {dict(sorted(counts.items()))}")
    for nodeid, (outcome, message) in sorted(reached.items()):
        if outcome == "failed":
            terminalreporter.write_line(f"  FAILED {nodeid}: {message}")
