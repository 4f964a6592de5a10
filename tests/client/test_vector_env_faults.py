"""HTTPVectorEnv when one pod fails: the answered envs go on, the failed ones are named and reset.

Two standalone pods serve the one stage (sim-0 and sim-1, two ``gym/Pendulum-v1`` envs each, the
job's token). sim-1 is killed (SIGKILL of its process group) between two steps, then started
again on the same port. Every run puts the envs in fixed state ids, so a fault-free run of the
same actions is the reference, bit for bit. The last test runs a controller job whose pod is
killed and restarted by the runner: its envs come back at a new generation (RoutingChangedError).
"""

from __future__ import annotations

import os
import re
import signal
from collections.abc import Iterator
from contextlib import closing

import httpx
import numpy as np
import pytest
from gymnasium.error import ResetNeeded
from gymnasium.vector import AutoresetMode
from support.service_procs import (
    Server,
    assignment_file,
    job_config,
    local_job,
    pod_server,
    running,
    wait_for_generation,
)

from vecsim.client import ClientError, HTTPVectorEnv, PodUnavailableError, RoutingChangedError

TOKEN = "vector-faults-token-0123456789abcdef"
PENDULUM = "gym/Pendulum-v1"
STATE_IDS = np.array([3, 4, 5, 6])
FIRST, SECOND = 0.5, -1.0  # the actions of the steps before and after the kill


@pytest.fixture
def pods(request, tmp_path) -> Iterator[tuple[Server, Server]]:
    """sim-0 and sim-1 on stage 0 with episodes of ``request.param`` steps (30 unless given)."""
    episode = getattr(request, "param", 30)
    made = []
    for name in ("sim-0", "sim-1"):
        path = assignment_file(tmp_path, name, [(PENDULUM, 2)], stage_id=0, max_episode_steps=episode)
        made.append(pod_server(name, tmp_path, args=["--assignment", str(path)], token=TOKEN))
    with running(made[0], ready=True), running(made[1], ready=True):
        yield made[0], made[1]


def vector_env(pods: tuple[Server, Server], mode: AutoresetMode = AutoresetMode.NEXT_STEP) -> HTTPVectorEnv:
    return HTTPVectorEnv(pod_urls=[p.url for p in pods], autoreset_mode=mode, timeout_s=10, token=TOKEN)


def on_pod(env: HTTPVectorEnv, name: str) -> list[int]:
    return sorted(i for i, route in env.routes.items() if route.pod == name)


def act(env: HTTPVectorEnv, value: float) -> np.ndarray:
    return np.full((env.num_envs, 1), value, np.float32)


def kill(server: Server) -> None:
    server.signal_group(signal.SIGKILL)
    server.proc.wait(timeout=30)  # type: ignore[union-attr]


def restart(server: Server) -> None:
    """Start the killed pod again: same command, port and assignment, fresh envs."""
    server.start()
    server.wait_ready()


def reference(pods: tuple[Server, Server], mode: AutoresetMode, actions: list[float]) -> list[tuple]:
    """A fault-free run from STATE_IDS: the reset's answer, then each step's."""
    with closing(vector_env(pods, mode)) as env:
        answers = [env.reset(options={"state_ids": STATE_IDS})]
        return answers + [env.step(act(env, a)) for a in actions]


@pytest.mark.slow
def test_a_killed_pod_fails_the_step_for_its_envs_alone_and_the_others_hold_their_true_rows(pods):
    _, doomed = pods
    ref = reference(pods, AutoresetMode.NEXT_STEP, [FIRST, SECOND, FIRST])
    with closing(vector_env(pods)) as env:
        healthy, failed = on_pod(env, "sim-0"), on_pod(env, "sim-1")
        env.reset(options={"state_ids": STATE_IDS})
        env.step(act(env, FIRST))
        kill(doomed)
        with pytest.raises(PodUnavailableError) as caught:
            env.step(act(env, SECOND))
        error = caught.value
        assert error.failed_envs == failed and error.pods == ["sim-1"]
        assert sorted(error.traj_keys) == [f"env{i}" for i in failed]
        obs, reward, terminated, truncated, info = error.result
        assert np.array_equal(obs[healthy], ref[2][0][healthy])
        assert np.array_equal(reward[healthy], ref[2][1][healthy])
        # Pendulum's reward is never 0: only the answered envs' rows hold one (info is Pendulum's: empty).
        assert (reward != 0).tolist() == [i in healthy for i in range(env.num_envs)] and info == {}

        # The buffer holds the healthy envs' new rows: the next reset of the failed ones returns them.
        restart(doomed)
        mask = np.isin(np.arange(env.num_envs), failed)
        obs, info = env.reset(options={"reset_mask": mask, "state_ids": STATE_IDS})
        assert np.array_equal(obs[healthy], ref[2][0][healthy])
        assert np.array_equal(obs[failed], ref[0][0][failed])
        assert info["_state_id"].tolist() == mask.tolist()

        # Every env steps again: the healthy ones on from where they were, the others from their reset.
        obs, reward, *_ = env.step(act(env, FIRST))
        assert np.array_equal(obs[healthy], ref[3][0][healthy])
        assert np.array_equal(obs[failed], ref[1][0][failed])
        assert np.array_equal(reward, np.where(mask, ref[1][1], ref[3][1]))


