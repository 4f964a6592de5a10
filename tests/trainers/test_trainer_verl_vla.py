"""verl-vla's own config, env worker, env manager and eval drive vecsim's verl-vla env over a real LIBERO job.

verl-vla is not on the package index: :mod:`verl_vla_code` re-enacts its code line by line at
8a18e3f (each block citing its lines) and registers it under verl-vla's module names, so that
docs/trainers.md's instructions run as pasted: ``register()`` puts vecsim's ``LiberoEnv`` where
verl-vla's env worker imports its own, and the documented yaml builds verl-vla's typed config
through hydra's ``instantiate``. The job: train envs on two pods (libero_spatial/0 and /3, episode
limit 20), eval envs on a third (both tasks, limit 1, no settle steps, so a whole benchmark of 100
episodes stays cheap); 32x32 cameras, K = 8.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import yaml
from gymnasium.error import ClosedEnvironmentError
from hydra.errors import InstantiationException
from omegaconf import OmegaConf
from support.service_procs import PodSpec, RunningPod, assignment, standalone_pods
from support.wire_http import metric

import vecsim.trainers.verl_vla as adapter
from vecsim.config import CameraConfig, LiberoProtocol

pytestmark = pytest.mark.libero

verl_vla_code = pytest.importorskip("verl_vla_code", reason="needs hydra-core (test extras)")
EnvWorker, EnvWorkerConfig, SimulatorConfig = (
    verl_vla_code.EnvWorker,
    verl_vla_code.EnvWorkerConfig,
    verl_vla_code.SimulatorConfig,
)

LIMIT = 20  # the train envs' episode limit: the third chunk of 8 ends every episode at its 4th action
K = 8
TASKS = ("libero_spatial/0", "libero_spatial/3")
CAMERA = CameraConfig(height=32, width=32)
DOCS = Path(__file__).resolve().parents[2] / "docs" / "trainers.md"


def _doc_blocks(language: str) -> list[str]:
    """The ``language`` code blocks of docs/trainers.md's verl-vla section, as written there."""
    section = DOCS.read_text().split("## verl-vla", 1)[1].split("\n## ", 1)[0]
    return re.findall(rf"```{language}\n(.*?)```", section, re.DOTALL)


@pytest.fixture(scope="module", autouse=True)
def verl_vla() -> Iterator[None]:
    """verl-vla's modules (re-enacted), with the user's lines from docs/trainers.md run as pasted."""
    with verl_vla_code.install():
        try:
            for block in _doc_blocks("python"):
                exec(compile(block, str(DOCS), "exec"), {})
            yield
        finally:
            for name in ("LiberoEnv", "VecsimSimulatorConfig"):  # made from the re-enactments
                vars(adapter).pop(name, None)


@pytest.fixture(scope="module")
def pods(tmp_path_factory) -> Iterator[list[RunningPod]]:
    train = [
        PodSpec(f"sim-{i}", 0, [(task, 1)], camera=CAMERA, max_episode_steps=LIMIT) for i, task in enumerate(TASKS)
    ]
    evaluation = assignment(
        "sim-2",
        [(task, 1) for task in TASKS],
        job_id="trainer-tests",
        camera=CAMERA,
        render="lean",
        max_episode_steps=1,
        libero=LiberoProtocol(settle_steps=0),
    )
    with standalone_pods([*train, evaluation], tmp_path_factory.mktemp("pods")) as running:
        yield running


def worker_config(
    pods, *, modes=("train",), auto_reset: bool = False, whole_chunks: bool = True, vecsim: bool = True
) -> Any:
    """verl-vla's typed env worker config from docs/trainers.md's yaml, the job's pods in place of
    its controller, built as verl-vla builds it (train_cluster/config.py:139-141)."""
    documented = yaml.safe_load(_doc_blocks("yaml")[0])["env"]["env_worker"]
    simulator = dict(documented["simulator"])
    settings = {k: v for k, v in simulator.pop("vecsim").items() if k != "controller_url"}
    settings.update(pod_urls=[p.url for p in pods], seed=3, whole_chunks=whole_chunks)
    if vecsim:
        simulator["vecsim"] = settings
    else:
        simulator["_target_"] = "verl_vla.workers.env.config.SimulatorConfig"  # verl-vla's own, unchanged
    return verl_vla_code.env_worker_config(
        {
            "_target_": "verl_vla.workers.env.config.EnvWorkerConfig",
            "auto_reset": auto_reset,
            "num_envs": 2,
            "modes": list(modes),
            "simulator": simulator,
            "action_execution": {"_target_": "verl_vla.envs.action_executor.ActionExecutionConfig", "mode": "serial"},
            "teleop": {"_target_": "verl_vla.teleop.config.TeleopConfig", "enable": False},
            "recorder": {"_target_": "verl_vla.recorder.config.RecorderConfig", "enable": False},
        }
    )


