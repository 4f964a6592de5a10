"""``vecsim up -c configs/<job>.yaml``: run a job locally until Ctrl-C."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time
from types import FrameType

from service.probes import PROBE_PATHS, quiet_probe_logs
from vecsim.auth import TOKEN_ENV
from vecsim.config import ConfigError, load_job_config

from .job import JobRejectedError, LocalJob
from .status import format_status


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="vecsim up",
        description="Start a job locally: the controller and N pods (sim-0..sim-N-1) as supervised processes. "
        "Ctrl-C stops them all.",
    )
    p.add_argument("-c", "--config", required=True, help="job config YAML, e.g. configs/tiny.yaml")
    p.add_argument("--log-dir", help="where each process's log goes (default: a new temporary directory)")
    p.add_argument("--status-every", type=float, default=5.0, help="seconds between status tables (default 5)")
    p.add_argument("--grace", type=float, default=None, help="seconds from SIGTERM to SIGKILL at shutdown")
    p.add_argument("--log-level", default="info", help="logging level of the runner (default info)")
    return p


def main(argv: list[str]) -> int:
    """Runs the job until SIGINT/SIGTERM. Returns 0 after a clean stop, 1 if the controller refused
    the job, 2 for a bad config."""
    args = _parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # The runner's own watching (probes, the status table's reads) at DEBUG; PUT /v1/job stays.
    quiet_probe_logs(PROBE_PATHS | {"/v1/pods", "/v1/routing"})
    try:
        config = load_job_config(args.config)
    except ConfigError as exc:
        print(f"vecsim up: {exc}", file=sys.stderr)
        return 2

    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)

    job = LocalJob(config, log_dir=args.log_dir)
    try:
        job.start()
    except JobRejectedError as exc:
        print(f"vecsim up: {exc}", file=sys.stderr)
        return 1
    code = 0
    try:
        print(f"job {config.job.job_id}: controller {job.controller_url}, logs in {job.log_dir}", flush=True)
        print(f"  watch it: curl {job.controller_url}/v1/pods ; curl {job.controller_url}/v1/routing", flush=True)
        if not os.environ.get(TOKEN_ENV):
            print(f"  trainers need the job's token: export {TOKEN_ENV}=$(cat {_write_token(job)})", flush=True)
        shown, was_ready, next_table = "", False, 0.0
        while not stop.wait(0.5):
            if job.job_error is not None:
                print(f"vecsim up: {job.job_error}", file=sys.stderr)
                code = 1
                break
            now = time.monotonic()
            if now < next_table:
                continue
            next_table = now + args.status_every
            table = format_status(job.status())
            if table != shown:
                print(table + "\n", flush=True)
                shown = table
            ready = job.is_ready()
            if ready and not was_ready:
                print(f"job {config.job.job_id} is ready: curl {job.controller_url}/v1/routing", flush=True)
            was_ready = ready
    finally:
        print("stopping every process...", flush=True)
        job.stop(args.grace)
        print("stopped.", flush=True)
    return code


def _write_token(job: LocalJob) -> str:
    """Write the token the job made for itself to ``<log dir>/token``, readable by its owner
    only. Returns the file's path."""
    path = job.log_dir / "token"
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as out:
        out.write(job.token + "\n")
    return str(path)