@pytest.mark.slow
def test_a_step_before_the_failed_envs_are_reset_is_refused_naming_them(pods):
    _, doomed = pods
    with closing(vector_env(pods)) as env:
        failed = on_pod(env, "sim-1")
        env.reset(seed=0)
        kill(doomed)
        with pytest.raises(PodUnavailableError):
            env.step(act(env, FIRST))
        with pytest.raises(ResetNeeded, match=re.escape(f"envs {failed} got no answer")):
            env.step(act(env, FIRST))


@pytest.mark.slow
def test_resetting_the_failed_envs_while_their_pod_is_down_fails_for_them_alone(pods):
    _, doomed = pods
    with closing(vector_env(pods)) as env:
        healthy, failed = on_pod(env, "sim-0"), on_pod(env, "sim-1")
        before, _ = env.reset(seed=0)
        kill(doomed)
        mask = np.isin(np.arange(env.num_envs), failed)
        with pytest.raises(PodUnavailableError, match="sim-1") as caught:
            env.reset(options={"reset_mask": mask})
        assert caught.value.failed_envs == failed
        # The healthy envs were not in the call: untouched, and a reset of them alone still works.
        obs, _ = caught.value.result
        assert np.array_equal(obs[healthy], before[healthy])
        with pytest.raises(ResetNeeded):
            env.step(act(env, FIRST))
        restart(doomed)
        env.reset(options={"reset_mask": mask})
        assert (env.step(act(env, FIRST))[1] != 0).all()


@pytest.mark.parametrize("pods", [2], indirect=True)
@pytest.mark.slow
def test_same_step_autoresets_the_answered_envs_that_end_in_the_failed_call(pods):
    _, doomed = pods
    ref = reference(pods, AutoresetMode.SAME_STEP, [FIRST, SECOND])
    with closing(vector_env(pods, AutoresetMode.SAME_STEP)) as env:
        healthy, failed = on_pod(env, "sim-0"), on_pod(env, "sim-1")
        env.reset(options={"state_ids": STATE_IDS})
        env.step(act(env, FIRST))
        kill(doomed)
        with pytest.raises(PodUnavailableError) as caught:
            env.step(act(env, SECOND))  # the second step of 2-step episodes: every env ends
        assert caught.value.failed_envs == failed
        obs, reward, terminated, truncated, info = caught.value.result
        assert truncated.tolist() == [i in healthy for i in range(env.num_envs)]
        assert info["_final_obs"].tolist() == truncated.tolist()
        for i in healthy:
            assert np.array_equal(info["final_obs"][i], ref[2][4]["final_obs"][i])
        for i in healthy:  # the healthy envs were reset already: they observe what the reference's reset gave
            assert np.array_equal(obs[i], ref[2][0][i])

        restart(doomed)
        env.reset(options={"reset_mask": ~truncated})
        _, _, terminated, truncated, info = env.step(act(env, FIRST))
        assert not (terminated | truncated).any()


JOB = {"job_id": "vector-faults", "tasks": [PENDULUM], "group_size": 2, "num_stages": 2, "camera": {"names": []}}


@pytest.mark.slow
def test_a_pod_restarted_into_its_slot_takes_its_envs_back_after_a_reset_of_them(tmp_path):
    with local_job(job_config(JOB, replicas=2), tmp_path) as job:
        with closing(HTTPVectorEnv(controller_url=job.controller_url, timeout_s=10, token=job.token)) as env:
            healthy, failed = on_pod(env, "sim-1"), on_pod(env, "sim-0")
            env.reset(options={"state_ids": STATE_IDS})
            generation = env.client.routing.generation
            os.killpg(job.processes["sim-0"].pid, signal.SIGKILL)  # the runner starts it again
            wait_for_generation(job.controller_url, generation)
            with pytest.raises(RoutingChangedError) as caught:
                env.step(act(env, FIRST))
            assert caught.value.failed_envs == failed
            assert sorted(caught.value.traj_keys) == [f"env{i}" for i in failed]
            assert (caught.value.result[1] != 0).tolist() == [i in healthy for i in range(env.num_envs)]

            mask = np.isin(np.arange(env.num_envs), failed)
            env.reset(options={"reset_mask": mask, "state_ids": STATE_IDS})
            assert sorted(env.routes) == list(range(env.num_envs))
            assert (env.step(act(env, FIRST))[1] != 0).all()


@pytest.mark.slow
def test_a_reset_after_the_jobs_envs_changed_is_refused_naming_the_generation(tmp_path):
    with local_job(job_config(JOB, replicas=2), tmp_path) as job:
        with closing(HTTPVectorEnv(controller_url=job.controller_url, timeout_s=10, token=job.token)) as env:
            env.reset(seed=0)
            generation = env.client.routing.generation
            bigger = {**JOB, "group_size": 3}
            auth = {"Authorization": f"Bearer {job.token}"}
            answer = httpx.put(f"{job.controller_url}/v1/job", json=bigger, timeout=30, headers=auth)
            assert answer.status_code == 200
            new_generation = wait_for_generation(job.controller_url, generation)
            with pytest.raises(RoutingChangedError) as caught:
                env.step(act(env, FIRST))
            assert caught.value.failed_envs == list(range(env.num_envs))
            with pytest.raises(ClientError, match=f"generation {new_generation}.*make a new one"):
                env.reset()
