"""One benchmark at two git revisions, turn about: did a change move its headline ratio?

Each revision is checked out as a detached worktree in a temporary directory (removed at the end,
on error or Ctrl-C too); the benchmark runs there, from that tree's own ``bench/<script>``, with
``PYTHONPATH=<that tree>`` and this venv's python, so it (and the pods it starts) imports that
revision's ``vecsim`` and ``service``. Runs alternate A, B, A, B ... for ``--rounds``, so load that
comes and goes on a shared machine hits both alike. Each run's ratio is the ``ratio`` field of the
record it writes to ``out/bench/<name>.json`` in its tree (its ``RESULT`` line names the record).

The headline: the median of B's ratios over the median of A's (1.0: no change; whether higher is
better depends on the benchmark's own ratio), beside each revision's min-max over the rounds.

    python bench/bench_revisions.py --bench bench_serving.py --quick --revisions HEAD,HEAD   # smoke
    python bench/bench_revisions.py --bench bench_robot_step.py --rounds 3 -- --tasks libero_10/0 --steps 80

Prints ``RESULT {json}`` and writes out/bench/bench_revisions_<bench>[_<tag>].json.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from lib.pods import log, setup_logging, wait_for_quiet
from lib.records import REPO_ROOT, RESULT_PREFIX, write_result

LABELS = ("A", "B")
MAX_ROUNDS = 20
GIT_TIMEOUT_S = 120
# After Ctrl-C (SIGINT) a benchmark's context managers stop the pods it started; then it is killed.
INTERRUPT_GRACE_S = 30


def git(repo: Path, *args: str) -> str:
    """Run ``git -C repo args``; return its stdout, stripped."""
    done = subprocess.run(
        ["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=GIT_TIMEOUT_S, check=False
    )
    if done.returncode != 0:
        raise RuntimeError(f"git {' '.join(args)} failed in {repo}: {done.stderr.strip()}")
    return done.stdout.strip()


def resolve(repo: Path, revisions: str, bench: str) -> list[dict[str, str]]:
    """``--revisions A,B`` as ``[{rev, commit, subject}, ...]``; raises ValueError naming the flag."""
    revs = [rev.strip() for rev in revisions.split(",")]
    if len(revs) != 2 or not all(revs):
        raise ValueError(f"--revisions: expected two revisions, A,B; got {revisions!r}")
    resolved = []
    for rev in revs:
        try:
            commit = git(repo, "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}")
        except RuntimeError:
            raise ValueError(f"--revisions: {rev!r} is not a commit of {repo}") from None
        if (
            subprocess.run(
                ["git", "-C", str(repo), "cat-file", "-e", f"{commit}:bench/{bench}"],
                capture_output=True,
                timeout=GIT_TIMEOUT_S,
            ).returncode
            != 0
        ):
            raise ValueError(f"--bench: bench/{bench} does not exist at revision {rev!r}")
        resolved.append({"rev": rev, "commit": commit, "subject": git(repo, "log", "-1", "--format=%s", commit)})
    return resolved


@contextlib.contextmanager
def worktrees(repo: Path, commits: Sequence[str]) -> Iterator[list[Path]]:
    """Detached worktrees of ``commits`` under a temporary directory; removed on exit, whatever happened."""
    root = Path(tempfile.mkdtemp(prefix="bench_revisions-"))
    trees: list[Path] = []
    try:
        for label, commit in zip(LABELS, commits):
            tree = root / label
            git(repo, "worktree", "add", "--detach", str(tree), commit)
            trees.append(tree)
        yield trees
    finally:
        for tree in trees:
            with contextlib.suppress(RuntimeError, subprocess.TimeoutExpired):
                git(repo, "worktree", "remove", "--force", str(tree))
        shutil.rmtree(root, ignore_errors=True)
        with contextlib.suppress(RuntimeError, subprocess.TimeoutExpired):
            git(repo, "worktree", "prune")


def stop(process: subprocess.Popen[str]) -> None:
    """Interrupt a benchmark's process group (so it stops its pods), then kill what is left."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGINT)
    try:
        process.wait(timeout=INTERRUPT_GRACE_S)
    except subprocess.TimeoutExpired:
        pass
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGKILL)
    process.wait()