def make_worker(pods, **kwargs: Any) -> Any:
    worker = EnvWorker(worker_config(pods, **kwargs), pipeline_stage_num=1)
    worker.init_worker()
    return worker


def make_env(pods, *, rank: int = 0, world_size: int = 1, only_eval: bool = False, **kwargs: Any) -> Any:
    """One simulator as verl-vla's env manager builds it (env_manager.py:359)."""
    from verl_vla.envs.libero.libero_env import LiberoEnv  # what env_worker.py:181 imports

    worker = EnvWorker(worker_config(pods, **kwargs), pipeline_stage_num=1)
    return LiberoEnv(worker.simulator_cfg, rank, world_size, stage_id=0, stage_num=1, only_eval=only_eval)


@pytest.fixture
def env(pods) -> Iterator[Any]:
    made = make_env(pods)
    yield made
    made.close()


def step_requests(pods) -> list[float]:
    return [metric(p.url, "vecsim_pod_step_seconds_count") for p in pods]


def resets(pods) -> list[float]:
    return [metric(p.url, "vecsim_pod_env_resets") for p in pods]


def chunks(n: int, seed: int = 0, k: int = K) -> list[torch.Tensor]:
    rng = np.random.default_rng(seed)
    return [torch.as_tensor(rng.uniform(-0.3, 0.3, (2, k, 7)).astype(np.float32)) for _ in range(n)]


def _reset_to(env: Any, global_ids: list[int]) -> dict[str, Any]:
    """A reset of both envs to chosen states, through the hook verl-vla's replay uses (extra)."""
    obs = [
        env.env_reset(env_ids=[i], extra={"info.reset_state_id": np.array([gid])}) for i, gid in enumerate(global_ids)
    ]
    return {key: [item for o in obs for item in o[key]] for key in obs[0]}


def _equal(a: dict[str, Any], b: dict[str, Any]) -> None:
    assert a.keys() == b.keys()
    for key, value in a.items():
        if isinstance(value, torch.Tensor):
            assert value.dtype == b[key].dtype and torch.equal(value, b[key]), key
        else:
            assert np.array_equal(np.asarray(value), np.asarray(b[key])), key


# -- verl-vla's typed config ---------------------------------------------------------------------


def test_the_documented_config_is_verl_vlas_typed_config_with_the_jobs_settings(pods):
    cfg = worker_config(pods)
    assert isinstance(cfg, EnvWorkerConfig) and isinstance(cfg.simulator, SimulatorConfig)
    assert cfg.simulator.vecsim == adapter.VecsimSettings(pod_urls=[p.url for p in pods], seed=3)
    # verl-vla's own class refuses the block (workers/env/config.py:33-41): the documented class is needed.
    with pytest.raises(TypeError, match="vecsim"):
        SimulatorConfig(vecsim={"pod_urls": [pods[0].url]})


def test_an_unknown_vecsim_setting_is_refused_naming_it(pods):
    cfg = yaml.safe_load(_doc_blocks("yaml")[0])["env"]["env_worker"]["simulator"]
    cfg["vecsim"] = {"pod_urls": [pods[0].url], "sed": 3}
    # hydra's instantiate, as verl-vla calls it, carries the adapter's message.
    with pytest.raises(InstantiationException, match=r"simulator.vecsim: unknown setting\(s\) \[\\?'sed\\?'\]"):
        verl_vla_code.env_worker_config({"_target_": "verl_vla.workers.env.config.EnvWorkerConfig", "simulator": cfg})


