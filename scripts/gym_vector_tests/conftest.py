"""Run gymnasium's own ``tests/vector`` with vecsim's HTTPVectorEnv in place of ``AsyncVectorEnv``.

Copied by ``scripts/gym_vector_tests/run.sh`` beside a copy of gymnasium's ``tests/`` (taken from
a Gymnasium checkout at the installed release's tag, never committed here). Only
``gymnasium.vector.AsyncVectorEnv`` is replaced (``make_vec``'s async mode calls it too), before
the test modules import it; ``SyncVectorEnv`` stays gymnasium's, the reference.

The stand-in does what ``AsyncVectorEnv`` does with the test's env factories, on a pod instead
of in worker processes: it writes each factory (cloudpickled, as ``AsyncVectorEnv`` sends it to
its worker) to a file that ``gymtests_shim`` gives the pod as the callable
``gymtests_shim:F<n>x<i>`` (vecsim's ``gym/<module>:<callable>`` task form, which serves the env
the callable returns, as it is); it starts a standalone pod with one task per factory (env ``i`` is factory ``i``'s env; the first one's spaces are the
job's, as ``AsyncVectorEnv`` takes its dummy env's) and returns ``HTTPVectorEnv(pod_urls=[pod])``
with the test's autoreset mode. No space, seed or reset is injected. A custom ``worker`` or an
``observation_mode`` other than ``"same"`` keeps gymnasium's class (reported, not counted). The
summary counts the tests that reached HTTPVectorEnv by outcome and names each failure and each
refusal by cause: not applicable is only a refusal naming a space the wire cannot carry, and
"cannot run here" only envs that need a package this machine lacks (gymnasium's own classes
fail alike); any other failure to serve the envs is a failure. ``VECSIM_REPO`` names the vecsim checkout under test.
"""

from __future__ import annotations

import atexit
import contextlib
import itertools
import os
import re
import shutil
import signal
import sys
import tempfile
from pathlib import Path

import cloudpickle
import pytest

HERE = Path(__file__).resolve().parent
REPO = Path(os.environ["VECSIM_REPO"]).resolve()
sys.path[:0] = [str(REPO), str(REPO / "tests")]
FACTORIES = Path(tempfile.mkdtemp(prefix="gymtests-factories-"))
atexit.register(shutil.rmtree, FACTORIES, True)
os.environ["GYMTESTS_FACTORIES"] = str(FACTORIES)
# The pods import gymtests_shim and, through the factories, the test modules (tests.vector...).
os.environ["PYTHONPATH"] = os.pathsep.join(
    [str(HERE), str(REPO), str(REPO / "tests"), os.environ.get("PYTHONPATH", "")]  # HERE holds tests/
)

import gymnasium  # noqa: E402
import gymnasium.vector  # noqa: E402
from gymnasium.vector import AutoresetMode  # noqa: E402
from support.service_procs import PodSpec, standalone_pods  # noqa: E402

from vecsim.client import HTTPVectorEnv  # noqa: E402
from vecsim.engine.checks import assignment_spaces  # noqa: E402

_AsyncVectorEnv = gymnasium.vector.AsyncVectorEnv
signal.signal(signal.SIGTERM, signal.default_int_handler)  # run.sh's timeout: pytest stops its pods
_count = itertools.count()
_pods: list[contextlib.ExitStack] = []  # the current test's pods, stopped after it

_reached: set[str] = set()  # test ids that got an HTTPVectorEnv
_refused: dict[str, str] = {}  # test id -> why the pod refused its envs
_unbuildable: dict[str, str] = {}  # test id -> the package its envs need that is not installed here
_kept: dict[str, str] = {}  # test id -> why gymnasium's own AsyncVectorEnv ran it
_outcomes: dict[str, tuple[str, str]] = {}  # test id -> (outcome, first error line of its failure)


def _test_id() -> str:
    return os.environ.get("PYTEST_CURRENT_TEST", "?").rsplit(" ", 1)[0]


