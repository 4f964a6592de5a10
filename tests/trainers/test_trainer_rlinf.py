"""RLinf's own code judges vecsim's RLinf env (vecsim.trainers.rlinf.VecsimLiberoEnv).

RLinf 0.3.0's ``LiberoEnv`` (its subprocess vector env over LIBERO) and ``VecsimLiberoEnv``
(over a real pod on loopback serving libero_spatial/0) are each driven through RLinf's own
``EnvWorker`` methods: ``_init_env``, ``bootstrap_step``, ``env_interact_step`` and
``finish_rollout``, with the same config, reset ids and scripted chunks. Every ``EnvOutput``
(observations, final observations, rewards, terminations, truncations, infos with the episode
statistics) and the env metrics must be equal, dtypes included, bit for bit.

Conventions set equal: the settle is RLinf's (15 steps of ``[0]*6 + [-1]`` inside ``reset()``,
``reset_gripper_open: true``; the job's ``libero: {settle_steps: 15}``), and the fixture seed:
RLinf seeds env slot ``i`` with ``seed * n + i`` before each reset (libero_env.py:663,
envs/venv/venv.py:858-864), vecsim every env with the job's ``fixture_seed``, so RLinf's vector
env here seeds every slot with the job's (0); fixtures (LIBERO's cabinets) are placed from it.
Seeded before every reset, each of RLinf's resets places the fixtures as a fresh env's first
reset does: the job's ``fixture_rule: first_reset`` (docs/libero.md), not the published loop's.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

pytest.importorskip("rlinf")

from support.rlinf_worker import env_worker as support_env_worker  # noqa: E402
from support.rlinf_worker import rlinf_config as support_rlinf_config  # noqa: E402
from support.service_procs import assignment, standalone_pods  # noqa: E402

from vecsim.config import CameraConfig  # noqa: E402
from vecsim.engine.tasks._libero import ensure_config  # noqa: E402

pytestmark = pytest.mark.libero

TASK = "libero_spatial/0"
SIZE = 64
NUM_ENVS = 2
K = 8
EPISODE_LIMIT = 20  # RLinf's max_episode_steps: the episode truncates at action 4 of chunk 3
FIXTURE_SEED = 0


@pytest.fixture(scope="module")
def pod_url(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """One pod serving two envs of libero_spatial/0 with RLinf's settle."""
    spec = assignment(
        "rlinf-pod",
        [(TASK, NUM_ENVS)],
        job_id="rlinf",
        camera=CameraConfig(names=("agentview", "robot0_eye_in_hand"), height=SIZE, width=SIZE),
        render=None,
        max_episode_steps=None,
        envs_per_worker=0,
        libero={"settle_steps": 15, "fixture_seed": FIXTURE_SEED, "fixture_rule": "first_reset"},
    )
    with standalone_pods([spec], tmp_path_factory.mktemp("rlinf-pod")) as pods:
        yield pods[0].url


def rlinf_config(auto_reset: bool, pod_url: str | None, **env: Any) -> Any:
    """An RLinf config as its EnvWorker reads it; ``pod_url`` adds the vecsim block."""
    train = {
        "env_type": "libero",
        "task_suite_name": "libero_spatial",
        "total_num_envs": NUM_ENVS,
        "seed": 0,
        "group_size": NUM_ENVS,
        "use_fixed_reset_state_ids": True,
        "use_ordered_reset_state_ids": False,
        "task_id_filter": [0],
        "ignore_terminations": False,
        "auto_reset": auto_reset,
        "use_rel_reward": True,
        "reward_coef": 5.0,
        "max_episode_steps": EPISODE_LIMIT,
        "max_steps_per_rollout_epoch": 5 * K,
        "rollout_epoch": 1,
        "reset_gripper_open": True,
        "video_cfg": {"save_video": False},
        "init_params": {"camera_heights": SIZE, "camera_widths": SIZE},
        **env,
    }
    if pod_url is not None:
        train["vecsim"] = {"pod_urls": [pod_url]}
    return support_rlinf_config(train, K)