def tree_env(tree: Path) -> dict[str, str]:
    """The environment a run in ``tree`` gets: that tree alone on PYTHONPATH (not this checkout's)."""
    env = {**os.environ, "PYTHONPATH": str(tree), "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    env.pop("VECSIM_TOKEN", None)  # the benchmark's own jobs set their tokens
    return env


def imported_from(tree: Path) -> dict[str, str]:
    """Where python, run as a benchmark in ``tree`` is, finds ``vecsim`` and ``service``.

    Raises RuntimeError if either comes from elsewhere (the venv's editable install, say): the
    run would measure the wrong revision.
    """
    code = "import vecsim, service; print(vecsim.__file__); print(service.__file__)"
    done = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tree,
        env=tree_env(tree),
        capture_output=True,
        text=True,
        timeout=GIT_TIMEOUT_S,
    )
    paths = dict(zip(("vecsim", "service"), done.stdout.split()))
    if done.returncode != 0 or len(paths) != 2 or not all(Path(p).is_relative_to(tree) for p in paths.values()):
        raise RuntimeError(f"{tree.name}: vecsim/service not imported from {tree}: {paths or done.stderr[-500:]}")
    return {name: str(Path(path).relative_to(tree)) for name, path in paths.items()}


def run_bench(tree: Path, bench: str, bench_args: Sequence[str], timeout_s: float, logs: Path) -> dict[str, Any]:
    """Run ``tree``'s ``bench/<bench>`` once; return its RESULT, its record's ratio and the wall time.

    Raises RuntimeError (naming the tree and the log) if it fails, times out or writes no record.
    """
    env = tree_env(tree)
    stdout_path, stderr_path = logs.with_suffix(".out"), logs.with_suffix(".err")
    started_wall, started = time.time(), time.perf_counter()
    with stdout_path.open("w") as stdout, stderr_path.open("w") as stderr:
        # Its own session: on a timeout or Ctrl-C the whole group (the bench, its pods) is stopped.
        process = subprocess.Popen(
            [sys.executable, str(tree / "bench" / bench), *bench_args],
            cwd=tree,
            env=env,
            stdout=stdout,
            stderr=stderr,
            text=True,
            start_new_session=True,
        )
        try:
            rc = process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            stop(process)
            raise RuntimeError(
                f"{tree.name}: bench/{bench} ran past --timeout-s {timeout_s:g}; log {stderr_path}"
            ) from None
        except BaseException:
            stop(process)
            raise
    wall_s = time.perf_counter() - started
    if rc != 0:
        tail = stderr_path.read_text(errors="replace")[-2000:]
        raise RuntimeError(f"{tree.name}: bench/{bench} exited {rc}; log {stderr_path}:\n{tail}")
    lines = [line for line in stdout_path.read_text().splitlines() if line.startswith(RESULT_PREFIX)]
    if len(lines) != 1:
        raise RuntimeError(f"{tree.name}: bench/{bench} printed {len(lines)} RESULT lines; log {stdout_path}")
    result = json.loads(lines[0].removeprefix(RESULT_PREFIX))
    record_path = tree / "out" / "bench" / f"{result['name']}.json"
    if not record_path.exists() or record_path.stat().st_mtime < started_wall:
        raise RuntimeError(f"{tree.name}: bench/{bench} left no fresh record at {record_path}")
    record = json.loads(record_path.read_text())
    if not isinstance(record.get("ratio"), (int, float)):
        raise RuntimeError(f"{tree.name}: {record_path} has no numeric 'ratio' (got {record.get('ratio')!r})")
    return {"ratio": float(record["ratio"]), "wall_s": round(wall_s, 1), "result": result}


def ratio_spread(values: Sequence[float]) -> dict[str, float]:
    """Median, min, max and count of per-round ratios, rounded for the record."""
    return {
        "median": round(statistics.median(values), 4),
        "min": round(min(values), 4),
        "max": round(max(values), 4),
        "n": len(values),
    }


def parse_args(argv: Sequence[str]) -> tuple[argparse.Namespace, list[str]]:
    """This script's flags, and the benchmark's: everything after ``--``."""
    argv = list(argv)
    bench_args = argv[argv.index("--") + 1 :] if "--" in argv else []
    own = argv[: argv.index("--")] if "--" in argv else argv
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bench", required=True, help="a script under bench/, e.g. bench_robot_step.py")
    parser.add_argument("--revisions", default="755e209,HEAD", help="A,B: two git revisions (default 755e209,HEAD)")
    parser.add_argument(
        "--rounds", type=int, help=f"runs of each revision, A and B alternating (default 2, at most {MAX_ROUNDS})"
    )
    parser.add_argument("--warmup", type=int, default=0, help="uncounted runs of each revision first (caches, JIT)")
    parser.add_argument("--timeout-s", type=float, default=900.0, help="the longest one run may take")
    parser.add_argument(
        "--wait-quiet-s", type=float, default=0.0, help="before each run, wait up to this long for load < 1.5"
    )
    parser.add_argument("--quick", action="store_true", help="smoke test: one round, the benchmark with --quick")
    parser.add_argument("--tag", help="suffix of the record's name")
    parser.add_argument(
        "--repo", type=Path, default=REPO_ROOT, help="the git checkout whose revisions run (default: this one)"
    )
    args = parser.parse_args(own)
    if not re.fullmatch(r"[A-Za-z0-9_]+\.py", args.bench):
        parser.error(f"--bench: a script name under bench/, such as bench_serving.py; got {args.bench!r}")
    args.rounds = args.rounds if args.rounds is not None else (1 if args.quick else 2)
    if not 1 <= args.rounds <= MAX_ROUNDS:
        parser.error(f"--rounds: between 1 and {MAX_ROUNDS}; got {args.rounds}")
    if not 0 <= args.warmup <= 2:
        parser.error(f"--warmup: between 0 and 2; got {args.warmup}")
    if args.timeout_s <= 0:
        parser.error(f"--timeout-s: must be positive; got {args.timeout_s}")
    if args.quick and "--quick" not in bench_args:
        bench_args.append("--quick")
    return args, bench_args


