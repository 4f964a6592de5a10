"""EnvLoop: the pipelined rollout. Read :meth:`EnvLoop.run` top to bottom.

Reset every trajectory, then loop over the stages: wait for stage s's observations, run the
policy on them, send stage s's actions without waiting, and go on to the next stage, so the policy
works on one stage while the pods simulate the others. The next stage is the first in turn
(s+1, s+2, ...) whose observations are already in; only when none is does the loop wait, for
whichever lands first. So a slow pod holds up its own stage only: with a stage per pod (or per
group of pods), fast pods step on while a slow one finishes. A trajectory ends on termination,
truncation or the horizon and is not stepped again. The result is per-trajectory tensors keyed
by traj_key, plus timing stats and, for chosen trajectories, videos of a camera.

A policy may act in chunks: returning ``[n, K, action_dim]``, each trajectory's K actions go to
its pod in one call (applied in order, stopping at a termination or truncation, rendered once).
The loop records every applied action and its reward; the horizon counts actions, not calls (a
chunk that would pass it is cut to fit). Videos of a chunked rollout carry every action's frame:
the pods render those frames for the recorded trajectories only.

Batches whose size is not a multiple of the number of stages are accepted: request ``i`` goes to
stage ``i % S`` (:func:`vecsim.sampler.stage_of`), so stage sizes differ by at most one. An empty
batch is a no-op, and a stage without trajectories is never called.

A pod that dies, hangs past the client's timeout or rebuilds its envs mid-episode does not fail
the rollout: its trajectories are reported lost by traj_key (:attr:`RolloutResult.lost`, with
their route, to resample) and every other trajectory runs on, those of the other pods of the
same stage call included (the client's error carries their rows: ``error.answered``).
"""

from __future__ import annotations

import logging
import re
import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from vecsim import trees
from vecsim.client import (
    PendingCall,
    PodUnavailableError,
    RoutingChangedError,
    StageBatch,
    StageClient,
    TrajRoute,
)

logger = logging.getLogger(__name__)

__all__ = [
    "EnvLoop",
    "ExampleCNNPolicy",
    "LostTrajectory",
    "RolloutResult",
    "RolloutStats",
    "Trajectory",
    "write_video",
]

# policy(observations, instructions, task_ids) -> actions [n, action_dim] or chunks [n, K, action_dim]
Policy = Callable[[dict[str, Any], list[str], list[str]], torch.Tensor]


# -- the example policy --------------------------------------------------------------------------


def _hash_bucket(text: str, buckets: int) -> int:
    # crc32, not hash(): Python salts str hashes per process.
    return zlib.crc32(text.encode()) % buckets