def env_worker(cfg: Any, env: Any) -> Any:
    return support_env_worker(cfg, env, NUM_ENVS)


def rlinf_libero_env(cfg: Any) -> Any:
    """RLinf's own LiberoEnv, its fixture seed set to the job's (module docstring)."""
    ensure_config()  # LIBERO's config file, so that importing LIBERO asks nothing
    from rlinf.envs import get_env_cls

    env = get_env_cls("libero", cfg.env.train)(cfg.env.train, NUM_ENVS, 0, 1, None)
    vector = env.env
    vector.seed = lambda seed=None: [worker.seed(FIXTURE_SEED) for worker in vector.workers]
    return env


def vecsim_env(cfg: Any) -> Any:
    import vecsim.trainers.rlinf

    vecsim.trainers.rlinf.register()
    from rlinf.envs import get_env_cls

    return get_env_cls("libero", cfg.env.train)(cfg.env.train, NUM_ENVS, 0, 1, None)


def scripted_chunks(n: int) -> list[Any]:
    import torch

    rng = np.random.default_rng(7)
    return [torch.tensor(rng.uniform(-0.6, 0.6, (NUM_ENVS, K, 7)), dtype=torch.float32) for _ in range(n)]


def rollout(cfg: Any, env: Any, chunks: list[Any]) -> list[tuple[str, Any]]:
    """RLinf's env-worker calls of one rollout and the start of the next; what each returned."""
    worker = env_worker(cfg, env)
    seen: list[tuple[str, Any]] = []
    worker._init_env()
    seen.append(("bootstrap", worker.bootstrap_step()[0]))
    for i, chunk in enumerate(chunks):
        output, metrics = worker.env_interact_step(chunk.clone(), 0)
        seen.append((f"chunk {i}", output))
        seen.append((f"chunk {i} metrics", metrics))
    worker.finish_rollout()
    seen.append(("reset ids after finish_rollout", env.reset_state_ids.copy()))
    seen.append(("next bootstrap", worker.bootstrap_step()[0]))
    return seen


def differences(theirs: Any, ours: Any, where: str) -> list[str]:
    """Where ``ours`` is not ``theirs`` bit for bit (types and dtypes included)."""
    import dataclasses

    import torch

    if dataclasses.is_dataclass(theirs) and not isinstance(theirs, type):
        fields = [f.name for f in dataclasses.fields(theirs)]
        return [d for f in fields for d in differences(getattr(theirs, f), getattr(ours, f), f"{where}.{f}")]
    if type(theirs) is not type(ours):
        return [f"{where}: {type(theirs).__name__} vs {type(ours).__name__}"]
    if isinstance(theirs, dict):
        if sorted(theirs) != sorted(ours):
            return [f"{where}: keys {sorted(theirs)} vs {sorted(ours)}"]
        return [d for k in theirs for d in differences(theirs[k], ours[k], f"{where}[{k!r}]")]
    if isinstance(theirs, (list, tuple)):
        if len(theirs) != len(ours):
            return [f"{where}: length {len(theirs)} vs {len(ours)}"]
        return [d for i, (a, b) in enumerate(zip(theirs, ours)) for d in differences(a, b, f"{where}[{i}]")]
    if isinstance(theirs, torch.Tensor):
        if theirs.dtype != ours.dtype or theirs.shape != ours.shape:
            return [f"{where}: {theirs.dtype}{tuple(theirs.shape)} vs {ours.dtype}{tuple(ours.shape)}"]
        if not torch.equal(theirs, ours):
            diff = (theirs.double() - ours.double()).abs().max().item()
            return [f"{where}: values differ (max {diff})"]
        return []
    if isinstance(theirs, np.ndarray):
        if theirs.dtype != ours.dtype or not np.array_equal(theirs, ours):
            return [f"{where}: {theirs!r} vs {ours!r}"]
        return []
    return [] if theirs == ours else [f"{where}: {theirs!r} vs {ours!r}"]