def test_without_a_vecsim_block_the_environment_names_the_job(pods, monkeypatch):
    monkeypatch.setenv(adapter.POD_URLS_ENV, ",".join(p.url for p in pods))
    made = make_env(pods, vecsim=False)
    try:
        assert made.vla.num_envs == 4 and made.settings.seed == 0
    finally:
        made.close()
    monkeypatch.delenv(adapter.POD_URLS_ENV)
    with pytest.raises(ValueError, match=r"\$VECSIM_CONTROLLER_URL and \$VECSIM_POD_URLS: give exactly one"):
        make_env(pods, vecsim=False)


# -- the env worker: train, eval, train ----------------------------------------------------------


def _eval_rollout(worker: Any):
    """One eval rollout: one chunk of one action ends every eval episode (the eval pod's limit is 1)."""
    return lambda reset_output: [worker.env_interact_step(chunks(1, seed=9, k=1)[0], mode="eval")]


def test_train_eval_train_in_one_run_finishes_eval_and_leaves_train_state_undisturbed(pods):
    both = make_worker(pods, modes=("train", "eval"))
    try:
        first = both.reset_env(mode="train")
        both.env_interact_step(chunks(1, seed=1)[0])
        records, rollouts = verl_vla_code.train_cluster_eval(both, _eval_rollout(both))
        benchmark = both.get_eval_benchmark_size()
        after_eval = both.env_interact_step(chunks(1, seed=2)[0])
    finally:
        both.close()
    train_only = make_worker(pods)
    try:
        assert torch.equal(train_only.reset_env(mode="train")["observation.state"], first["observation.state"])
        train_only.env_interact_step(chunks(1, seed=1)[0])
        undisturbed = train_only.env_interact_step(chunks(1, seed=2)[0])
    finally:
        train_only.close()
    _equal(after_eval, undisturbed)
    # Every benchmark episode accepted once, numbered as verl-vla numbers its list: task 0's 50
    # states, then task 3's; the two eval envs walk them in 50 rollouts.
    assert benchmark == 100 and rollouts == 50
    assert sorted(r["eval_episode_id"] for r in records) == list(range(100))
    assert {r["task_id"] for r in records if r["eval_episode_id"] < 50} == {0}
    assert {r["task_id"] for r in records if r["eval_episode_id"] >= 50} == {3}


def test_eval_simulators_take_the_job_envs_after_the_train_ones(pods):
    worker = make_worker(pods, modes=("train", "eval"))
    try:
        before = resets(pods)
        worker.reset_env(mode="eval", reset_eval=True)
        assert [a - b for a, b in zip(resets(pods), before)] == [0, 0, 2]
        before = resets(pods)
        worker.reset_env(mode="train")
        assert [a - b for a, b in zip(resets(pods), before)] == [1, 1, 0]
    finally:
        worker.close()


def test_the_env_managers_get_state_is_found_and_a_restarted_simulator_continues_its_draws(pods):
    restarted, kept = make_worker(pods), make_worker(pods)
    try:
        restarted.reset_env()
        kept.reset_env()
        manager = restarted.simulator_list[0]
        manager.stop_simulator()
        manager.start_simulator()
        again, expected = restarted.reset_env(), kept.reset_env()
    finally:
        restarted.close()
        kept.close()
    assert manager.errors == [] and manager.state_buffer
    assert torch.equal(again["observation.state"], expected["observation.state"])


def test_observations_have_verl_vlas_keys_and_dtypes(pods):
    worker = make_worker(pods)
    try:
        batch = worker.reset_env()
        step = worker.env_interact_step(chunks(1)[0])
    finally:
        worker.close()
    assert (
        batch["observation.images.image"].shape == (2, 32, 32, 3)
        and batch["observation.images.image"].dtype == torch.uint8
    )
    assert batch["observation.images.wrist_image"].shape == (2, 32, 32, 3)
    # LIBERO's 8-float state, float64 as verl-vla's env builds it (libero_env.py:292-298).
    assert batch["observation.state"].shape == (2, 8) and batch["observation.state"].dtype == torch.float64
    assert step["obs.observation.state"].dtype == torch.float64 and step["next.reward"].dtype == torch.float32
    assert batch["task_id"].tolist() == [0, 3] and batch["task_id"].dtype == np.int64
    assert batch["eval_episode_id"].tolist() == [-1, -1]


# -- chunks --------------------------------------------------------------------------------------