class ExampleCNNPolicy(nn.Module):
    """A small CNN policy over vecsim's observation: camera images, proprio, instruction, task id.

    Each camera goes through one shared conv encoder; proprio through a linear layer; the
    instruction as a hashed bag of words and the task id as a hashed embedding. A tanh head maps
    to the action space's bounds. With ``noise_std > 0`` Gaussian noise explores around it.
    """

    def __init__(
        self,
        observation_space: spaces.Dict,
        action_space: spaces.Box,
        hidden: int = 64,
        noise_std: float = 0.0,
        buckets: int = 1024,
        seed: int = 0,
    ) -> None:
        super().__init__()
        torch.manual_seed(seed)
        image_space = observation_space.spaces.get("images")
        self.cameras = list(image_space.spaces) if image_space is not None else []
        self.encoder = nn.Sequential(
            nn.Conv2d(3, 16, kernel_size=5, stride=2, padding=2),
            nn.ReLU(),
            nn.Conv2d(16, 32, kernel_size=3, stride=2, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(1),
            nn.Flatten(),
        )
        proprio_dim = int(np.prod(observation_space["proprio"].shape))
        self.proprio = nn.Linear(proprio_dim, hidden)
        self.buckets = buckets
        self.words = nn.EmbeddingBag(buckets, 16, mode="mean")
        self.tasks = nn.Embedding(buckets, 16)
        action_dim = int(np.prod(action_space.shape))
        self.head = nn.Sequential(
            nn.Linear(32 * len(self.cameras) + hidden + 32, hidden), nn.ReLU(), nn.Linear(hidden, action_dim)
        )
        low, high = np.asarray(action_space.low, np.float32), np.asarray(action_space.high, np.float32)
        bounded = np.isfinite(low) & np.isfinite(high)
        self.register_buffer("center", torch.from_numpy(np.where(bounded, (low + high) / 2, 0.0).astype(np.float32)))
        self.register_buffer("scale", torch.from_numpy(np.where(bounded, (high - low) / 2, 1.0).astype(np.float32)))
        self.noise_std = float(noise_std)

    def forward(self, obs: dict[str, Any], instructions: list[str], task_ids: list[str]) -> torch.Tensor:
        """Return actions ``[n, action_dim]`` for a batch of observations (tensors on the module's device)."""
        device = self.center.device
        features = []
        for camera in self.cameras:
            image = obs["images"][camera].to(device=device, dtype=torch.float32) / 255.0
            features.append(self.encoder(image.permute(0, 3, 1, 2)))
        features.append(torch.relu(self.proprio(obs["proprio"].to(device=device, dtype=torch.float32))))
        words = [[_hash_bucket(w, self.buckets) for w in text.lower().split()] or [0] for text in instructions]
        flat = torch.tensor([b for ws in words for b in ws], device=device, dtype=torch.long)
        offsets = torch.tensor(np.cumsum([0] + [len(ws) for ws in words[:-1]]), device=device, dtype=torch.long)
        features.append(self.words(flat, offsets))
        features.append(self.tasks(torch.tensor([_hash_bucket(t, self.buckets) for t in task_ids], device=device)))
        mean = torch.tanh(self.head(torch.cat(features, dim=1)))
        if self.noise_std > 0:
            mean = (mean + self.noise_std * torch.randn_like(mean)).clamp(-1.0, 1.0)
        return self.center + self.scale * mean


# -- results -------------------------------------------------------------------------------------


@dataclass
class Trajectory:
    """One finished trajectory of T actions, taken over C policy calls.

    ``observations`` holds the kept keys of the observation (``images`` and/or ``proprio``),
    each ``[C+1, ...]``: what the policy saw at each call, and the last one; ``actions``
    ``[T, A]``; ``rewards`` ``[T]``; ``dones`` ``[T]`` (True at the last step); ``num_steps``
    ``[C]``: the actions applied after each observation (all ones, and C = T, for a policy of
    one action per call). ``success``: the task was solved at some step.
    """

    traj_key: str
    route: TrajRoute
    observations: dict[str, Any]
    actions: torch.Tensor
    rewards: torch.Tensor
    dones: torch.Tensor
    terminated: bool
    truncated: bool
    success: bool
    num_steps: torch.Tensor = field(default_factory=lambda: torch.zeros(0, dtype=torch.int32))

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])


@dataclass
class RolloutStats:
    """How a rollout spent its time.

    ``policy_s``: time in the policy (including moving observations to tensors);
    ``simulation_s``: time with at least one stage call in flight; ``wait_s``: time the loop
    blocked waiting for observations; ``overlap_fraction``: share of ``policy_s`` during which
    some stage was simulating (1.0 = the policy never ran alone).
    """

    num_trajectories: int = 0
    env_steps: int = 0
    wall_s: float = 0.0
    env_steps_per_s: float = 0.0
    policy_s: float = 0.0
    simulation_s: float = 0.0
    wait_s: float = 0.0
    overlap_s: float = 0.0
    overlap_fraction: float = 0.0
    success_per_task: dict[str, float] = field(default_factory=dict)
    # (what, stage_id, begin_s, end_s) from the rollout's start; what is "policy" or "sim".
    timeline: list[tuple[str, int, float, float]] = field(default_factory=list)


@dataclass(frozen=True)
class LostTrajectory:
    """A trajectory whose env went away mid-episode: its pod died, did not answer within the
    client's timeout, or rebuilt its envs. ``route`` names what to resample (its task and state
    id); ``steps`` is how many actions it had taken; ``reason`` is the client's error."""

    traj_key: str
    route: TrajRoute
    steps: int
    reason: str


@dataclass
class RolloutResult:
    """Finished trajectories keyed by traj_key (in request order), the lost ones (neither
    finished nor failed the rollout: resample them), stats, and the videos written."""

    trajectories: dict[str, Trajectory]
    stats: RolloutStats
    videos: dict[str, Path] = field(default_factory=dict)
    lost: dict[str, LostTrajectory] = field(default_factory=dict)


# -- the loop ------------------------------------------------------------------------------------


