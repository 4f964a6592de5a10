"""EnvLoop: the pipelined rollout. Read :meth:`EnvLoop.run` top to bottom.

Reset every trajectory, one call per lane (a stage's envs on one pod: a pod of the ``slices``
layout is in a lane of every stage, :meth:`StageClient.pod_call`), then loop:
take the answers of the next stage in turn (s+1, s+2, ...) of which some pod's answer is in
(waiting, only when none is, for whichever lands first), run the policy on the observations of
that stage's landed pods, and send each of those pods its next actions without waiting. There
is no lockstep over a stage's pods: a pod's answer is used when it lands, and a slow pod holds
up only its own envs. ``max_batch`` bounds a policy call; ``batch_wait_s`` lets the loop wait a
little for more of the stage's pods before the policy runs. A trajectory ends on termination,
truncation or the horizon and is not stepped again. The result is per-trajectory tensors keyed
by traj_key in request order, plus timing stats and, for chosen trajectories, videos of a camera.

Refill: a batch may hold more requests than the job has envs. Request ``i`` belongs to stage
``i % S`` (:func:`vecsim.rollout.sampler.stage_of`), as the sampler drew it; the first requests of each
(stage, task) start at once, and each of the others starts, reset to its state id, on an env of
its task on its stage as soon as one's trajectory ends (in the call that steps that pod's other
envs). A GRPO group's requests may so run at different times; the result reports them together.

A policy may act in chunks: returning ``[n, K, action_dim]``, each trajectory's K actions go to
its pod in one call (applied in order, stopping at a termination or truncation, rendered once).
The loop records every applied action and its reward; the horizon counts actions, not calls (a
chunk that would pass a trajectory's horizon is cut to fit, for all of that pod's call). Videos
of a chunked rollout carry every action's frame: the pods render them for the recorded
trajectories only. An empty batch is a no-op, and a pod without trajectories is never called.

A pod that dies, hangs past the client's timeout or rebuilds its envs mid-episode does not fail
the rollout: its trajectories are reported lost by traj_key (:attr:`RolloutResult.lost`, with
their route, to resample), no waiting request starts on it, and every other trajectory runs on.
An env that raises in a reset or step (its own exception, or an engine's ``SimStateError``) costs
only its trajectory: lost, naming the exception, never stepped again, and its env is freed as an
ended trajectory's, so a waiting request starts there with a reset (which clears the failure).
"""

from __future__ import annotations

import logging
import math
import re
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium import spaces

from vecsim import trees
from vecsim.client import (
    CapacityError,
    PendingCall,
    PodUnavailableError,
    RoutingChangedError,
    StageBatch,
    StageClient,
    StepActions,
    TrajRoute,
)
from vecsim.client.routing import check_request
from vecsim.config import RoutingTable
from vecsim.plan import stage_of
from vecsim.rollout.intervals import covered, intersection, merge
from vecsim.rollout.results import LostTrajectory, RolloutResult, RolloutStats, Trajectory
from vecsim.rollout.video import Recorder, write_video


logger = logging.getLogger(__name__)

__all__ = ["EnvLoop", "Policy"]

# policy(observations, instructions, task_ids) -> actions [n, action_dim] or chunks [n, K, action_dim]
Policy = Callable[[dict[str, Any], list[str], list[str]], torch.Tensor]
# (stage_id, pod): one stage's envs on one pod, what one call of the loop steps.
Lane = tuple[int, str]


# -- the loop ------------------------------------------------------------------------------------