def test_a_chunk_is_one_request_per_pod_and_equals_verl_vlas_own_step_loop(pods):
    runs = {}
    for whole in (True, False):
        made = make_env(pods, whole_chunks=whole)
        try:
            made._latest_obs = _reset_to(made, [7, 159])
            before = step_requests(pods)
            runs[whole] = [made.step(c, chunk_values=None) for c in chunks(2, seed=5)]
            sent = [a - b for a, b in zip(step_requests(pods), before)]
        finally:
            made.close()
        assert sent == ([2, 2, 0] if whole else [2 * K, 2 * K, 0])
    for chunk, loop in zip(runs[True], runs[False]):
        for mine, theirs in zip(chunk[1:], loop[1:]):
            assert torch.equal(mine, theirs)
        for mine, theirs in zip(chunk[0]["observation"], loop[0]["observation"]):
            _equal(mine, theirs)


def test_the_simulator_runs_in_a_process_spawned_as_verl_vlas_env_manager_spawns_it(pods, tmp_path, monkeypatch):
    """verl-vla's env manager runs each simulator in a spawned process, ``cfg`` and ``env_cls``
    pickled into it (env_manager.py:183-205): vecsim's lazily made ``LiberoEnv`` pickles by name,
    the env worker's config (``OmegaConf.structured`` of the typed one, env_worker.py:119-130, holding
    ``VecsimSettings``) with it, and both work there as in this process. The spawned process
    imports verl-vla's names from files standing in for its installed package."""
    from verl_vla.envs.libero.libero_env import LiberoEnv

    verl_vla_code.write_packages(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))  # a spawned process starts with this sys.path

    worker = EnvWorker(worker_config(pods), pipeline_stage_num=1)
    assert OmegaConf.get_type(worker.simulator_cfg.simulator.vecsim) is adapter.VecsimSettings
    spawned = verl_vla_code.SpawnedEnvManager(worker.simulator_cfg, rank=0, world_size=1, env_cls=LiberoEnv)
    spawned.start_simulator()
    try:
        child = spawned.process.pid
        assert child != os.getpid() and spawned.context.get_start_method() == "spawn"
        spawned._latest_obs = _reset_to(spawned, [7, 159])
        theirs = [spawned.step(c, chunk_values=None) for c in chunks(2, seed=5)]
    finally:
        spawned.stop_simulator()
    assert spawned.exitcode == 0 and spawned.state_buffer is not None  # get_state answered, then shutdown
    local = make_env(pods)
    try:
        local._latest_obs = _reset_to(local, [7, 159])
        ours = [local.step(c, chunk_values=None) for c in chunks(2, seed=5)]
    finally:
        local.close()
    for mine, spawn in zip(ours, theirs):
        for a, b in zip(mine[1:], spawn[1:]):
            assert a.dtype == b.dtype and torch.equal(a, b)
        for a, b in zip(mine[0]["observation"], spawn[0]["observation"]):
            _equal(a, b)


def test_an_episode_that_ends_mid_chunk_is_stepped_on_without_auto_reset(env):
    env._latest_obs = _reset_to(env, [7, 159])
    truncated = torch.cat([env.step(c)[3] for c in chunks(4, seed=1)], dim=1)
    # The limit of 20 comes at action 20 (index 19) and holds after it, as verl-vla's own
    # LIBERO env counts (libero_env.py:380-383); no env is reset, none refused.
    assert not truncated[:, : LIMIT - 1].any() and truncated[:, LIMIT - 1 :].all()


def test_with_auto_reset_an_env_that_ends_mid_chunk_is_reset_once_after_the_chunk(pods):
    made = make_env(pods, auto_reset=True)
    try:
        made._latest_obs = _reset_to(made, [7, 159])
        before = resets(pods)
        for chunk in chunks(2, seed=1):
            made.step(chunk)
        ending = made.step(chunks(1, seed=2)[0])
        after_end = resets(pods)
        fresh = made.step(chunks(1, seed=3)[0])
    finally:
        made.close()
    assert [a - b for a, b in zip(after_end, before)] == [1, 1, 0]  # one reset each, after the chunk
    assert ending[3][:, LIMIT - 2 * K - 1 :].all()  # the chunk stayed in the old episode
    assert not fresh[3].any()  # a fresh episode's first chunk