@contextlib.contextmanager
def both_envs(cfg_theirs: Any, cfg_ours: Any) -> Iterator[tuple[Any, Any]]:
    theirs = rlinf_libero_env(cfg_theirs)
    try:
        ours = vecsim_env(cfg_ours)
        try:
            yield theirs, ours
        finally:
            ours.close()
    finally:
        theirs.env.close()


@pytest.mark.timeout(900)
@pytest.mark.parametrize("auto_reset", [False, True], ids=["no-auto-reset", "auto-reset"])
def test_rlinf_env_worker_sees_what_rlinf_libero_env_gives(pod_url: str, auto_reset: bool) -> None:
    chunks = scripted_chunks(4 if not auto_reset else 5)
    cfg_theirs, cfg_ours = rlinf_config(auto_reset, None), rlinf_config(auto_reset, pod_url)
    with both_envs(cfg_theirs, cfg_ours) as (theirs, ours):
        expected = rollout(cfg_theirs, theirs, chunks)
        got = rollout(cfg_ours, ours, chunks)
    # the episode truncated inside chunk 2 (action 4 of 8) in both
    truncations = dict(expected)["chunk 2"].truncations
    assert truncations.any(), "the script should end an episode inside chunk 2"
    problems = [d for (name, a), (_, b) in zip(expected, got) for d in differences(a, b, name)]
    assert not problems, "\n".join(problems[:20])


# -- bad input: a clear error naming the field, and no env changed --------------------------------


@pytest.fixture()
def ours(pod_url: str) -> Iterator[Any]:
    env = vecsim_env(rlinf_config(False, pod_url))
    try:
        yield env
    finally:
        env.close()


def first_chunk_obs(env: Any, before: Any = None) -> Any:
    """Reset both slots to state 0, run ``before`` (if any), step one scripted chunk; its obs."""
    env.is_start = False
    env.reset(reset_state_ids=np.array([0, 0]))
    if before is not None:
        before()
    return env.chunk_step(scripted_chunks(1)[0])[0][-1]


def test_a_chunk_of_the_wrong_shape_is_refused_naming_it_and_changes_no_env(ours: Any) -> None:
    expected = first_chunk_obs(ours)

    def bad() -> None:
        with pytest.raises(ValueError, match="chunk_actions"):
            ours.chunk_step(np.zeros((NUM_ENVS, K, 6)))
        with pytest.raises(ValueError, match="chunk_actions"):
            ours.chunk_step(np.zeros((NUM_ENVS + 1, K, 7)))
        with pytest.raises(ValueError, match="chunk_actions"):
            ours.chunk_step(np.full((NUM_ENVS, K, 7), np.nan))
        with pytest.raises(ValueError, match=r"chunk_actions: a chunk holds at least 1 action"):
            ours.chunk_step(np.zeros((NUM_ENVS, 0, 7)))
        with pytest.raises(ValueError, match="^actions must be"):
            ours.step(np.zeros((NUM_ENVS, 6)))
        assert ours.elapsed_steps.tolist() == [0, 0]

    assert not differences(expected, first_chunk_obs(ours, bad), "obs")