class EnvLoop:
    """The pipelined rollout of a policy over a :class:`StageClient`'s stages.

    ``horizon`` caps every trajectory's length (the pods' own ``max_episode_steps`` may end it
    sooner). ``keep_obs`` names the observation keys stored per trajectory (``()`` stores none).
    ``record`` names traj_keys (or a count of the first trajectories) whose camera ``camera``
    (default: the first) is written to ``video_dir`` as ``<traj_key>.<video_format>`` (mp4 or
    gif). Progress is logged every ``log_every_s`` seconds.

    ``max_batch``: the most observations one policy call gets (None: no bound).
    ``batch_wait_s``: how long the loop waits, once a pod's answer is in, for more of its stage's
    pods to land before the policy runs (0: never waits).
    """

    def __init__(
        self,
        client: StageClient,
        policy: Policy,
        *,
        horizon: int,
        device: str | torch.device = "cpu",
        keep_obs: Sequence[str] = ("images", "proprio"),
        record: Sequence[str] | int = (),
        camera: str | None = None,
        video_dir: str | Path | None = None,
        video_format: str = "mp4",
        video_fps: int = 10,
        log_every_s: float = 10.0,
        max_batch: int | None = None,
        batch_wait_s: float = 0.0,
    ) -> None:
        """Set the loop up; nothing runs until :meth:`run`.

        Raises:
            ValueError: ``horizon < 1``, videos asked for without ``video_dir``, an unknown
                ``video_format``, ``max_batch < 1`` or a negative ``batch_wait_s``.
        """
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if record and video_dir is None:
            raise ValueError("record asks for videos: give video_dir")
        if video_format not in ("mp4", "gif"):
            raise ValueError(f"video_format must be 'mp4' or 'gif', got {video_format!r}")
        if max_batch is not None and max_batch < 1:
            raise ValueError(f"max_batch must be >= 1 or None, got {max_batch}")
        if not (batch_wait_s >= 0 and math.isfinite(batch_wait_s)):
            raise ValueError(f"batch_wait_s must be a finite number >= 0, got {batch_wait_s}")
        self.client = client
        self.policy = policy
        self.horizon = int(horizon)
        self.device = torch.device(device)
        self.keep_obs = tuple(keep_obs)
        self.record = record
        self.camera = camera
        self.video_dir = Path(video_dir) if video_dir is not None else None
        self.video_format = video_format
        self.video_fps = video_fps
        self.log_every_s = log_every_s
        self.max_batch = max_batch
        self.batch_wait_s = float(batch_wait_s)

    def run(
        self,
        requests: Sequence[tuple[str, int]],
        traj_keys: Sequence[str] | None = None,
        horizons: Sequence[int] | None = None,
    ) -> RolloutResult:
        """Roll out one trajectory per request ``(task_id, state_id)``; return them with stats.

        ``horizons``, when given, caps each request's trajectory on its own (each 1..``horizon``).

        Request ``i`` runs on stage ``stage_of(i, S)``. There may be more requests than envs: a
        request for which its stage has no free env of its task waits, and starts (reset to its
        state id) on the first such env whose trajectory ends. The result holds every request's
        trajectory, in request order, whenever it ran.

        Trajectories whose pod went away (``PodUnavailableError``, ``RoutingChangedError``) end
        up in the result's ``lost``, not in its ``trajectories``; the trajectories of the other
        pods go on. Waiting requests that no env was left for (their task's envs on their stage
        all on failed pods) are lost too, with ``steps`` 0 and a route of pod ``""``, env -1.
        A trajectory whose env raised in its reset or a step (``StageBatch.errors``: that row did
        nothing) is lost as well, its ``reason`` naming the env, the exception's type and message,
        its ``steps`` the actions applied before; it is not stepped again, and its env takes a
        waiting request of its task as an ended trajectory's does. Other trajectories go on as if
        nothing happened.

        Raises:
            CapacityError: a stage has no env of a request's task at all.
            ValueError: a malformed request, traj_keys or horizons, or videos of trajectories or
                a camera that are not there.
            PodRequestError, StaleGenerationError: from the client (a refused request).
        """
        started = time.perf_counter()
        requests = list(requests)
        keys = list(traj_keys) if traj_keys is not None else self.client.new_traj_keys(len(requests))
        if len(keys) != len(requests) or len(set(keys)) != len(keys):
            raise ValueError(f"traj_keys: need {len(requests)} distinct keys, one per request, got {len(keys)}")
        caps = [self.horizon] * len(requests) if horizons is None else [int(h) for h in horizons]
        if len(caps) != len(requests):
            raise ValueError(f"horizons: need one per request ({len(requests)}), got {len(caps)}")
        bad = [i for i, h in enumerate(caps) if not 1 <= h <= self.horizon]
        if bad:
            raise ValueError(
                f"horizons[{bad[0]}] is {caps[bad[0]]}: each must be 1..{self.horizon} (the loop's horizon)"
            )
        cap_of = dict(zip(keys, caps))
        stages = [stage_of(i, self.client.num_stages) for i in range(len(requests))] if requests else []
        first = _first_wave(self.client.routing, requests, stages)
        routes = self.client.reset_trajectories(
            [requests[i] for i in first], [keys[i] for i in first], [stages[i] for i in first]
        )
        if not routes:
            return RolloutResult({}, RolloutStats())
        placed = set(first)
        waiting = {
            stage: [i for i in range(len(requests)) if i not in placed and stages[i] == stage] for stage in set(stages)
        }
        instructions = self.client.instructions
        buffers = {key: _Buffer(key, route, self.keep_obs, cap_of[key]) for key, route in routes.items()}
        recorded = self._recorded_keys(keys)
        recorder = Recorder(recorded, self._video_camera())
        clock = Clock(started, self.log_every_s)
        # A lane is one stage's envs on one pod, (stage, pod): the unit a call goes to. A pod of
        # the 'slices' layout is in a lane of every stage, each with a call of its own.
        stage_pods = {
            stage.stage_id: [(stage.stage_id, routed.pod) for routed in stage.pods]
            for stage in self.client.routing.stages
        }
        inflight = _InFlight()
        lost: dict[str, LostTrajectory] = {}
        failed: set[str] = set()  # pods that failed a call: no request is started on them any more

        try:
            # Reset every lane at once; then serve whichever stage is next in line, lane by lane.
            for lane in (lane for lanes in stage_pods.values() for lane in lanes):
                self._send(
                    lane,
                    [key for key, route in routes.items() if (route.stage_id, route.pod) == lane],
                    None,
                    inflight,
                    buffers,
                    lost,
                    recorded,
                )
            turn = -1  # the stage served last
            while inflight.calls:
                stage = clock.next_ready(inflight, turn)  # the next stage in turn with a pod's answer in
                turn = stage
                landed = clock.gather(stage, inflight, self.max_batch, self.batch_wait_s)
                live: list[tuple[Lane, StageBatch, int]] = []  # (lane, batch, row) still running
                ended: list[str] = []
                for pod in landed:
                    for batch in self._take(pod, stage, inflight, clock, buffers, lost, failed):
                        raised = self._env_raised(batch, buffers)  # lost; their envs are freed as ended
                        lost.update(raised)
                        ended.extend(raised)
                        for row, key in enumerate(batch.traj_keys):
                            if key in raised:
                                continue
                            buffers[key].add(batch, row)
                            recorder.add(key, batch, row)
                            if buffers[key].ended():
                                ended.append(key)
                            else:
                                live.append((pod, batch, row))
                clock.maybe_log(buffers)
                # Refill: the waiting requests of this stage start on the envs free now, on pods
                # without a call in flight (the ones just landed first).
                idle = landed + [pod for pod in stage_pods[stage] if pod not in inflight.calls and pod not in landed]
                resets = self._refill(
                    stage, waiting.get(stage, []), ended, requests, keys, cap_of, idle, failed, buffers
                )
                stepped = list(dict.fromkeys(pod for pod, _, _ in live))
                for pod in resets:
                    if pod not in stepped:  # nothing to step there: reset at once, before the policy
                        self._send(pod, resets[pod], None, inflight, buffers, lost, recorded)
                if not live:
                    continue
                with clock.in_policy(stage):
                    actions = self._act(live, instructions)  # the policy, on the stage's landed pods
                for pod in stepped:  # each pod its next actions as soon as they exist
                    rows = [j for j, (on, _, _) in enumerate(live) if on == pod]
                    # One call, one chunk length: the pod's shortest remaining horizon cuts them all.
                    left = min(buffers[actions.traj_keys[j]].left() for j in rows)
                    self._send(pod, resets.get(pod, []), actions.rows(rows, left), inflight, buffers, lost, recorded)
        except BaseException:
            inflight.cancel_all()  # Ctrl-C or a refused call: the client takes new calls at once
            raise

        for stage, left_over in waiting.items():
            for i in left_over:
                key, (task_id, state_id) = keys[i], requests[i]
                lost[key] = LostTrajectory(
                    traj_key=key,
                    route=TrajRoute("", -1, task_id, stage, int(state_id)),
                    steps=0,
                    reason=f"no env of task {task_id!r} on stage {stage} was left: its pods failed",
                )
        trajectories = {key: buffers[key].finish() for key in keys if key in buffers and key not in lost}
        videos = self._write_videos(recorder)
        return RolloutResult(trajectories, clock.stats(trajectories), videos, lost)

    def _take(
        self,
        pod: Lane,
        stage: int,
        inflight: _InFlight,
        clock: Clock,
        buffers: Mapping[str, _Buffer],
        lost: dict[str, LostTrajectory],
        failed: set[str],
    ) -> list[StageBatch]:
        """A landed pod call's answers (resets, then steps); a failed one's trajectories without
        an answer are lost, those with one go on."""
        call, carried = inflight.pop(pod)
        try:
            return [batch for batch in clock.take(stage, call, pod[1]) if batch.n]
        except (PodUnavailableError, RoutingChangedError) as exc:
            failed.add(pod[1])
            answered = [batch for batch in (exc.answered or ()) if batch is not None and batch.n]
            got = {key for batch in answered for key in batch.traj_keys}
            lost.update(self._lose([key for key in carried if key not in got], buffers, exc))
            if answered:
                clock.simulated(stage, answered[0])
            return answered

    def _refill(
        self,
        stage: int,
        waiting: list[int],
        ended: list[str],
        requests: Sequence[tuple[str, int]],
        keys: Sequence[str],
        cap_of: Mapping[str, int],
        pods: list[Lane],
        failed: set[str],
        buffers: dict[str, _Buffer],
    ) -> dict[Lane, list[str]]:
        """Free the envs of ``ended`` trajectories and place waiting requests (in request order)
        on free envs of their task on the lanes ``pods``; return the new traj_keys to reset, by lane."""
        resets: dict[Lane, list[str]] = {}
        if not waiting:
            return resets
        live = self.client.routes
        self.client.retire_trajectories([key for key in ended if key in live])
        candidates = [pod for _, pod in pods if pod not in failed]
        full: set[str] = set()  # tasks with no free env left on the candidates
        for i in list(waiting):
            if requests[i][0] in full:
                continue
            route = self.client.place_trajectory(keys[i], requests[i], stage, candidates)
            if route is None:
                full.add(requests[i][0])
                continue
            waiting.remove(i)
            buffers[keys[i]] = _Buffer(keys[i], route, self.keep_obs, cap_of[keys[i]])
            resets.setdefault((route.stage_id, route.pod), []).append(keys[i])
        return resets

    def _send(
        self,
        pod: Lane,
        reset: list[str],
        step: StepActions | None,
        inflight: _InFlight,
        buffers: Mapping[str, _Buffer],
        lost: dict[str, LostTrajectory],
        recorded: Sequence[str] = (),
    ) -> None:
        """Send one lane (a stage's envs on a pod) its resets and its actions in one call, noted in
        ``inflight`` (nothing to send: no call).

        Trajectories whose envs went away when another call re-read the routing are refused
        before anything is sent: they are lost, and the rest is sent without them.
        """
        while reset or (step is not None and step.traj_keys):
            try:
                record = [key for key in recorded if key in step.traj_keys] if step is not None and step.chunk else []
                call = self.client.pod_call(pod[1], reset=reset, step=step, record=record)
            except RoutingChangedError as exc:
                named = set(exc.traj_keys)
                gone = [key for key in [*reset, *step] if key in named]
                if not gone:
                    raise  # not about these trajectories: sending again would meet it again
                lost.update(self._lose(gone, buffers, exc))
                reset = [key for key in reset if key not in named]
                if step is not None:
                    step = step.rows([j for j, key in enumerate(step.traj_keys) if key not in named])
                continue
            stepped = [] if step is None else step.traj_keys
            for j, key in enumerate(stepped):
                buffers[key].act(step.array[j] if step.chunk is not None else step.array[j : j + 1])  # type: ignore[union-attr]
            inflight.add(pod, call, [*reset, *stepped])
            return

    @staticmethod
    def _env_raised(batch: StageBatch, buffers: Mapping[str, _Buffer]) -> dict[str, LostTrajectory]:
        """The trajectories of ``batch`` (a reset or step answer) whose env raised, as lost: their
        rows did nothing, and ``steps`` counts the actions applied before."""
        lost: dict[str, LostTrajectory] = {}
        for key, kind, message in batch.errors:
            buffer = buffers[key]
            route, call = buffer.route, "reset" if buffer.sent is None else "step"
            reason = f"env {route.env_index} of pod {route.pod!r} raised {kind} in its {call}: {message}"
            logger.warning("rollout: trajectory %s lost: %s", key, reason)
            lost[key] = LostTrajectory(traj_key=key, route=route, steps=len(buffer.actions), reason=reason)
        return lost

    @staticmethod
    def _lose(
        keys: list[str], buffers: Mapping[str, _Buffer], error: PodUnavailableError | RoutingChangedError
    ) -> dict[str, LostTrajectory]:
        """The trajectories of a failed call that got no answer, as lost: the ones the error names
        and any other the call carried without an answer (a call that met several failures)."""
        named = set(error.traj_keys)
        logger.warning("rollout: %d trajectories lost: %s", len(keys), error)
        return {
            key: LostTrajectory(
                traj_key=key,
                route=buffers[key].route,
                steps=len(buffers[key].actions),
                reason=str(error) if key in named else f"lost with its stage's call, which failed: {error}",
            )
            for key in keys
        }

    def _act(self, rows: list[tuple[Lane, StageBatch, int]], instructions: Mapping[str, str]) -> StepActions:
        """Run the policy on ``rows`` (``(lane, batch, row)``), at most ``max_batch`` a call;
        return the rows' actions or chunks, as the client checked them (float32)."""
        size = self.max_batch or len(rows)
        out: list[np.ndarray] = []
        for begin in range(0, len(rows), size):
            part = rows[begin : begin + size]
            obs = _to_tensors(_gather_obs([(batch, row) for _, batch, row in part]), self.device)
            task_ids = [batch.task_ids[row] for _, batch, row in part]
            with torch.no_grad():
                actions = self.policy(obs, [instructions.get(t, "") for t in task_ids], task_ids)
            out.append(actions.detach().to("cpu", torch.float32).numpy())
        keys = [batch.traj_keys[row] for _, batch, row in rows]
        return self.client.step_actions(keys, out[0] if len(out) == 1 else np.concatenate(out))

    def _video_camera(self) -> str | None:
        """The camera to record, checked against the observation space before anything runs."""
        if not self.record:
            return None
        space = self.client.observation_space
        images = space.spaces.get("images") if isinstance(space, spaces.Dict) else None
        cameras = list(images.spaces) if images is not None else []
        if not cameras:
            raise ValueError("videos asked for, but the observations have no camera images")
        camera = self.camera or cameras[0]
        if camera not in cameras:
            raise ValueError(f"cannot record camera {camera!r}: the observations have {cameras}")
        return camera

    def _recorded_keys(self, keys: list[str]) -> list[str]:
        if isinstance(self.record, int):
            return keys[: self.record]
        unknown = [k for k in self.record if k not in keys]
        if unknown:
            raise ValueError(f"record names traj_keys not in this batch: {unknown}")
        return list(self.record)

    def _write_videos(self, recorder: Recorder) -> dict[str, Path]:
        videos: dict[str, Path] = {}
        if self.video_dir is None:
            return videos
        for key, frames in recorder.frames.items():
            if not frames:
                continue
            safe = re.sub(r"[^A-Za-z0-9_.-]", "_", key)
            path = self.video_dir / f"{safe}.{self.video_format}"
            write_video(path, frames, self.video_fps)
            videos[key] = path
        return videos