class EnvLoop:
    """The pipelined rollout of a policy over a :class:`StageClient`'s stages.

    ``horizon`` caps every trajectory's length (the pods' own ``max_episode_steps`` may end it
    sooner). ``keep_obs`` names the observation keys stored per trajectory (``()`` stores none).
    ``record`` names traj_keys (or a count of the first trajectories) whose camera ``camera``
    (default: the first) is written to ``video_dir`` as ``<traj_key>.<video_format>`` (mp4 or
    gif). Progress is logged every ``log_every_s`` seconds.
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
    ) -> None:
        """Set the loop up; nothing runs until :meth:`run`.

        Raises:
            ValueError: ``horizon < 1``, videos asked for without ``video_dir``, or an unknown
                ``video_format``.
        """
        if horizon < 1:
            raise ValueError(f"horizon must be >= 1, got {horizon}")
        if record and video_dir is None:
            raise ValueError("record asks for videos: give video_dir")
        if video_format not in ("mp4", "gif"):
            raise ValueError(f"video_format must be 'mp4' or 'gif', got {video_format!r}")
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

    def run(self, requests: Sequence[tuple[str, int]], traj_keys: Sequence[str] | None = None) -> RolloutResult:
        """Roll out one trajectory per request ``(task_id, state_id)``; return them with stats.

        Trajectories whose pod went away (``PodUnavailableError``, ``RoutingChangedError``) end
        up in the result's ``lost``, not in its ``trajectories``; the trajectories of the pods
        that answered the same call go on.

        Raises:
            CapacityError: a stage lacks envs for a task (see ``StageClient.reset_trajectories``).
            ValueError: a malformed request, or videos of trajectories or a camera that are not
                there.
            PodRequestError, StaleGenerationError: from the client (a refused request).
        """
        started = time.perf_counter()
        routes = self.client.reset_trajectories(requests, traj_keys)
        if not routes:
            return RolloutResult({}, RolloutStats())
        instructions = self.client.instructions
        buffers = {key: _Buffer(key, route, self.keep_obs) for key, route in routes.items()}
        recorded = self._recorded_keys(list(routes))
        recorder = _Recorder(recorded, self._video_camera())
        clock = _Clock(started, self.log_every_s)

        # Reset every stage at once; then serve whichever stage is next in line.
        pending: dict[int, PendingCall[StageBatch]] = {
            stage: self.client.reset_stage(stage)
            for stage in range(self.client.num_stages)
            if self.client.stage_traj_keys(stage)
        }
        carried = {stage: self.client.stage_traj_keys(stage) for stage in pending}
        lost: dict[str, LostTrajectory] = {}
        turn = -1  # the stage served last
        while pending:
            stage = clock.next_ready(pending, turn)  # the next stage in turn whose answer is in
            turn = stage
            try:
                batch = clock.take(stage, pending.pop(stage))  # stage s's observations
            except (PodUnavailableError, RoutingChangedError) as exc:
                # The failed pods' trajectories are lost; the pods that answered go on.
                batch = exc.answered
                answered = set(batch.traj_keys) if batch is not None else set()
                lost.update(self._lose([k for k in carried[stage] if k not in answered], buffers, exc))
                if not answered:
                    continue
                clock.simulated(stage, batch)
            live = []
            for row, key in enumerate(batch.traj_keys):
                buffers[key].add(batch, row)
                recorder.add(key, batch, row)
                if not buffers[key].ended(self.horizon):
                    live.append(row)
            clock.maybe_log(buffers)
            if not live:
                continue  # this stage is finished
            with clock.in_policy(stage):
                actions = self._act(batch, live, instructions)  # the policy, on stage s
            # A stage's live trajectories have taken the same number of actions (one that applied
            # fewer stopped), so one cut keeps every chunk within the horizon and of one length.
            left = self.horizon - len(buffers[batch.traj_keys[live[0]]].actions)
            step = {batch.traj_keys[row]: _within(actions[row], left) for row in live}
            sent = self._send(stage, step, buffers, lost, recorded)  # don't wait: on to the next stage
            if sent is not None:
                pending[stage], carried[stage] = sent

        trajectories = {key: buffer.finish() for key, buffer in buffers.items() if key not in lost}
        videos = self._write_videos(recorder)
        return RolloutResult(trajectories, clock.stats(trajectories), videos, lost)

    def _send(
        self,
        stage: int,
        step: dict[str, np.ndarray],
        buffers: Mapping[str, _Buffer],
        lost: dict[str, LostTrajectory],
        recorded: Sequence[str] = (),
    ) -> tuple[PendingCall[StageBatch], list[str]] | None:
        """Send a stage's actions; return the call and the traj_keys it carries (None: nothing left).

        Trajectories whose envs went away when another stage's call re-read the routing are
        refused before anything is sent: they are lost, and the rest is sent without them.
        """
        while step:
            try:
                chunked = next(iter(step.values())).ndim == 2
                record = [key for key in recorded if key in step] if chunked else []
                call = self.client.step_stage(stage, step, record=record)
            except RoutingChangedError as exc:
                named = set(exc.traj_keys)
                gone = [key for key in step if key in named]
                if not gone:
                    raise  # not about these trajectories: sending again would meet it again
                lost.update(self._lose(gone, buffers, exc))
                step = {key: action for key, action in step.items() if key not in gone}
                continue
            for key, action in step.items():
                buffers[key].act(action)
            return call, list(step)
        return None

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

    def _act(self, batch: StageBatch, rows: list[int], instructions: Mapping[str, str]) -> dict[int, np.ndarray]:
        """Run the policy on rows ``rows`` of a batch; return ``{row: action or chunk}`` as float32 arrays."""
        index = np.asarray(rows)
        obs = _to_tensors(batch.obs, index, self.device)
        task_ids = [batch.task_ids[r] for r in rows]
        with torch.no_grad():
            actions = self.policy(obs, [instructions.get(t, "") for t in task_ids], task_ids)
        actions = actions.detach().to("cpu", torch.float32).numpy()
        return {row: actions[j] for j, row in enumerate(rows)}

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

    def _write_videos(self, recorder: _Recorder) -> dict[str, Path]:
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


def _to_tensors(obs: Any, rows: np.ndarray, device: torch.device) -> Any:
    return trees.map_leaves(lambda leaf: torch.from_numpy(np.ascontiguousarray(leaf[rows])).to(device), obs)


def _within(action: np.ndarray, left: int) -> np.ndarray:
    """A chunk (``[K, A]``) cut to at most ``left`` actions; one action (``[A]``) as it is."""
    return action[:left] if action.ndim == 2 else action


def _take_row(obs: Any, row: int, keep: tuple[str, ...] | None) -> Any:
    """Row ``row`` of a batched observation (copies), its top-level keys cut to ``keep`` if given."""
    if isinstance(obs, dict) and keep is not None:
        obs = {key: value for key, value in obs.items() if key in keep}
    return trees.row(obs, row)


class _Buffer:
    """What one trajectory has seen so far."""

    def __init__(self, key: str, route: TrajRoute, keep_obs: tuple[str, ...]) -> None:
        self.key, self.route, self.keep_obs = key, route, keep_obs
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
            per_action = [np.reshape(values[row], -1)[:applied] for values in
                          (batch.reward, batch.terminated, batch.truncated, batch.success)]  # fmt: skip
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

    def act(self, action: np.ndarray) -> None:
        """Note the action (``[A]``) or chunk (``[K, A]``) sent; :meth:`add` keeps what was applied."""
        self.sent = action[None] if action.ndim == 1 else action

    def ended(self, horizon: int) -> bool:
        if len(self.actions) >= horizon and not (self.terminated or self.truncated):
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
            observations=trees.map_leaves(torch.from_numpy, trees.stack(self.observations)) if self.observations else {},
            actions=torch.from_numpy(np.stack(self.actions)) if self.actions else torch.zeros((0, *action_dim)),
            rewards=torch.tensor(self.rewards, dtype=torch.float32),
            dones=dones,
            terminated=self.terminated,
            truncated=self.truncated,
            success=self.success,
            num_steps=torch.tensor(self.num_steps, dtype=torch.int32),
        )


class _Recorder:
    """Frames of one camera for the trajectories chosen for video."""

    def __init__(self, keys: list[str], camera: str | None) -> None:
        self.frames: dict[str, list[np.ndarray]] = {key: [] for key in keys}
        self.camera = camera

    def add(self, key: str, batch: StageBatch, row: int) -> None:
        """Take the frames of a reset or step answer: a chunk's recorded frames, one per applied
        action, or else the observation's."""
        if key not in self.frames:
            return
        chunk = batch.frames.get(key)
        if chunk is not None:
            self.frames[key].extend(np.array(frame) for frame in chunk[self.camera][: int(batch.num_steps[row])])
        else:
            self.frames[key].append(np.array(batch.obs["images"][self.camera][row]))


