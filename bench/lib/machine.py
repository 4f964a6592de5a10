"""What a bench records and needs of its machine: GL and EGL probes, the GPU, the CPU topology and
which cores pods get, memory in use and a watch that stops a run above a limit.
"""

from __future__ import annotations

import _thread
import contextlib
import ctypes.util
import glob
import json
import os
import re
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import psutil


MESA_VENDOR_GLOBS = ("/usr/share/glvnd/egl_vendor.d/*mesa*.json", "/etc/glvnd/egl_vendor.d/*mesa*.json")
NVIDIA_VENDOR_FILES = (
    "/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json",
    "/usr/share/glvnd/egl_vendor.d/10_nvidia.json",
)
GL_LIBRARY = re.compile(r"EGL|GLX|GLdispatch|nvidia|mesa|LLVM|_dri\.so|gallium|gbm|glapi")


def gl_probe(extra_env: dict[str, str] | None = None, timeout_s: float = 120.0) -> dict[str, Any]:
    """Return the GL backend/vendor/renderer/version a pod process would render with (made in a
    child process with this environment plus ``extra_env``), or ``{"error": ...}``."""
    code = "import json; from vecsim.engine.batch_render import gl_info; print(json.dumps(gl_info()))"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), **(extra_env or {})}
    try:
        done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return {"error": f"no GL context within {timeout_s:.0f} s"}
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    return json.loads(done.stdout.strip().splitlines()[-1])


def mesa_egl() -> dict[str, Any]:
    """Return whether Mesa's libEGL is on this machine: its glvnd vendor file and library."""
    vendors = sorted({path for pattern in MESA_VENDOR_GLOBS for path in glob.glob(pattern)})
    return {"vendor_files": vendors, "library": ctypes.util.find_library("EGL_mesa"), "present": bool(vendors)}


def gpu_name() -> str | None:
    """Return nvidia-smi's name and driver of the GPU, or None without one."""
    try:
        done = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
            capture_output=True,
            text=True,
            timeout=20,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() or None


def gpu_process_table() -> list[str] | None:
    """Return nvidia-smi's table of the processes on each GPU (type G: a GL context, C: CUDA),
    which shows the GPU the pods render on; None without nvidia-smi."""
    try:
        done = subprocess.run(["nvidia-smi"], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired):
        return None
    lines = done.stdout.splitlines()
    start = next((i for i, line in enumerate(lines) if "Processes:" in line), None)
    return lines[start:] if start is not None else lines[-40:]


def _read(path: str) -> str | None:
    try:
        return Path(path).read_text().strip()
    except OSError:
        return None


def cpu_topology() -> dict[str, Any]:
    """Return the CPUs this process may use and how they sit on physical cores: per CPU its
    package, core and hyperthread siblings (``/sys/devices/system/cpu``), the number of physical
    cores, threads per core, and lscpu's model name and counts."""
    allowed = sorted(os.sched_getaffinity(0))
    cpus: dict[int, dict[str, Any]] = {}
    for cpu in allowed:
        base = f"/sys/devices/system/cpu/cpu{cpu}/topology"
        cpus[cpu] = {
            "package": _read(f"{base}/physical_package_id"),
            "core": _read(f"{base}/core_id"),
            "siblings": _read(f"{base}/thread_siblings_list"),
        }
    cores = {(c["package"], c["core"]) if c["core"] is not None else ("cpu", n) for n, c in cpus.items()}
    lscpu: dict[str, str] = {}
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=20).stdout
        for line in out.splitlines():
            key, _, value = line.partition(":")
            if key.strip() in (
                "Model name",
                "CPU(s)",
                "Thread(s) per core",
                "Core(s) per socket",
                "Socket(s)",
                "NUMA node(s)",
                "Hypervisor vendor",
            ):
                lscpu[key.strip()] = value.strip()
    return {
        "cpus": len(allowed),
        "physical_cores": len(cores),
        "threads_per_core": round(len(allowed) / max(len(cores), 1), 2),
        "per_cpu": {str(n): c for n, c in cpus.items()},
        "lscpu": lscpu,
    }


def cores_first(topology: dict[str, Any]) -> list[int]:
    """The usable CPUs ordered so that one thread of every physical core comes before any second
    thread of a core (hyperthread siblings last), each group in CPU order."""
    seen: dict[tuple[Any, Any], int] = {}
    rounds: list[tuple[int, int]] = []
    for name, cpu in sorted(topology["per_cpu"].items(), key=lambda item: int(item[0])):
        key = (cpu["package"], cpu["core"]) if cpu["core"] is not None else ("cpu", name)
        rounds.append((seen.get(key, 0), int(name)))
        seen[key] = seen.get(key, 0) + 1
    return [cpu for _, cpu in sorted(rounds)]


