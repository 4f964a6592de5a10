"""Running a ``bench/`` script end to end, as a person would run it, for the benchmark smoke tests.

A unit test imports a bench script or ``bench/lib`` as the scripts do, with ``bench/`` on
``sys.path`` (:func:`bench_importable`, :func:`bench_import`).

A smoke test copies ``bench/`` into a directory of its own (:func:`copy_bench`), so that the
script's record (``out/bench/<name>.json``) and plots land under that directory and not over the
recorded ones in the repository; runs the script from the copy with this interpreter
(:func:`run_bench_script`), in an environment built by :func:`bench_env`; and checks that it
exited 0 and printed exactly one ``RESULT {json}`` line, which it parses (:func:`result_of`).
:func:`bench_result` does all of that in one call.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import logging
import os
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

from support import ROOT

log = logging.getLogger(__name__)

RESULT_PREFIX = "RESULT "
# How much of the script's stderr and stdout a failure message quotes.
STDERR_TAIL = 3000
STDOUT_TAIL = 2000


BENCH = ROOT / "bench"


@contextlib.contextmanager
def bench_importable() -> Iterator[Path]:
    """``bench/`` on ``sys.path`` within the block, as a bench script has it (its own modules and
    ``lib`` import as the scripts import them); yields ``bench/``."""
    sys.path.insert(0, str(BENCH))
    try:
        yield BENCH
    finally:
        sys.path.remove(str(BENCH))


@contextlib.contextmanager
def bench_import(name: str) -> Iterator[ModuleType]:
    """The bench module ``name`` (``"bench_mjwarp"``, ``"lib.scripted"``), imported and used
    within the block with ``bench/`` on ``sys.path`` (:func:`bench_importable`)."""
    with bench_importable():
        yield importlib.import_module(name)


def copy_bench(root: Path) -> Path:
    """Copy the repository's ``bench/`` (without ``__pycache__``) to ``root/bench``, unless a copy
    is there already, and return the copy. Its scripts write their records under ``root/out``."""
    copy = root / "bench"
    if not copy.exists():
        shutil.copytree(ROOT / "bench", copy, ignore=shutil.ignore_patterns("__pycache__"))
    return copy


def bench_env(
    *,
    repo_on_path: bool = True,
    default_mujoco_gl: str | None = "egl",
    drop: Iterable[str] = ("VECSIM_TOKEN",),
    extra: Mapping[str, str] | None = None,
) -> dict[str, str]:
    """This process's environment for a bench script: ``MUJOCO_GL`` set to ``default_mujoco_gl``
    where it is unset (left alone where that is None), ``PYTHONPATH`` the repository where
    ``repo_on_path`` (else inherited), the variables named in ``drop`` removed, and ``extra`` set
    over all of it."""
    env = dict(os.environ)
    if default_mujoco_gl is not None:
        env.setdefault("MUJOCO_GL", default_mujoco_gl)
    if repo_on_path:
        env["PYTHONPATH"] = str(ROOT)
    for name in drop:
        env.pop(name, None)
    env.update(extra or {})
    return env


def run_bench_script(
    root: Path,
    script: str,
    *args: str,
    timeout: float,
    env: Mapping[str, str] | None = None,
    cwd: Path | None = None,
) -> subprocess.CompletedProcess[str]:
    """Run ``bench/<script> args`` with this interpreter from a copy of ``bench/`` in ``root``
    (made if missing), in ``cwd`` (``root`` by default) and ``env`` (:func:`bench_env`'s default
    by default), within ``timeout`` seconds. Return the finished process; its return code is not
    checked, so that a test can expect a refusal."""
    command = [sys.executable, str(copy_bench(root) / script), *args]
    where = root if cwd is None else cwd
    log.info("running %s in %s", shlex.join(command), where)
    start = time.monotonic()
    run_env = bench_env() if env is None else dict(env)
    done = subprocess.run(command, cwd=where, env=run_env, capture_output=True, text=True, timeout=timeout, check=False)
    log.info("%s exited %d after %.1f s", script, done.returncode, time.monotonic() - start)
    return done


def result_of(done: subprocess.CompletedProcess[str]) -> dict[str, Any]:
    """The parsed ``RESULT {json}`` line of a bench script run by :func:`run_bench_script`, after
    asserting that it exited 0 (quoting the end of its stderr otherwise) and printed exactly one
    such line (quoting the end of its stdout otherwise)."""
    what = shlex.join([Path(str(done.args[1])).name, *map(str, done.args[2:])])
    assert done.returncode == 0, f"{what} exited {done.returncode}:\n{done.stderr[-STDERR_TAIL:]}"
    lines = [line for line in done.stdout.splitlines() if line.startswith(RESULT_PREFIX)]
    assert len(lines) == 1, f"{what} printed {len(lines)} RESULT lines:\n{done.stdout[-STDOUT_TAIL:]}"
    return json.loads(lines[0].removeprefix(RESULT_PREFIX))


def bench_result(
    root: Path,
    script: str,
    *args: str,
    timeout: float,
    env: Mapping[str, str] | None = None,
    cwd: Path | None = None,
) -> dict[str, Any]:
    """:func:`run_bench_script`, then :func:`result_of`: the script's one ``RESULT`` line, parsed,
    from a run that must succeed. Its record lies under ``root / "out" / "bench"``."""
    return result_of(run_bench_script(root, script, *args, timeout=timeout, env=env, cwd=cwd))