class _Clock:
    """Timing of one rollout: policy intervals, stage-call intervals, waits, progress logs."""

    def __init__(self, started: float, log_every_s: float) -> None:
        self.started = started
        self.log_every_s = log_every_s
        self.last_log = started
        self.policy: list[tuple[float, float]] = []
        self.simulation: list[tuple[float, float]] = []
        self.timeline: list[tuple[str, int, float, float]] = []
        self.wait_s = 0.0

    def next_ready(self, pending: Mapping[int, PendingCall[StageBatch]], after: int) -> int:
        """Return the first stage after ``after``, in turn, whose call has finished; when none
        has, wait (timed as waiting) until one does."""
        order = sorted(pending, key=lambda stage: (stage <= after, stage))
        begin = time.perf_counter()
        try:
            while True:
                for stage in order:
                    if pending[stage].done():
                        return stage
                PendingCall.wait_any([pending[stage] for stage in order])
        finally:
            self.wait_s += time.perf_counter() - begin

    def take(self, stage: int, call: PendingCall[StageBatch]) -> StageBatch:
        """The answer of a finished call (raising what the call raised), recorded."""
        batch = call.result()
        self.simulated(stage, batch)
        return batch

    def simulated(self, stage: int, batch: StageBatch) -> None:
        """Record the interval a stage call's answer spent in flight."""
        self.simulation.append((batch.submitted_at, batch.finished_at))
        self.timeline.append(("sim", stage, batch.submitted_at - self.started, batch.finished_at - self.started))

    def in_policy(self, stage: int) -> _Interval:
        return _Interval(self.policy, lambda begin, end: self.timeline.append(
            ("policy", stage, begin - self.started, end - self.started)))

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
        policy = _measure(self.policy)
        simulation = _merge(self.simulation)
        overlap = _intersection(_merge(self.policy), simulation)
        per_task: dict[str, list[bool]] = {}
        for trajectory in trajectories.values():
            per_task.setdefault(trajectory.route.task_id, []).append(trajectory.success)
        return RolloutStats(
            num_trajectories=len(trajectories),
            env_steps=steps,
            wall_s=wall,
            env_steps_per_s=steps / wall if wall > 0 else 0.0,
            policy_s=policy,
            simulation_s=_measure(simulation),
            wait_s=self.wait_s,
            overlap_s=overlap,
            overlap_fraction=overlap / policy if policy > 0 else 0.0,
            success_per_task={task: float(np.mean(s)) for task, s in per_task.items()},
            timeline=sorted(self.timeline, key=lambda item: item[2]),
        )