def split_cores(order: Sequence[int], pinned: int) -> tuple[list[str], list[int]]:
    """Return the CPU lists of ``pinned`` pod cores and the trainer's cores: the first ``pinned``
    of ``order`` and the rest; with too few CPUs the trainer keeps the first and the pods share
    the others (as on a 2-core development machine)."""
    if len(order) > pinned:
        return [str(c) for c in order[:pinned]], sorted(order[pinned:])
    rest = list(order[1:]) or list(order)
    return [str(rest[i % len(rest)]) for i in range(pinned)], [order[0]]


def memory_gib() -> float:
    """Return the machine's memory in use, GiB."""
    return round(psutil.virtual_memory().used / 2**30, 1)


class MemoryWatch:
    """Samples the machine's memory in use every ``every_s`` in a thread while the body runs;
    once it passes ``limit_gib`` it interrupts the main thread, which the body's exit turns into
    :class:`MemoryError` (so the job is torn down before the machine runs out). Keeps the peak."""

    def __init__(self, limit_gib: float, every_s: float = 2.0) -> None:
        self.limit_gib = limit_gib
        self.every_s = every_s
        self.peak_gib = memory_gib()
        self.tripped: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, name="memory-watch", daemon=True)

    def _watch(self) -> None:
        while not self._stop.wait(self.every_s):
            used = memory_gib()
            self.peak_gib = max(self.peak_gib, used)
            if used > self.limit_gib:
                self.tripped = used
                _thread.interrupt_main()
                return

    def __enter__(self) -> MemoryWatch:
        self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, *rest: object) -> None:
        self._stop.set()
        self._thread.join()
        if self.tripped is not None and (kind is None or issubclass(kind, KeyboardInterrupt)):
            raise MemoryError(
                f"{self.tripped} GiB of memory in use, above --max-memory-gib {self.limit_gib}: "
                "run fewer pods, tasks per pod or envs"
            )


RENDER_PROBE_CODE = (
    "import json; from vecsim.engine.batch_render import gl_info; info = gl_info(); "
    "info['libraries'] = sorted({l.split()[-1] for l in open('/proc/self/maps') if '.so' in l.split()[-1]}); "
    "print(json.dumps(info))"
)


def render_probe(env: dict[str, str], timeout_s: float = 120.0) -> dict[str, Any]:
    """Return GL backend/vendor/renderer/version and the GL libraries (EGL, drivers) that a child
    process with this environment plus ``env`` maps once it has a context, or ``{"error": ...}``."""
    full = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), **env}
    try:
        done = subprocess.run(
            [sys.executable, "-c", RENDER_PROBE_CODE], env=full, capture_output=True, text=True, timeout=timeout_s
        )
    except subprocess.TimeoutExpired:
        return {"error": f"no GL context within {timeout_s:.0f} s"}
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr.strip() else f"exit {done.returncode}"}
    info = json.loads(done.stdout.strip().splitlines()[-1])
    info["libraries"] = [path for path in info["libraries"] if GL_LIBRARY.search(Path(path).name)]
    return info


def gpu_egl_env() -> dict[str, str]:
    """The environment of the machine's own EGL: NVIDIA's vendor file alone where there is one."""
    for path in NVIDIA_VENDOR_FILES:
        if Path(path).is_file():
            return {"__EGL_VENDOR_LIBRARY_FILENAMES": path}
    return {}


def software_egl_env() -> tuple[dict[str, str] | None, str]:
    """The environment that makes a process render through Mesa's EGL, and where that Mesa is:
    the device bundle's private copy (``VECSIM_MESA_*`` from ``mesa.sh``), else the machine's.
    None when neither is there."""
    vendor = os.environ.get("VECSIM_MESA_EGL_VENDOR")
    if vendor:
        paths = [os.environ["VECSIM_MESA_LIBRARY_PATH"], os.environ.get("LD_LIBRARY_PATH", "")]
        return {
            "__EGL_VENDOR_LIBRARY_FILENAMES": vendor,
            "LD_LIBRARY_PATH": ":".join(path for path in paths if path),
            "LIBGL_DRIVERS_PATH": os.environ["VECSIM_MESA_DRIVERS"],
        }, "the device bundle's Mesa (private prefix)"
    mesa = mesa_egl()
    if mesa["present"]:
        return {"__EGL_VENDOR_LIBRARY_FILENAMES": mesa["vendor_files"][0]}, "the machine's Mesa"
    return None, "no Mesa EGL: neither the bundle's (source mesa.sh) nor the machine's"


def physical_core_of(topology: dict[str, Any], cpu: str) -> str:
    """``package:core`` of a CPU (the CPU itself where the topology does not say)."""
    info = topology["per_cpu"].get(cpu, {})
    return f"{info.get('package')}:{info.get('core')}" if info.get("core") is not None else f"cpu{cpu}"
