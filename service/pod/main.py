"""``vecsim pod``: run one sim pod under uvicorn.

Standalone (no controller, generation 0)::

    vecsim pod --config configs/x.yaml --stage 0 --tasks tiny/lift,tiny/stack --group-size 2 --port 8100
    vecsim pod --assignment assignment.json --port 8100

Under a controller: no assignment flags, ``CONTROLLER_URL`` (or ``--controller-url``) set; the
pod registers and waits for the controller to push its assignment.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import uvicorn
from pydantic import ValidationError

from service.errors import RefusedError
from service.probes import quiet_probe_logs
from service.serving import uvicorn_limits
from vecsim.config import Assignment, ConfigError, JobSpec, load_job_config
from vecsim.engine.tasks import normalize_task_id, suite_tasks
from vecsim.envsettings import SettingsError
from vecsim.plan import Plan, slot_contents

from .app import create_app
from .settings import PodSettings
from .state import check_assignment

log = logging.getLogger(__name__)


def build_parser() -> argparse.ArgumentParser:
    """The ``vecsim pod`` argument parser; flags override the environment variables."""
    parser = argparse.ArgumentParser(
        prog="vecsim pod",
        description="Run one sim pod. Identity and limits come from the environment "
        "(POD_NAME, POD_IP, VECSIM_PORT, VECSIM_ADVERTISE_URL, CONTROLLER_URL, VECSIM_MAX_ENVS, ...); "
        "flags override them.",
    )
    standalone = parser.add_argument_group("standalone assignment (generation 0, no controller needed)")
    standalone.add_argument("--config", type=Path, help="job config YAML (cameras, render preset, seed, tasks)")
    standalone.add_argument("--stage", type=int, default=0, help="stage id of this pod (default 0)")
    standalone.add_argument("--tasks", help="comma-separated task ids (default: the config's tasks or suite)")
    standalone.add_argument("--group-size", type=int, help="envs per task (default: the config's group_size)")
    standalone.add_argument("--assignment", type=Path, help="an Assignment JSON file to serve as is")

    identity = parser.add_argument_group("identity and serving (override the environment)")
    identity.add_argument("--name", help="pod name (POD_NAME, default sim-0)")
    identity.add_argument(
        "--host", help="address to listen on (VECSIM_HOST; default 0.0.0.0 if POD_IP is set, else 127.0.0.1)"
    )
    identity.add_argument("--port", type=int, help="port to listen on (VECSIM_PORT, default 8100)")
    identity.add_argument(
        "--advertise-url", help="URL others reach this pod at (VECSIM_ADVERTISE_URL, default http://$POD_IP:$PORT)"
    )
    identity.add_argument("--controller-url", help="controller to register with (CONTROLLER_URL)")
    identity.add_argument("--max-envs", type=int, help="most envs this pod hosts (VECSIM_MAX_ENVS, default 64)")
    identity.add_argument(
        "--heartbeat-interval",
        type=float,
        dest="heartbeat_interval_s",
        help="seconds between heartbeats (VECSIM_HEARTBEAT_INTERVAL_S, default 1.0)",
    )
    identity.add_argument(
        "--max-body-bytes", type=int, help="largest request body (VECSIM_MAX_BODY_BYTES, default 64 MiB)"
    )
    identity.add_argument("--access-log", action="store_true", default=None, help="log every request")
    identity.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    return parser


def standalone_assignment(args: argparse.Namespace, pod: str) -> Assignment | None:
    """The assignment the flags describe, for pod ``pod`` at generation 0; None when no
    assignment flag is given.

    Raises:
        ConfigError: the config file cannot be used.
        ValueError: the flags do not make a valid assignment (the message names what is wrong).
    """
    if args.assignment is not None:
        if args.config or args.tasks or args.group_size is not None:
            raise ValueError("--assignment is a whole assignment: give it without --config/--tasks/--group-size")
        try:
            return Assignment.model_validate_json(args.assignment.read_text())
        except OSError as exc:
            raise ValueError(f"--assignment {args.assignment}: cannot read: {exc}") from None
        except ValidationError as exc:
            raise ValueError(f"--assignment {args.assignment}: {exc}") from None
    if args.config is None and args.tasks is None:
        return None
    if args.stage < 0:
        raise ValueError(f"--stage must be >= 0, got {args.stage}")
    if args.group_size is not None and args.group_size < 0:
        raise ValueError(f"--group-size must be >= 0, got {args.group_size}")
    tasks = tuple(_split(args.tasks)) if args.tasks else None
    job = load_job_config(args.config).job if args.config else JobSpec(tasks=tasks or ())
    # One pod holds a whole stage: lay the stage's blocks out as the controller's plan would.
    update: dict[str, object] = {"num_stages": args.stage + 1, "pods_per_stage": 1}
    if tasks:
        update["tasks"] = tasks
    if args.group_size is not None:
        update["group_size"] = args.group_size
    job = JobSpec.model_validate({**job.model_dump(), **update})
    if job.tasks:
        task_ids = [normalize_task_id(task_id) for task_id in job.tasks]
    else:
        task_ids = [spec.task_id for spec in suite_tasks(job.suite)]
    slots = slot_contents(job, task_ids)
    return Plan(generation=0, job=job, slots=tuple(slots)).assignment_for(slots[args.stage], pod)


def _split(csv: str) -> list[str]:
    return [part.strip() for part in csv.split(",") if part.strip()]


def main(argv: list[str] | None = None) -> int:
    """Run a pod until SIGINT/SIGTERM.

    Returns:
        0 after a clean shutdown, 2 for unusable flags, settings or config.
    """
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # httpx logs every request at INFO: a heartbeat a second would drown the pod's own log.
    logging.getLogger("httpx").setLevel(logging.WARNING)
    quiet_probe_logs()
    try:
        settings = PodSettings.from_env(
            name=args.name,
            host=args.host,
            port=args.port,
            advertise_url=args.advertise_url,
            controller_url=args.controller_url,
            max_envs=args.max_envs,
            heartbeat_interval_s=args.heartbeat_interval_s,
            max_body_bytes=args.max_body_bytes,
            access_log=args.access_log,
            log_level=args.log_level,
        )
        assignment = standalone_assignment(args, settings.name)
        if assignment is not None:
            check_assignment(settings, assignment)
            settings = settings.model_copy(update={"assignment": assignment})
    except RefusedError as exc:
        print(f"vecsim pod: {exc.detail}", file=sys.stderr)
        return 2
    except (SettingsError, ConfigError, ValueError, KeyError) as exc:
        print(f"vecsim pod: {exc}", file=sys.stderr)
        return 2
    if settings.assignment is None and not settings.controller_url:
        log.info("no assignment and no CONTROLLER_URL: waiting for PUT /v1/assignment at %s", settings.url)
    config = uvicorn.Config(
        create_app(settings),
        host=settings.bind_host,
        port=settings.port,
        access_log=settings.access_log,
        log_level=settings.log_level,
        log_config=None,
        timeout_graceful_shutdown=10,
        **uvicorn_limits(settings.header_timeout_s, settings.keep_alive_s, settings.max_connections),
    )
    server = uvicorn.Server(config)
    server.run()
    return 0 if server.started else 1