def test_unknown_env_indices_and_reset_ids_are_refused_naming_them_and_change_no_env(ours: Any) -> None:
    expected = first_chunk_obs(ours)

    def bad() -> None:
        with pytest.raises(ValueError, match="env_idx"):
            ours.reset(env_idx=[NUM_ENVS], reset_state_ids=np.array([0]))
        with pytest.raises(ValueError, match="reset_state_ids"):
            ours.reset(env_idx=[0], reset_state_ids=np.array([500]))  # libero_spatial has 10 x 50
        with pytest.raises(ValueError, match="libero_spatial/1"):
            ours.reset(env_idx=[0], reset_state_ids=np.array([50]))  # task 1: not served by the job
        with pytest.raises(ValueError, match="env_idx must be integers"):
            ours.reset(env_idx=[0.5], reset_state_ids=np.array([0]))
        with pytest.raises(ValueError, match="reset_state_ids must be integers"):
            ours.reset(env_idx=[0], reset_state_ids=np.array([1.7]))
        with pytest.raises(ValueError, match=r"reset_state_ids for 2 envs \(env_idx\)"):
            ours.reset(env_idx=[0, 1], reset_state_ids=np.array([0]))

    assert not differences(expected, first_chunk_obs(ours, bad), "obs")


def test_more_slots_of_a_task_than_the_stage_holds_is_refused_naming_the_task(pod_url: str) -> None:
    from vecsim.trainers.rlinf import VecsimLiberoEnv

    cfg = rlinf_config(False, pod_url, group_size=2 * NUM_ENVS)
    env = VecsimLiberoEnv(cfg.env.train, 2 * NUM_ENVS, 0, 1, None)
    try:
        with pytest.raises(ValueError, match=f"stage 0 has {NUM_ENVS} env.* of task '{TASK}'"):
            env.reset()
    finally:
        env.close()


def test_stepping_after_close_raises(pod_url: str) -> None:
    from gymnasium.error import ClosedEnvironmentError

    env = vecsim_env(rlinf_config(False, pod_url))
    env.reset()
    env.close()
    with pytest.raises(ClosedEnvironmentError):
        env.chunk_step(np.zeros((NUM_ENVS, K, 7)))
    with pytest.raises(ClosedEnvironmentError):
        env.reset()


def test_an_env_config_naming_no_job_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    from vecsim.trainers.rlinf import CONTROLLER_URL_ENV, VecsimLiberoEnv

    monkeypatch.delenv(CONTROLLER_URL_ENV, raising=False)
    cfg = rlinf_config(False, None)
    cfg.env.train.vecsim = {}
    with pytest.raises(ValueError, match="controller_url"):
        VecsimLiberoEnv(cfg.env.train, NUM_ENVS, 0, 1, None)


def test_register_picks_vecsim_env_only_for_configs_with_a_vecsim_block() -> None:
    ensure_config()
    import vecsim.trainers.rlinf
    from rlinf.envs.libero.libero_env import LiberoEnv

    vecsim.trainers.rlinf.register()
    vecsim.trainers.rlinf.register()  # idempotent
    import rlinf.envs
    import rlinf.workers.env.env_worker as env_worker

    with_block, without = rlinf_config(False, "http://127.0.0.1:1"), rlinf_config(False, None)
    for lookup in (rlinf.envs.get_env_cls, env_worker.get_env_cls):
        assert lookup("libero", with_block.env.train) is vecsim.trainers.rlinf.VecsimLiberoEnv
        assert lookup("libero", without.env.train) is LiberoEnv


def test_slots_keep_their_env_while_their_task_stays_and_spread_over_pods() -> None:
    from vecsim.client.routing import RoutedEnv
    from vecsim.trainers.rlinf import place_slots

    envs = [RoutedEnv(pod, i, task, 0) for pod in ("a", "b") for i, task in enumerate(["s/0", "s/0", "s/1"])]
    first = place_slots(envs, {}, {0: "s/0", 1: "s/0", 2: "s/1"}, 0)
    assert [(first[s].pod, first[s].env_index) for s in range(3)] == [("a", 0), ("b", 0), ("a", 2)]
    again = place_slots(envs, first, {0: "s/0", 2: "s/0"}, 0)
    assert again[0] == first[0] and again[2].task_id == "s/0" and again[2] not in (first[0], first[1])
    with pytest.raises(ValueError, match="task 's/1'"):
        place_slots(envs, {}, {0: "s/1", 1: "s/1", 2: "s/1"}, 0)