# -- helpers of the loop -------------------------------------------------------------------------


def _to_tensors(obs: Any, device: torch.device) -> Any:
    return trees.map_leaves(lambda leaf: torch.from_numpy(np.ascontiguousarray(leaf)).to(device), obs)


def _gather_obs(rows: list[tuple[StageBatch, int]]) -> Any:
    """One batched observation of the given rows of several answers, in order."""
    parts: list[tuple[StageBatch, list[int]]] = []
    for batch, row in rows:
        if parts and parts[-1][0] is batch:
            parts[-1][1].append(row)
        else:
            parts.append((batch, [row]))
    taken = [trees.take_rows(batch.obs, np.asarray(index)) for batch, index in parts]
    return taken[0] if len(taken) == 1 else _concat(taken)


def _concat(trees_: list[Any]) -> Any:
    """One tree whose leaves concatenate the trees' leaves along the first axis."""
    first = trees_[0]
    if isinstance(first, dict):
        return {key: _concat([tree[key] for tree in trees_]) for key in first}
    if isinstance(first, tuple):
        return tuple(_concat([tree[i] for tree in trees_]) for i in range(len(first)))
    return np.concatenate(trees_)


def _first_wave(table: RoutingTable, requests: Sequence[tuple[str, int]], stages: Sequence[int]) -> list[int]:
    """The indices of the requests placed at the start: in request order, as many of each
    (stage, task) as the stage has envs of the task; the others wait for a free env.

    Raises:
        ValueError: a malformed request (names it).
        CapacityError: a stage has no env of a request's task (names task, stage and requests).
    """
    checked = [check_request(i, request) for i, request in enumerate(requests)]
    capacity: dict[tuple[int, str], int] = {}
    pods: dict[tuple[int, str], list[str]] = {}
    for stage in table.stages:
        for routed in stage.pods:
            for block in routed.tasks:
                where = (stage.stage_id, block.task_id)
                capacity[where] = capacity.get(where, 0) + block.num_envs
                pods.setdefault(where, []).append(routed.pod)
    if not table.stages:
        return list(range(len(requests)))  # the client names the table without stages
    wave: list[int] = []
    taken: Counter[tuple[int, str]] = Counter()
    for i, (task_id, _) in enumerate(checked):
        where = (stages[i], task_id)
        if not capacity.get(where):
            asked = [j for j, (t, _) in enumerate(checked) if (stages[j], t) == where]
            raise CapacityError(task_id, stages[i], 0, asked, sorted(set(pods.get(where, []))))
        if taken[where] < capacity[where]:
            taken[where] += 1
            wave.append(i)
    return wave