def _served_async(
    env_fns,
    shared_memory=True,
    copy=True,
    context=None,
    daemon=True,
    worker=None,
    observation_mode="same",
    autoreset_mode=AutoresetMode.NEXT_STEP,
):
    """``AsyncVectorEnv(env_fns, ...)``, served by a pod (see the module docstring)."""
    if worker is not None or not (isinstance(observation_mode, str) and observation_mode == "same"):
        _kept[_test_id()] = "custom worker" if worker is not None else f"observation_mode={observation_mode!r}"
        return _AsyncVectorEnv(
            env_fns,
            shared_memory=shared_memory,
            copy=copy,
            context=context,
            daemon=daemon,
            worker=worker,
            observation_mode=observation_mode,
            autoreset_mode=autoreset_mode,
        )
    test = _test_id()
    _reached.add(test)
    token = next(_count)
    tasks = []
    for i, fn in enumerate(env_fns):
        (FACTORIES / f"F{token}x{i}.pkl").write_bytes(cloudpickle.dumps(fn))
        tasks.append((f"gym/gymtests_shim:F{token}x{i}", 1))
    spec = PodSpec(f"gymtests-{token}", 0, tasks, max_episode_steps=None, envs_per_worker=len(tasks))
    stack = contextlib.ExitStack()
    try:
        # AsyncVectorEnv checks its envs' spaces as it is made. A pod runs this same check on its
        # assignment as it starts, but its exception would reach the test only as a line of the
        # pod's log: run here too, it reaches the test as it reaches a caller of the check.
        assignment_spaces(spec.assignment())
        pod = stack.enter_context(standalone_pods([spec]))[0]
    except Exception as exc:
        stack.close()
        cause = _pod_refusal(exc)
        if cause is not None:
            _refused[test] = cause
        _note_missing_package(test, str(exc))
        raise
    _pods.append(stack)
    return HTTPVectorEnv(pod_urls=[pod.url], autoreset_mode=autoreset_mode, timeout_s=30)


def _note_missing_package(test: str, text: str) -> None:
    """Count ``test`` as cannot run here if ``text`` (its error) says a package is missing."""
    missing = re.search(r"DependencyNotInstalled: [^\n]*", text)
    if missing:
        _unbuildable[test] = missing.group(0)[:200]


# A refusal naming a space (or dtype) the wire cannot carry: the only cause counted not applicable.
_CANNOT_TRAVEL = re.compile(r"[^\n]*(?:is not supported \(|cannot travel on the wire)[^\n]*")


def _pod_refusal(exc: Exception) -> str | None:
    """The line of the pod's error saying which space the wire cannot carry; None for any other
    failure to start (a failure of the test)."""
    found = _CANNOT_TRAVEL.search(str(exc))
    if found is None:
        return None
    cause = re.sub(r"gym/gymtests_shim:F\d+x\d+: ", "", found.group(0).strip())
    return re.sub(r"^.*?tasks: ", "", cause)[:200]


gymnasium.vector.AsyncVectorEnv = _served_async


@pytest.fixture(autouse=True)
def _stop_pods():
    yield
    while _pods:
        _pods.pop().close()


def pytest_runtest_logreport(report):
    if report.when == "call" or report.outcome != "passed":
        message = ""
        if report.failed and report.longrepr:
            lines = [line for line in str(report.longrepr).strip().splitlines() if line.startswith("E ")]
            message = (lines[0] if lines else str(report.longrepr).strip().splitlines()[-1])[:200]
        if report.nodeid not in _outcomes or report.outcome != "passed":
            _outcomes[report.nodeid] = (report.outcome, message)
        if report.failed and report.longrepr:  # an env of the test needing a package not installed
            _note_missing_package(report.nodeid, str(report.longrepr))


def _group(entries: dict[str, str]) -> dict[str, list[str]]:
    groups: dict[str, list[str]] = {}
    for nodeid, cause in sorted(entries.items()):
        groups.setdefault(cause, []).append(nodeid)
    return groups


def pytest_terminal_summary(terminalreporter):
    write = terminalreporter.write_line
    reached = {nodeid: _outcomes.get(nodeid, ("?", "")) for nodeid in _reached}
    refused = {nodeid: _refused[nodeid] for nodeid in reached if nodeid in _refused}
    unbuildable = {nodeid: _unbuildable[nodeid] for nodeid in reached if nodeid in _unbuildable}
    counts = {"passed": 0, "failed": 0, "not applicable": len(refused), "cannot run here": len(unbuildable)}
    failed: dict[str, str] = {}
    for nodeid, (outcome, message) in reached.items():
        if nodeid in refused or nodeid in unbuildable:
            continue
        counts[outcome] = counts.get(outcome, 0) + 1
        if outcome == "failed":
            failed[nodeid] = message
    write(f"tests that reached HTTPVectorEnv: {len(reached)} {counts}")
    for cause, nodeids in _group(refused).items():
        write(f"  NOT APPLICABLE ({len(nodeids)}): the pod refused: {cause}")
        for nodeid in nodeids:
            write(f"    {nodeid}")
    for cause, nodeids in _group(unbuildable).items():
        write(f"  CANNOT RUN HERE ({len(nodeids)}): the envs need what is not installed: {cause}")
        for nodeid in nodeids:
            write(f"    {nodeid}")
    for nodeid, message in sorted(failed.items()):
        write(f"  FAILED {nodeid}: {message}")
    for cause, nodeids in _group(_kept).items():
        write(f"  kept on gymnasium's AsyncVectorEnv ({len(nodeids)}, not counted): {cause}")
