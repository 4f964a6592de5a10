"""``vecsim controller``: serve the controller with uvicorn."""

from __future__ import annotations

import argparse
import logging
import sys

import uvicorn

from service.probes import quiet_probe_logs
from service.serving import uvicorn_limits
from vecsim.auth import token_from_env
from vecsim.config import ConfigError, load_job_config

from .app import create_app
from .settings import ControllerSettings


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="vecsim controller", description="Run the vecsim controller.")
    p.add_argument("-c", "--config", help="job config YAML (configs/*.yaml): the job and the controller section")
    p.add_argument("--host", help="address to listen on (default: the config's, else 127.0.0.1)")
    p.add_argument("--port", type=int, help="port to listen on (default: the config's, else 8000)")
    p.add_argument(
        "--heartbeat-interval", type=float, dest="heartbeat_interval_s", help="seconds between pod heartbeats"
    )
    p.add_argument("--heartbeat-ttl", type=float, dest="heartbeat_ttl_s", help="drop pods silent this long (s)")
    p.add_argument("--reconcile-interval", type=float, dest="reconcile_interval_s", help="seconds between passes")
    p.add_argument(
        "--adopt-grace", type=float, dest="adopt_grace_s", help="wait this long for pod reports at start (s)"
    )
    p.add_argument("--max-body-bytes", type=int, dest="max_body_bytes", help="largest request body (default 1 MiB)")
    p.add_argument(
        "--header-timeout", type=float, dest="header_timeout_s", help="close a connection silent this long (s)"
    )
    p.add_argument("--max-connections", type=int, dest="max_connections", help="connections kept at most")
    p.add_argument("--access-log", action="store_true", default=None, help="log every request")
    p.add_argument("--log-level", default="info", help="logging level (default info)")
    return p


def main(argv: list[str]) -> int:
    """Runs the controller until it is stopped. Returns the exit code (2: bad config or flags).

    The shared token comes from the environment (``VECSIM_TOKEN``), never from a flag, which
    anyone on the machine could read in the process list.
    """
    args = _parser().parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    quiet_probe_logs()
    overrides = {k: v for k, v in vars(args).items() if k not in ("config",)}
    try:
        overrides["token"] = token_from_env()
        if args.config:
            settings = ControllerSettings.from_job_config(load_job_config(args.config), **overrides)
        else:
            settings = ControllerSettings.model_validate({k: v for k, v in overrides.items() if v is not None})
        app = create_app(settings)
    except (ConfigError, ValueError) as exc:
        print(f"vecsim controller: {exc}", file=sys.stderr)
        return 2
    uvicorn.run(
        app,
        host=settings.host,
        port=settings.port,
        access_log=settings.access_log,
        log_level=settings.log_level,
        timeout_graceful_shutdown=5,
        **uvicorn_limits(settings.header_timeout_s, settings.keep_alive_s, settings.max_connections),
    )
    return 0