def _take_row(obs: Any, row: int, keep: tuple[str, ...] | None) -> Any:
    """Row ``row`` of a batched observation (copies), its top-level keys cut to ``keep`` if given."""
    if isinstance(obs, dict) and keep is not None:
        obs = {key: value for key, value in obs.items() if key in keep}
    return trees.row(obs, row)


class _Buffer:
    """What one trajectory has seen so far."""

    def __init__(self, key: str, route: TrajRoute, keep_obs: tuple[str, ...], horizon: int) -> None:
        self.key, self.route, self.keep_obs, self.horizon = key, route, keep_obs, horizon
        self.observations: list[Any] = []
        self.actions: list[np.ndarray] = []
        self.rewards: list[float] = []
        self.num_steps: list[int] = []
        self.sent: np.ndarray | None = None  # the chunk ([K, A]) of the call in flight
        self.terminated = self.truncated = self.success = False

    def add(self, batch: StageBatch, row: int) -> None:
        """Take in a reset or step answer for this trajectory: each applied action and its reward."""
        if self.keep_obs:
            self.observations.append(_take_row(batch.obs, row, self.keep_obs))
        if self.sent is not None:  # a step answer
            applied = int(batch.num_steps[row])
            per_action = [
                np.reshape(values[row], -1)[:applied]
                for values in (batch.reward, batch.terminated, batch.truncated, batch.success)
            ]
            reward, terminated, truncated, success = per_action
            self.actions.extend(self.sent[:applied])
            self.rewards.extend(float(r) for r in reward)
            self.num_steps.append(applied)
            self.terminated = bool(terminated[-1]) if applied else self.terminated
            self.truncated = bool(truncated[-1]) if applied else self.truncated
            self.success = self.success or bool(success.any())
            self.sent = None
        else:
            self.success = self.success or bool(np.reshape(batch.success[row], -1).any())

    def act(self, chunk: np.ndarray) -> None:
        """Note the actions sent (``[K, *action shape]``; one action is a chunk of one);
        :meth:`add` keeps what was applied."""
        self.sent = chunk

    def left(self) -> int:
        """Actions left before the horizon."""
        return self.horizon - len(self.actions)

    def ended(self) -> bool:
        if len(self.actions) >= self.horizon and not (self.terminated or self.truncated):
            self.truncated = True  # the horizon is a time limit
        return self.terminated or self.truncated

    def finish(self) -> Trajectory:
        steps = len(self.actions)
        dones = torch.zeros(steps, dtype=torch.bool)
        if steps:
            dones[-1] = True
        action_dim = self.actions[0].shape if self.actions else (0,)
        return Trajectory(
            traj_key=self.key,
            route=self.route,
            observations=trees.map_leaves(torch.from_numpy, trees.stack(self.observations))
            if self.observations
            else {},
            actions=torch.from_numpy(np.stack(self.actions)) if self.actions else torch.zeros((0, *action_dim)),
            rewards=torch.tensor(self.rewards, dtype=torch.float32),
            dones=dones,
            terminated=self.terminated,
            truncated=self.truncated,
            success=self.success,
            num_steps=torch.tensor(self.num_steps, dtype=torch.int32),
        )