# -- a pod restart mid-rollout: RLinf's EnvWorker rolls on ---------------------------------------


@pytest.fixture(scope="module")
def rlinf_job(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    """A local job (controller + one pod, the runner restarting what dies) serving the same two
    envs as ``pod_url``'s pod."""
    from service.runner import Backoff, LocalJob
    from support.service_procs import job_config

    job = {
        "job_id": "rlinf-faults",
        "tasks": [TASK],
        "group_size": NUM_ENVS,
        "num_stages": 1,
        "pods_per_stage": 1,
        "camera": {"names": ["agentview", "robot0_eye_in_hand"], "height": SIZE, "width": SIZE},
        "max_episode_steps": None,
        "envs_per_worker": 0,
        "libero": {"settle_steps": 15, "fixture_seed": FIXTURE_SEED, "fixture_rule": "first_reset"},
    }
    local = LocalJob(
        job_config(job, replicas=1),
        log_dir=tmp_path_factory.mktemp("rlinf-job"),
        grace_s=10,
        backoff=Backoff(initial_s=0.2),
    )
    with local:
        local.wait_ready(timeout=600)
        yield local


def job_rlinf_config(job: Any, auto_reset: bool) -> Any:
    cfg = rlinf_config(auto_reset, None)
    cfg.env.train.vecsim = {"controller_url": job.controller_url, "timeout_s": 30, "heal_wait_s": 600}
    return cfg


@pytest.mark.slow
@pytest.mark.timeout(1200)
def test_rlinf_env_worker_rolls_out_across_a_pod_restart_and_flags_the_lost_episodes(rlinf_job, monkeypatch) -> None:
    import os
    import signal

    import torch

    monkeypatch.setenv("VECSIM_TOKEN", rlinf_job.token)
    cfg = job_rlinf_config(rlinf_job, auto_reset=True)
    chunks = scripted_chunks(4)
    env = vecsim_env(cfg)
    try:
        worker = env_worker(cfg, env)
        worker._init_env()
        worker.bootstrap_step()
        first, _ = worker.env_interact_step(chunks[0].clone(), 0)
        assert "lost" not in first.env_infos
        pod = rlinf_job.processes["sim-0"]
        os.killpg(pod.pid, signal.SIGKILL)  # the runner starts it again; the controller gives it its slot
        # The chunk meets the dead pod: both slots' episodes end truncated and lost, and the
        # auto-reset inside it waits until the pod serves again.
        struck, _ = worker.env_interact_step(chunks[1].clone(), 0)
        assert pod.restarts == 1
        assert struck.truncations[:, -1].all() and not struck.terminations.any()
        assert struck.env_infos["lost"].tolist() == [True, True]
        assert struck.env_infos["final_info"]["lost"].tolist() == [True, True]
        assert torch.equal(struck.rewards, torch.zeros_like(struck.rewards))
        reset_ids = env.reset_state_ids.copy()
        after = [worker.env_interact_step(chunk.clone(), 0)[0] for chunk in chunks[2:]]
        assert not any("lost" in output.env_infos for output in after)
    finally:
        env.close()
    # The episodes after the lost ones are what a fresh env gives for the same reset ids and chunks.
    reference = vecsim_env(job_rlinf_config(rlinf_job, auto_reset=False))
    try:
        reference.is_start = False
        reference.reset(reset_state_ids=reset_ids)
        expected = [reference.chunk_step(chunk.clone()) for chunk in chunks[2:]]
    finally:
        reference.close()
    for i, (output, (obs_list, rewards, _, truncations, _)) in enumerate(zip(after, expected)):
        problems = differences(obs_list[-1], output.obs, f"chunk {i + 2} obs") + differences(
            rewards, output.rewards, f"chunk {i + 2} rewards"
        )
        assert not problems, "\n".join(problems[:20])
