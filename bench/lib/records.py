"""Helpers shared by the benchmarks: where results go, the machine they ran on, and how they print.

Every benchmark is one command (``python bench/bench_<name>.py``) that ends by calling
:func:`write_result`: the full record goes to ``out/bench/<name>.json`` and one line
``RESULT {json}`` (the summary, machine-readable) goes to stdout.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

RESULT_PREFIX = "RESULT "
REPO_ROOT = Path(__file__).resolve().parents[2]


def out_dir() -> Path:
    """Return ``out/bench`` under the repository root, created if missing."""
    path = REPO_ROOT / "out" / "bench"
    path.mkdir(parents=True, exist_ok=True)
    return path


def img_dir() -> Path:
    """Return ``docs/img`` under the repository root (plots for docs/benchmarks.md), created if missing."""
    path = REPO_ROOT / "docs" / "img"
    path.mkdir(parents=True, exist_ok=True)
    return path


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def machine_info() -> dict[str, Any]:
    """Describe where and when a benchmark ran.

    Returns:
        date (UTC, ISO 8601), host, cpu model, logical cores, 1-minute load average at the
        end of the run (others share this machine), python, platform and numpy versions.
    """
    import numpy as np

    return {
        "date": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "host": platform.node(),
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "load_avg_1m": round(os.getloadavg()[0], 2),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "numpy": np.__version__,
    }


def spread(values: Sequence[float]) -> dict[str, float]:
    """Return median, min, max and count of ``values`` (one per round)."""
    return {
        "median": statistics.median(values),
        "min": min(values),
        "max": max(values),
        "n": len(values),
    }


def with_flags(defaults: dict[str, Any], args: Any) -> dict[str, Any]:
    """Return ``defaults`` with each flag given on the command line (an attribute of ``args`` of
    the same name that is not None) taking precedence."""
    return {key: value if getattr(args, key, None) is None else getattr(args, key) for key, value in defaults.items()}


def command_line() -> str:
    """Return the command that ran this benchmark, relative to the repository root."""
    script = Path(sys.argv[0]).resolve()
    try:
        script = script.relative_to(REPO_ROOT)
    except ValueError:
        pass
    return " ".join(["python", str(script), *sys.argv[1:]])


def write_record(record: dict[str, Any], out: Path) -> None:
    """Write ``record`` as JSON to ``out`` (its folder made), over what an earlier call wrote: a
    bench that writes after every measurement leaves a record however early it is cut short."""
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1) + "\n")


def write_result(name: str, summary: dict[str, Any], details: dict[str, Any] | None = None) -> Path:
    """Write ``out/bench/<name>.json`` and print the one ``RESULT {json}`` line.

    The file holds the summary, the details (per-round numbers) and the machine; the line holds
    the summary, the machine and the command.

    Returns:
        the path of the JSON file.
    """
    record = {"name": name, "command": command_line(), "machine": machine_info(), **summary}
    path = out_dir() / f"{name}.json"
    path.write_text(json.dumps({**record, "details": details or {}}, indent=2) + "\n")
    print(RESULT_PREFIX + json.dumps(record, separators=(",", ":")), flush=True)
    return path
