"""The controller needs no simulator: it learns the tasks from the job and the task catalogue
(``vecsim.suites``), never from the engine's registry.

- ``vecsim controller`` runs in a process where importing mujoco, robosuite, torch, LIBERO or any
  ``vecsim.engine`` module fails; it accepts a job, a real pod (this venv, simulator and all)
  registers and builds its assignment, and a client resets and steps the job's envs through the
  controller's routing table. It refuses a job of unknown or mismatched tasks with 422, naming them.
- A task the pods cannot serve (CartPole's Discrete actions under cameras) is the pod's to refuse:
  the controller, which makes no env, names the pod's refusal in its readiness.
- The catalogue and the engine's registry list the same suites and task ids, in the same order.
"""

from __future__ import annotations

import sys

import httpx
import numpy as np
import pytest
from support.service_procs import Server, clean_env, free_port, pod_server, running, wait_until

from service.controller.jobs import check_job
from vecsim import suites
from vecsim.client import StageClient
from vecsim.config import JobSpec
from vecsim.engine import tasks as registry

BLOCKED = ("mujoco", "robosuite", "torch", "libero", "vecsim.engine")
# ``python -c`` with every blocked module set to None in sys.modules: importing one raises ImportError.
WITHOUT_SIMULATOR = [
    sys.executable,
    "-c",
    f"import sys\nfor name in {BLOCKED!r}:\n    sys.modules[name] = None\n"
    "from service.cli import main\nsys.exit(main(sys.argv[1:]))",
]
JOB = {
    "job_id": "no-sim",
    "tasks": ["gym/Pendulum-v1"],
    "group_size": 2,
    "num_stages": 1,
    "pods_per_stage": 1,
    "camera": {"names": []},
    "max_episode_steps": 5,
}


def routing_ready(url: str) -> bool:
    answer = httpx.get(f"{url}/v1/routing", timeout=5)
    return answer.status_code == 200 and answer.json()["ready"]


def readiness(url: str) -> str:
    return httpx.get(f"{url}/readyz", timeout=5).text


@pytest.mark.slow
def test_a_controller_that_cannot_import_the_simulator_serves_a_job_a_real_pod_runs(tmp_path):
    port = free_port()
    argv = ["controller", "--host", "127.0.0.1", "--port", str(port), "--heartbeat-interval", "0.5"]
    controller = Server("controller", argv, port, clean_env(), tmp_path / "controller.log", program=WITHOUT_SIMULATOR)
    with running(controller):
        mixed = {**JOB, "tasks": ["libero_10/0", "tiny/lift"]}
        refused = httpx.put(f"{controller.url}/v1/job", json=mixed, timeout=30)
        assert refused.status_code == 422 and "'tiny/lift' has other observation/action spaces" in refused.text
        unknown = httpx.put(f"{controller.url}/v1/job", json={**JOB, "tasks": ["libero_10/10"]}, timeout=30)
        assert unknown.status_code == 422 and "libero_10/10" in unknown.text
        camera = {"names": ["render"], "height": 8, "width": 8}
        cartpole = {**JOB, "tasks": ["gym/CartPole-v1"], "camera": camera}
        assert httpx.put(f"{controller.url}/v1/job", json=cartpole, timeout=30).status_code == 200
        agent = {"CONTROLLER_URL": controller.url, "VECSIM_HEARTBEAT_INTERVAL_S": "0.5", "VECSIM_MAX_ENVS": "2"}
        with running(pod_server("sim-0", tmp_path, **agent)):
            # A first push can find the pod not yet listening (a connect error); the controller
            # pushes again, and the pod's refusal is what readiness must name in the end.
            wait_until(lambda: "gym/CartPole-v1" in readiness(controller.url), "the pod's refusal named", timeout_s=120)
            assert "last push failed" in readiness(controller.url)
            assert httpx.put(f"{controller.url}/v1/job", json=JOB, timeout=30).status_code == 200
            wait_until(lambda: routing_ready(controller.url), "the job's routing table ready", timeout_s=120)
            with StageClient.from_controller(controller.url, timeout_s=10, wait_ready_s=60) as client:
                client.reset_trajectories([("gym/Pendulum-v1", 0), ("gym/Pendulum-v1", 1)], ["a", "b"])
                first = client.reset_stage(0).result()
                stepped = client.step_stage(0, {key: np.zeros(1, np.float32) for key in first.traj_keys}).result()
        assert controller.alive()
    assert sorted(first.traj_keys) == ["a", "b"] and sorted(stepped.traj_keys) == ["a", "b"]
    assert stepped.errors == [] and np.isfinite(stepped.reward).all()
    assert "ImportError" not in controller.log_text() and "ModuleNotFoundError" not in controller.log_text()


def test_the_catalogue_lists_the_registrys_suites_and_tasks_in_order():
    assert suites.suite_names() == registry.list_suites()
    for suite in suites.suite_names():
        assert suites.suite_task_ids(suite) == [spec.task_id for spec in registry.suite_tasks(suite)], suite


def test_the_catalogue_knows_suite_tasks_and_any_gym_id_and_nothing_else():
    assert all(suites.is_known(t) for t in ("libero_90/89", "robosuite/Door", "tiny/lift", "gym/Foo-v0", "gym:Foo-v0"))
    assert not any(suites.is_known(t) for t in ("libero_10/10", "libero_10/01", "tiny/Lift", "gym/", "nope/x"))


def test_tasks_of_one_family_share_spaces_and_two_families_are_refused_naming_both():
    job = JobSpec.model_validate({**JOB, "tasks": ["libero_10/0", "libero_90/3"]})
    assert check_job(job, [])[1] == []
    tasks, problems = check_job(JobSpec.model_validate({**JOB, "tasks": ["robosuite/Lift", "gym:Pendulum-v1"]}), [])
    assert tasks == ["robosuite/Lift", "gym/Pendulum-v1"]
    assert (
        len(problems) == 1
        and "'gym/Pendulum-v1' has other observation/action spaces than 'robosuite/Lift'" in problems[0]
    )


def test_a_suite_resolves_to_its_tasks_and_an_unknown_suite_names_the_known_ones():
    spec = {key: value for key, value in JOB.items() if key != "tasks"}
    tasks, problems = check_job(JobSpec.model_validate({**spec, "suite": "tiny"}), [])
    assert tasks == ["tiny/lift", "tiny/stack", "tiny/door"] and problems == []
    _, problems = check_job(JobSpec.model_validate({**spec, "suite": "nope"}), [])
    assert problems == [f"suite: unknown suite 'nope'; use one of {suites.suite_names()} or list task ids in 'tasks'"]