def test_base_env_steps_a_subset_of_envs_through_the_one_action_hook(env, pods):
    env._latest_obs = _reset_to(env, [7, 159])
    before_state = np.stack([o["observation.state"] for o in env._latest_obs["observation"]])
    sent = step_requests(pods)
    result = env.mask_step(
        np.full((2, 7), 0.2, np.float32), np.array([False, True]), np.zeros(2, bool), np.zeros(2, np.float32)
    )
    assert [a - b for a, b in zip(step_requests(pods), sent)] == [0, 1, 0]  # env 0's pod got nothing
    assert result["task_id"].tolist() == [3] and len(result["observation"]) == 1
    after_state = np.stack([o["observation.state"] for o in env._latest_obs["observation"]])
    assert np.array_equal(after_state[0], before_state[0]) and not np.array_equal(after_state[1], before_state[1])


def test_a_replayed_reset_names_its_benchmark_episode(env):
    obs = _reset_to(env, [7, 159])
    assert list(obs["eval_episode_id"]) == [7, 59]  # task 0's row 7; task 3's row 9 after task 0's 50


# -- bad input -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda e: e.step(torch.zeros(2, K, 6)), r"action must have shape \[2, T >= 1, 7\]"),
        (lambda e: e.step(torch.zeros(3, K, 7)), r"action must have shape \[2, T >= 1, 7\]"),
        (lambda e: e.step(torch.full((2, K, 7), float("nan"))), r"action must be finite"),
        (lambda e: e.step([[1.0], [1.0, 2.0]]), r"action must be an array of numbers"),
        (lambda e: e.env_step(np.zeros((1, 7)), env_ids=[5]), r"env_ids must be distinct env indices 0..1"),
        (lambda e: e.env_step(np.zeros((2, 7)), env_ids=[1]), r"action must have shape \[1, 7\]"),
        (
            lambda e: e.env_reset(env_ids=[0], extra={"info.reset_state_id": np.array([150])}),
            r"env 0 runs libero_spatial/0",
        ),
        (lambda e: e.env_reset(env_ids=[0], extra={"info.reset_state_id": np.array([200])}), r"outside 0..199"),
        (
            lambda e: e.env_reset(env_ids=[0], extra={"info.reset_state_id": np.array([1.7])}),
            r"extra\['info.reset_state_id'\] must hold one integer state id, got 1.7",
        ),
        (
            lambda e: e.env_reset(env_ids=[0], extra={"info.reset_state_id": ["x"]}),
            r"extra\['info.reset_state_id'\] must hold one integer",
        ),
        (
            lambda e: e.env_reset(env_ids=[0], extra={"info.reset_state_id": np.array([np.nan])}),
            r"extra\['info.reset_state_id'\] must hold one integer",
        ),
        (
            lambda e: e.env_reset(env_ids=[0], extra={"info.reset_state_id": np.array([True])}),
            r"extra\['info.reset_state_id'\] must hold one integer",
        ),
        (
            lambda e: e.env_reset(env_ids=[0], extra={"info.reset_state_id": np.array([1, 2])}),
            r"extra\['info.reset_state_id'\] must hold one integer",
        ),
        (lambda e: e.env_reset(env_ids=[0], extra={}), r"extra\['info.reset_state_id'\] must hold one integer"),
        (lambda e: e.load_state(b"{}"), r"state_buffer: not a vecsim verl-vla env state"),
    ],
)
def test_bad_input_is_refused_naming_the_field_and_changes_no_env(env, pods, call, message):
    env._latest_obs = _reset_to(env, [7, 159])
    counts = step_requests(pods), resets(pods)
    with pytest.raises(ValueError, match=message):
        call(env)
    assert (step_requests(pods), resets(pods)) == counts


def test_stepping_after_close_is_refused(pods):
    made = make_env(pods)
    made._latest_obs = _reset_to(made, [7, 159])
    made.close()
    with pytest.raises(ClosedEnvironmentError):
        made.step(torch.zeros(2, K, 7))


def test_a_process_beyond_the_jobs_envs_is_refused(pods):
    with pytest.raises(
        ValueError,
        match=r"num_envs: train process 2 takes job envs 4..5 \(train simulators take 0..5\), but the job has 4",
    ):
        make_env(pods, rank=2, world_size=3)