class _Interval:
    def __init__(self, into: list[tuple[float, float]], also: Callable[[float, float], None]) -> None:
        self.into = into
        self.also = also

    def __enter__(self) -> None:
        self.begin = time.perf_counter()

    def __exit__(self, *exc: object) -> None:
        end = time.perf_counter()
        self.into.append((self.begin, end))
        self.also(self.begin, end)


def _merge(intervals: list[tuple[float, float]]) -> list[tuple[float, float]]:
    merged: list[tuple[float, float]] = []
    for begin, end in sorted(intervals):
        if merged and begin <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], end))
        else:
            merged.append((begin, end))
    return merged


def _measure(intervals: list[tuple[float, float]]) -> float:
    return sum(end - begin for begin, end in _merge(intervals))


def _intersection(a: list[tuple[float, float]], b: list[tuple[float, float]]) -> float:
    """Total length of the overlap of two sorted, disjoint interval lists."""
    total, i, j = 0.0, 0, 0
    while i < len(a) and j < len(b):
        total += max(0.0, min(a[i][1], b[j][1]) - max(a[i][0], b[j][0]))
        if a[i][1] < b[j][1]:
            i += 1
        else:
            j += 1
    return total


def write_video(path: str | Path, frames: Sequence[np.ndarray], fps: int = 10) -> Path:
    """Write uint8 ``HxWx3`` frames to ``path``: ``.gif`` with Pillow, anything else with ffmpeg.

    Returns the path written.

    Raises:
        ValueError: no frames, or frames that are not uint8 ``HxWx3`` of one size.
    """
    path = Path(path)
    if not frames:
        raise ValueError(f"{path}: no frames to write")
    shapes = {np.shape(f) for f in frames}
    if len(shapes) != 1 or len(next(iter(shapes))) != 3 or next(iter(shapes))[2] != 3:
        raise ValueError(f"{path}: frames must be HxWx3 of one size, got shapes {sorted(shapes)}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == ".gif":
        from PIL import Image

        images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
        images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
        return path
    import imageio.v2 as imageio

    height, width, _ = next(iter(shapes))
    # yuv420p needs even sides: pad by one edge pixel rather than let ffmpeg rescale.
    pad = ((0, height % 2), (0, width % 2), (0, 0))
    with imageio.get_writer(path, fps=fps, codec="libx264", macro_block_size=1, pixelformat="yuv420p") as writer:
        for frame in frames:
            writer.append_data(np.pad(np.asarray(frame, dtype=np.uint8), pad, mode="edge"))
    return path