class _InFlight:
    """The call in flight on each lane (at most one) and the traj_keys it carries; a lane's stage
    is its first item."""

    def __init__(self) -> None:
        self.calls: dict[Lane, tuple[PendingCall[tuple[StageBatch, StageBatch]], list[str]]] = {}

    def add(self, pod: Lane, call: PendingCall[tuple[StageBatch, StageBatch]], keys: list[str]) -> None:
        self.calls[pod] = (call, keys)

    def pop(self, pod: Lane) -> tuple[PendingCall[tuple[StageBatch, StageBatch]], list[str]]:
        return self.calls.pop(pod)

    def cancel_all(self) -> None:
        """Cancel every call in flight (what the pods did stays done)."""
        for call, _ in self.calls.values():
            call.cancel()
        self.calls.clear()


class Clock:
    """Timing of one rollout: policy intervals, stage-call intervals, waits, progress logs."""

    def __init__(self, started: float, log_every_s: float) -> None:
        self.started = started
        self.log_every_s = log_every_s
        self.last_log = started
        self.policy: list[tuple[float, float]] = []
        self.simulation: list[tuple[float, float]] = []
        self.timeline: list[tuple[str, int, float, float]] = []
        self.pod_calls: list[tuple[int, str, float, float, int, int]] = []
        self.wait_s = 0.0

    def next_ready(self, inflight: _InFlight, after: int) -> int:
        """Return the first stage after ``after``, in turn, of which a pod's call has finished;
        when none has, wait (timed as waiting) until one does."""
        begin = time.perf_counter()
        try:
            while True:
                landed = {lane[0] for lane, (call, _) in inflight.calls.items() if call.done()}
                if landed:
                    return min(landed, key=lambda stage: (stage <= after, stage))
                PendingCall.wait_any([call for call, _ in inflight.calls.values()])
        finally:
            self.wait_s += time.perf_counter() - begin

    def gather(self, stage: int, inflight: _InFlight, max_batch: int | None, wait_s: float) -> list[Lane]:
        """The pods of ``stage`` whose calls have finished, in the stage's pod order; with
        ``wait_s`` > 0, first wait up to that long (timed as waiting) for the stage's other pods
        while their rows would still fit in ``max_batch``."""
        deadline = time.perf_counter() + wait_s
        begin = time.perf_counter()
        while True:
            mine = [lane for lane in inflight.calls if lane[0] == stage]
            landed = [pod for pod in mine if inflight.calls[pod][0].done()]
            rows = sum(len(inflight.calls[pod][1]) for pod in landed)
            others = [inflight.calls[pod][0] for pod in mine if pod not in landed]
            left = deadline - time.perf_counter()
            if not others or left <= 0 or (max_batch is not None and rows >= max_batch):
                break
            PendingCall.wait_any(others, left)
        self.wait_s += time.perf_counter() - begin
        return landed

    def take(
        self, stage: int, call: PendingCall[tuple[StageBatch, StageBatch]], pod: str = ""
    ) -> tuple[StageBatch, StageBatch]:
        """The answer of a finished call (raising what the call raised), recorded."""
        batches = call.result()
        self.simulated(stage, batches[0])
        reset, step = batches
        self.pod_calls.append(
            (stage, pod, reset.submitted_at - self.started, reset.finished_at - self.started, reset.n, step.n)
        )
        return batches

    def simulated(self, stage: int, batch: StageBatch) -> None:
        """Record the interval a stage call's answer spent in flight."""
        self.simulation.append((batch.submitted_at, batch.finished_at))
        self.timeline.append(("sim", stage, batch.submitted_at - self.started, batch.finished_at - self.started))

    def in_policy(self, stage: int) -> Interval:
        return Interval(
            self.policy,
            lambda begin, end: self.timeline.append(("policy", stage, begin - self.started, end - self.started)),
        )

    def maybe_log(self, buffers: Mapping[str, _Buffer]) -> None:
        now = time.perf_counter()
        if now - self.last_log < self.log_every_s:
            return
        self.last_log = now
        steps = sum(len(b.actions) for b in buffers.values())
        done = sum(b.terminated or b.truncated for b in buffers.values())
        logger.info(
            "rollout: %d/%d trajectories done, %d env-steps, %.1f env-steps/s",
            done,
            len(buffers),
            steps,
            steps / max(now - self.started, 1e-9),
        )

    def stats(self, trajectories: Mapping[str, Trajectory]) -> RolloutStats:
        wall = time.perf_counter() - self.started
        steps = sum(t.length for t in trajectories.values())
        policy = covered(self.policy)
        simulation = merge(self.simulation)
        overlap = intersection(merge(self.policy), simulation)
        per_task: dict[str, list[bool]] = {}
        for trajectory in trajectories.values():
            per_task.setdefault(trajectory.route.task_id, []).append(trajectory.success)
        return RolloutStats(
            num_trajectories=len(trajectories),
            env_steps=steps,
            wall_s=wall,
            env_steps_per_s=steps / wall if wall > 0 else 0.0,
            policy_s=policy,
            simulation_s=covered(simulation),
            wait_s=self.wait_s,
            overlap_s=overlap,
            overlap_fraction=overlap / policy if policy > 0 else 0.0,
            success_per_task={task: float(np.mean(s)) for task, s in per_task.items()},
            timeline=sorted(self.timeline, key=lambda item: item[2]),
            pod_calls=list(self.pod_calls),
        )


class Interval:
    def __init__(self, into: list[tuple[float, float]], also: Callable[[float, float], None]) -> None:
        self.into = into
        self.also = also

    def __enter__(self) -> None:
        self.begin = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        end = time.perf_counter()
        self.into.append((self.begin, end))
        self.also(self.begin, end)