def main(argv: Sequence[str]) -> int:
    args, bench_args = parse_args(argv)
    setup_logging()
    # SIGINT and SIGTERM end this script as Ctrl-C does, so the worktrees and the running bench are
    # cleaned up. Set explicitly: a shell starts a background job with SIGINT ignored, which its
    # children would inherit, and then a bench could not be interrupted into stopping its pods.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    repo = args.repo.resolve()
    try:
        revisions = resolve(repo, args.revisions, args.bench)
    except ValueError as error:
        log.error("%s", error)
        return 2
    runs: dict[str, list[dict[str, Any]]] = {label: [] for label in LABELS}
    logs = Path(tempfile.mkdtemp(prefix="bench_revisions-logs-"))
    try:
        with worktrees(repo, [r["commit"] for r in revisions]) as trees:
            imports = {label: imported_from(tree) for label, tree in zip(LABELS, trees)}
            for r in range(-args.warmup, args.rounds):
                for label, tree, revision in zip(LABELS, trees, revisions):
                    load_before = wait_for_quiet(timeout_s=args.wait_quiet_s)
                    kind = "warm-up" if r < 0 else f"round {r + 1}/{args.rounds}"
                    log.info("%s %s (%s): bench/%s %s", kind, label, revision["rev"], args.bench, " ".join(bench_args))
                    run = run_bench(tree, args.bench, bench_args, args.timeout_s, logs / f"{label}_{r + args.warmup}")
                    run["load_avg_before"] = round(load_before, 2)
                    log.info("%s %s: ratio %.4f in %.0f s", kind, label, run["ratio"], run["wall_s"])
                    if r >= 0:
                        runs[label].append(run)
    except RuntimeError as error:
        log.error("%s (worktrees removed; logs kept in %s)", error, logs)
        return 1
    shutil.rmtree(logs, ignore_errors=True)
    ratios = {label: [run["ratio"] for run in runs[label]] for label in LABELS}
    spreads = {label: ratio_spread(values) for label, values in ratios.items()}
    b_over_a = spreads["B"]["median"] / spreads["A"]["median"]
    overlap = spreads["B"]["min"] <= spreads["A"]["max"] and spreads["A"]["min"] <= spreads["B"]["max"]
    first = runs["A"][0]["result"]
    stem = Path(args.bench).stem
    summary = {
        "baseline": f"revision A ({revisions[0]['rev']}): the same benchmark, its median ratio",
        "ratio": round(b_over_a, 4),
        "target": "no change: B's ratios within A's round-to-round spread (their min-max ranges overlap)",
        "met": overlap,
        "quick": args.quick,
        "setup": {
            "bench": args.bench,
            "bench_args": bench_args,
            "bench_record": first["name"],
            "bench_ratio_is": first.get("baseline"),
            "rounds": args.rounds,
            "warmup": args.warmup,
            "order": "A, B alternating each round",
            "revisions": dict(zip(LABELS, revisions)),
            "imported_from_tree": imports,
            "python": sys.executable,
        },
        "ratios": {
            label: {
                **spreads[label],
                "per_round": [round(x, 4) for x in ratios[label]],
                "rev": rev["rev"],
                "commit": rev["commit"],
            }
            for label, rev in zip(LABELS, revisions)
        },
        "b_over_a_per_round": [round(b / a, 4) for a, b in zip(ratios["A"], ratios["B"])],
        "wall_s": {label: [run["wall_s"] for run in runs[label]] for label in LABELS},
        "load_avg_before": {label: [run["load_avg_before"] for run in runs[label]] for label in LABELS},
    }
    details = {label: [run["result"] for run in runs[label]] for label in LABELS}
    write_result(f"bench_revisions_{stem}" + (f"_{args.tag}" if args.tag else ""), summary, details)
    return 0


if __name__ == "__main__":
    try:
        raise SystemExit(main(sys.argv[1:]))
    except KeyboardInterrupt:
        log.error("interrupted: worktrees removed")
        raise SystemExit(130) from None
