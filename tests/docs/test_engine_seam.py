"""The engine seam (vecsim/engine/base.py), each rule read from the code itself:

- nothing above the pod's engine (service/, and every ``vecsim`` module outside
  ``vecsim.engine``) imports a concrete engine, in an ``import`` statement at any depth or at run
  time: the pod reaches one through ``vecsim.engine.base.engine_kind`` only;
- the engines the registry knows are the names a job may set, and each engine's module builds
  the engine of its name;
- each engine has every call the pod makes of a :class:`PodEngine`, with the same parameters;
- an engine name no registry knows is a config error naming ``job.engine``;
- exporting an ``mjwarp`` scene (the CPU stack's job) loads no warp.
"""

from __future__ import annotations

import ast
import importlib.util
import inspect
import typing
from pathlib import Path

import pytest
from docs.test_layering import ROOT, loaded_after_importing, offenders, python_files

from service.pod.settings import PodSettings
from service.pod.state import check_assignment
from vecsim.config import Assignment, CameraConfig, ConfigError, EngineName, TaskBlock, load_job_config
from vecsim.engine.base import ENGINES, PodEngine, engine_kind
from vecsim.engine.errors import InvalidRequestError

# The modules that are one engine or another's insides: what only the registry imports.
CONCRETE = (
    "vecsim.engine.cpu",
    "vecsim.engine.vector_env",
    "vecsim.engine.pool",
    "vecsim.engine.supervisor",
    "vecsim.engine.answers",
    "vecsim.engine.worker",
    "vecsim.engine.protocol",
    "vecsim.engine.mjwarp",
    "vecsim.engine.TaskGroupedVectorEnv",
)


def above_the_engine() -> list:
    return [
        *python_files("service"),
        *(p for p in python_files("vecsim") if ROOT / "vecsim" / "engine" not in p.parents),
    ]


def test_nothing_above_the_engine_imports_a_concrete_engine():
    assert offenders(above_the_engine(), CONCRETE) == {}


def test_importing_the_pod_loads_no_concrete_engine():
    loaded = loaded_after_importing(python_files("service/pod"), "vecsim.engine")
    assert sorted(m for m in loaded if any(m == c or m.startswith(c + ".") for c in CONCRETE)) == []


def test_the_registry_knows_exactly_the_engines_a_job_may_name():
    assert sorted(ENGINES) == sorted(typing.get_args(EngineName))


@pytest.mark.parametrize("name", sorted(ENGINES))
def test_each_engine_has_every_call_the_pod_makes_with_the_same_parameters(name):
    kind = engine_kind(name)
    assert kind.name == name
    engine_class = typing.get_type_hints(kind.build)["return"]
    assert engine_class is not PodEngine
    calls = [n for n, v in vars(PodEngine).items() if callable(v) and not n.startswith("_")]
    assert {"reset_envs", "chunk_step_envs", "frame", "close"} <= set(calls)
    for call in calls:
        want = list(inspect.signature(getattr(PodEngine, call)).parameters.values())
        have = list(inspect.signature(getattr(engine_class, call)).parameters.values())
        assert [(p.name, p.kind, p.default) for p in have] == [(p.name, p.kind, p.default) for p in want], (name, call)


@pytest.mark.parametrize("name", sorted(ENGINES))
def test_each_engine_builds_a_spare_pod_that_is_a_pod_engine(name):
    """A spare pod (no tasks) on each engine: built without its packages' heavy parts, it has
    every attribute and call of a PodEngine, and an empty call is a no-op."""
    assignment = Assignment(generation=0, pod="sim-0", stage_id=0, engine=name, camera=CameraConfig(names=()))
    engine = engine_kind(name).build(assignment)
    try:
        assert isinstance(engine, PodEngine)
        assert engine.num_envs == 0
        obs, info = engine.reset_envs([], [])
        assert list(info["success"]) == [] and info["errors"] == []
    finally:
        engine.close()


def test_an_unknown_engine_is_a_config_error_naming_the_field(tmp_path):
    path = tmp_path / "job.yaml"
    path.write_text("job:\n  tasks: [tiny/lift]\n  engine: physx\n")
    with pytest.raises(ConfigError, match=r"job\.engine: Input should be 'cpu' or 'mjwarp'"):
        load_job_config(path)


def test_a_job_without_an_engine_runs_on_the_cpu_engine(tmp_path):
    path = tmp_path / "job.yaml"
    path.write_text("job:\n  tasks: [tiny/lift]\n")
    assert load_job_config(path).job.engine == "cpu"


@pytest.mark.skipif(importlib.util.find_spec("mujoco_warp") is not None, reason="the mjwarp extra is installed here")
def test_a_pod_without_the_mjwarp_extra_refuses_an_mjwarp_assignment_naming_the_engine():
    settings = PodSettings(name="sim-0")
    assignment = Assignment(
        generation=1,
        pod="sim-0",
        stage_id=0,
        engine="mjwarp",
        tasks=(TaskBlock(task_id="libero_10/0", env_start=0, num_envs=2),),
    )
    with pytest.raises(InvalidRequestError, match=r"^engine: the mjwarp engine needs the mjwarp extra"):
        check_assignment(settings, assignment)


def test_exporting_a_scene_loads_no_warp():
    """The CPU pod's install (the ``pod`` extra: the image's CPU venv, which exports the scenes at
    build time) has no warp: every vecsim module the export imports, at any depth of
    ``vecsim/engine/mjwarp/scene.py``, loads none."""
    scene = ROOT / "vecsim" / "engine" / "mjwarp" / "scene.py"
    imported = {scene}
    for node in ast.walk(ast.parse(scene.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("vecsim"):
            path = ROOT / Path(*node.module.split("."))
            imported.add(path / "__init__.py" if path.is_dir() else path.with_suffix(".py"))
    assert ROOT / "vecsim" / "engine" / "mjwarp" / "tables.py" in imported
    assert loaded_after_importing(sorted(imported), "warp") == []
