"""RLinf's LIBERO env contract over a vecsim job: ``env_type: libero`` plus a ``vecsim:`` block.

:class:`VecsimLiberoEnv` has the constructor, attributes and methods of RLinf 0.3.0's
``rlinf.envs.libero.libero_env.LiberoEnv`` (cited below as ``libero_env.py:<line>``), so RLinf's
own ``EnvWorker`` drives it unchanged; :func:`register` makes ``get_env_cls("libero", cfg)``
return it for every env config that has a ``vecsim`` block (the job's address:
``vecsim.controller_url``, ``vecsim.pod_urls``, or ``$VECSIM_CONTROLLER_URL``)::

    # env.train / env.eval of the RLinf config, beside RLinf's own LIBERO keys:
    #   vecsim: {controller_url: "http://controller:8000"}
    import vecsim.trainers.rlinf
    vecsim.trainers.rlinf.register()   # in every process that builds envs (Ray: a worker setup hook)

The task mapping rule. RLinf's reset id is suite-global (task ``t``'s rows come after those of
tasks ``0..t-1``; 50 a task for LIBERO) and RLinf rebuilds an env for whatever task it draws; a
vecsim env's task is fixed by the job. So each RLinf env slot runs each episode on a free env of
the drawn task on the job stage ``vecsim.stage_id`` (default: the env's ``seed_offset``): a slot
keeps its env while its task stays, else it takes the free env of the task on the pod holding
the fewest slots. A stage needs as many envs of a task as slots may draw it at once
(``num_envs`` of every task RLinf may draw, or fewer with ``task_id_filter`` / GRPO groups); a
reset that does not fit raises ``ValueError`` naming the task, the reset ids and the stage.
RLinf's bookkeeping (reset-id draws, rewards, episode statistics, flags) runs here, re-enacted
from its code; the pods run physics and report success (``ended_envs="step"``: ended envs keep
being stepped, as RLinf steps them). docs/trainers.md ("RLinf") lists what differs.
"""

from __future__ import annotations

import logging
import os
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from gymnasium.error import ClosedEnvironmentError

from vecsim.client.conventions import camera_key_map, suite_of, suite_task_index
from vecsim.client.errors import PodUnavailableError, RoutingChangedError
from vecsim.client.routing import RoutedEnv, TrajRoute, routed_envs
from vecsim.client.stage import StageBatch, StageClient

from .rlinf_bookkeeping import LIBERO_SUITE_TASKS, LiberoBookkeeping, to_tensor

logger = logging.getLogger(__name__)

__all__ = ["CONTROLLER_URL_ENV", "LIBERO_SUITE_TASKS", "VecsimLiberoEnv", "place_slots", "register"]

# Where the job is when the env config's vecsim block names none.
CONTROLLER_URL_ENV = "VECSIM_CONTROLLER_URL"
ACTION_DIM = 7
# Client-side settle actions go out at most this many a call (well under the pods' max_chunk).
SETTLE_CHUNK = 16
# A reset that meets a restarting pod tries again after this long, doubling up to the max.
_HEAL_BACKOFF_S = 0.2
_HEAL_BACKOFF_MAX_S = 2.0


def _opt(cfg: Any, key: str, default: Any = None) -> Any:
    """``cfg.get(key, default)`` for an OmegaConf config or a plain mapping."""
    value = cfg.get(key, default) if hasattr(cfg, "get") else getattr(cfg, key, default)
    return default if value is None else value


def place_slots(
    stage_envs: Sequence[RoutedEnv], held: Mapping[int, RoutedEnv], requests: Mapping[int, str], stage_id: int
) -> dict[int, RoutedEnv]:
    """Return the env each requesting slot runs its next episode on (the module's mapping rule).

    ``held``: the env each slot holds now; ``requests``: slot -> task id of its next episode.
    Slots not requesting keep their envs; a requesting slot keeps its env when its task stays,
    else takes a free env of the task on the pod holding the fewest slots (lowest index first).

    Raises:
        ValueError: the stage has no free env of a requested task (names task, slots, stage).
    """
    taken = {(e.pod, e.env_index) for slot, e in held.items() if slot not in requests}
    placed: dict[int, RoutedEnv] = {}
    for slot, task in requests.items():
        env = held.get(slot)
        if env is not None and env.task_id == task and (env.pod, env.env_index) not in taken:
            placed[slot] = env
            taken.add((env.pod, env.env_index))
    pod_order = {e.pod: i for i, e in reversed(list(enumerate(stage_envs)))}
    for slot, task in requests.items():
        if slot in placed:
            continue
        free = [e for e in stage_envs if e.task_id == task and (e.pod, e.env_index) not in taken]
        if not free:
            of_task = [e for e in stage_envs if e.task_id == task]
            wanted = sorted(s for s, t in requests.items() if t == task)
            raise ValueError(
                f"stage {stage_id} has {len(of_task)} env(s) of task {task!r} and slots {wanted} ask for it "
                f"while {len(of_task) - len([s for s in wanted if s in placed])} are held by other slots: "
                f"give the job's stage as many envs of each task as the RLinf env's slots may draw at once"
            )
        load = Counter(pod for pod, _ in taken)
        env = min(free, key=lambda e: (load[e.pod], pod_order[e.pod], e.env_index))
        placed[slot] = env
        taken.add((env.pod, env.env_index))
    return placed


class VecsimLiberoEnv(LiberoBookkeeping):
    """RLinf's ``LiberoEnv`` (constructor, ``reset``, ``step``, ``chunk_step``, reset-id draws)
    over a vecsim job; see the module docstring for the config and the task mapping rule.

    RLinf's options are read where RLinf reads them (``cfg.reward_coef``, ``use_rel_reward``,
    ``use_step_penalty``, ``ignore_terminations``, ``auto_reset``, ``max_episode_steps``,
    ``use_fixed_reset_state_ids``, ``use_ordered_reset_state_ids``, ``task_id_filter``,
    ``specific_reset_id``, ``is_eval``, ``group_size``, ``seed``, ``reset_gripper_open``). The
    ``vecsim`` block adds: ``controller_url`` | ``pod_urls``, ``stage_id``, ``timeout_s``,
    ``camera_keys`` (default ``"rlinf"``: agentview -> main_images, eye-in-hand -> wrist_images)
    and ``settle_steps``: unset, the job's own settle (``libero: {settle_steps: 15}`` for RLinf's
    15 steps with ``reset_gripper_open: true``); a number N, N settle actions sent by this env
    after each reset, RLinf's own (arm still, gripper -1 if ``reset_gripper_open`` else 0), the
    job's ``settle_steps`` then 0. ``obs_list`` holds the chunk's last observation in its last
    entry and ``None`` before it (the pods render once a chunk).

    A pod that fails a chunk (killed, restarted, partitioned) ends its slots' episodes alone:
    truncated at every action of the chunk, ``infos["lost"]`` (bool ``[num_envs]``, present in
    such a chunk only) marking them, also after an auto-reset. Their next reset waits for the job to heal (the pod back in
    its slot at a new generation), up to ``vecsim.heal_wait_s`` (default 600 s), and goes on there.
    """

    def __init__(self, cfg: Any, num_envs: int, seed_offset: int, total_num_processes: int, worker_info: Any) -> None:
        vcfg = _opt(cfg, "vecsim", {})
        self.seed_offset = seed_offset
        self.cfg = cfg
        self.total_num_processes = total_num_processes
        self.worker_info = worker_info
        self.seed = cfg.seed + seed_offset
        self._is_start = True
        if not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive int, got {num_envs!r}")
        self.num_envs = int(num_envs)
        self.group_size = cfg.group_size
        if self.group_size < 1 or self.num_envs % self.group_size:
            raise ValueError(f"group_size {self.group_size} must divide num_envs {self.num_envs}")
        self.num_group = self.num_envs // self.group_size
        self.use_fixed_reset_state_ids = cfg.use_fixed_reset_state_ids
        self.specific_reset_id = _opt(cfg, "specific_reset_id")
        self.task_id_filter = _opt(cfg, "task_id_filter")
        if self.task_id_filter is not None:
            self.task_id_filter = list(self.task_id_filter)
        self.ignore_terminations = cfg.ignore_terminations
        self.auto_reset = cfg.auto_reset
        self.is_eval = _opt(cfg, "is_eval", False)
        self._generator = np.random.default_rng(seed=self.seed)
        self._generator_ordered = np.random.default_rng(seed=0)
        self.start_idx = 0
        self.suite = str(cfg.task_suite_name).lower()
        if self.suite not in LIBERO_SUITE_TASKS:
            raise ValueError(f"task_suite_name {cfg.task_suite_name!r} is not one of {sorted(LIBERO_SUITE_TASKS)}")
        self._settle_steps = _opt(vcfg, "settle_steps")
        if self._settle_steps is not None and (not isinstance(self._settle_steps, int) or self._settle_steps < 0):
            raise ValueError(f"vecsim.settle_steps must be a non-negative int or unset, got {self._settle_steps!r}")
        self._camera_keys = camera_key_map(_opt(vcfg, "camera_keys", "rlinf"))
        self._heal_wait_s = _opt(vcfg, "heal_wait_s", 600.0)
        if (
            isinstance(self._heal_wait_s, bool)
            or not isinstance(self._heal_wait_s, (int, float))
            or self._heal_wait_s < 0
        ):
            raise ValueError(f"vecsim.heal_wait_s must be a number of seconds >= 0, got {self._heal_wait_s!r}")
        self._closed = False

        self._client = _connect(vcfg)
        try:
            self._setup_job(vcfg)
        except BaseException:
            self._client.close()
            raise

        self._compute_total_num_group_envs()
        self.reset_state_ids_all = self.get_reset_state_ids_all()
        if self.is_eval:
            pool = self.reset_state_ids_all[self.seed_offset]
            self._eval_reset_pool = pool[pool >= 0].copy()
        else:
            self._eval_reset_pool = np.array([], dtype=np.int64)
        self.update_reset_state_ids()
        self.task_ids, self.trial_ids = self._get_task_and_trial_ids_from_reset_state_ids(self.reset_state_ids)
        self.task_descriptions = [self._instruction(t) for t in self.task_ids]

        self.prev_step_reward = np.zeros(self.num_envs)
        self.use_rel_reward = cfg.use_rel_reward
        self.use_step_penalty = getattr(cfg, "use_step_penalty", False)
        self._init_metrics()
        self._elapsed_steps = np.zeros(self.num_envs, dtype=np.int32)
        self.video_cfg = _opt(cfg, "video_cfg")
        self.current_raw_obs = None  # RLinf's name; here {key: array[num_envs, ...]} once reset
        self._held: dict[int, RoutedEnv] = {}
        # Slots whose episode a pod's failure ended; stepped no more until their next reset.
        self._lost = np.zeros(self.num_envs, dtype=bool)

    # -- the job ----------------------------------------------------------------------------------

    def _setup_job(self, vcfg: Any) -> None:
        table = self._client.routing
        self.stage_id = int(_opt(vcfg, "stage_id", self.seed_offset))
        if not 0 <= self.stage_id < len(table.stages):
            raise ValueError(
                f"vecsim.stage_id {self.stage_id} (default: the env's seed_offset) is not a stage of the job, "
                f"which has {len(table.stages)}: give the job one stage per RLinf env process and pipeline stage"
            )
        self._stage_envs = [e for e in routed_envs(table) if e.stage_id == self.stage_id]
        num_states = self._client.num_states
        instructions = self._client.instructions
        # task index -> the job's task id, count and instruction, for this suite's tasks only
        self._job_tasks = {suite_task_index(t): t for t in num_states if suite_of(t) == self.suite}
        if not self._job_tasks:
            raise ValueError(
                f"the job serves no task of task_suite_name {self.suite!r} (its tasks: {sorted(num_states)})"
            )
        counts = {num_states[t] for t in self._job_tasks.values()}
        if len(counts) != 1:
            raise ValueError(f"the job's {self.suite} tasks have different state counts {sorted(counts)}")
        self._states_per_task = counts.pop()
        self._instructions = {i: instructions.get(t, "") for i, t in self._job_tasks.items()}
        if self.task_id_filter is not None:
            missing = [t for t in self.task_id_filter if isinstance(t, (int, np.integer)) and t not in self._job_tasks]
            if missing:
                raise ValueError(f"task_id_filter names tasks {missing} of {self.suite} that the job does not serve")
        self._keys = [f"rlinf{self.seed_offset}-{i}" for i in range(self.num_envs)]

    def _instruction(self, task_index: int) -> str:
        return self._instructions.get(int(task_index), "")

    # -- observations ------------------------------------------------------------------------------

    def _wrap_obs(self) -> dict[str, Any]:
        import torch

        obs: dict[str, Any] = {key: torch.from_numpy(array.copy()) for key, array in self.current_raw_obs.items()}
        obs["task_descriptions"] = self.task_descriptions
        return obs

    def _store_obs(self, rows: Sequence[int], batch_obs: Mapping[str, Any]) -> None:
        images = batch_obs.get("images", {})
        picked = {self._camera_keys[c]: np.asarray(images[c]) for c in self._camera_keys if c in images}
        if "state" not in batch_obs:
            raise ValueError("the job's observations have no 'state' (LIBERO's 8-float state): serve LIBERO tasks")
        picked["states"] = np.asarray(batch_obs["state"], dtype=np.float32)
        if self.current_raw_obs is None:
            self.current_raw_obs = {k: np.zeros((self.num_envs, *v.shape[1:]), v.dtype) for k, v in picked.items()}
        for key, value in picked.items():
            self.current_raw_obs[key][list(rows)] = value

    # -- reset ------------------------------------------------------------------------------------

    def _check_env_idx(self, env_idx: Any) -> np.ndarray:
        idx = np.asarray(env_idx).reshape(-1)
        if idx.size and idx.dtype.kind not in "iu":
            raise ValueError(f"env_idx must be integers, got dtype {idx.dtype}")
        idx = idx.astype(np.int64)
        bad = [int(i) for i in idx if not 0 <= i < self.num_envs]
        if bad:
            raise ValueError(f"env_idx {bad} outside 0..{self.num_envs - 1}")
        if len(set(idx.tolist())) != len(idx):
            raise ValueError(f"env_idx {idx.tolist()} repeats an env")
        return idx

    def _reconfigure(self, reset_state_ids: Any, env_idx: np.ndarray) -> None:
        """Run each slot's next episode on an env of its task, reset to its row (libero_env.py:649-673)."""
        tasks, rows = self._get_task_and_trial_ids_from_reset_state_ids(reset_state_ids)
        if len(tasks) != len(env_idx):
            raise ValueError(f"got {len(tasks)} reset_state_ids for {len(env_idx)} envs (env_idx)")
        missing = sorted({int(t) for t in tasks} - set(self._job_tasks))
        if missing:
            raise ValueError(
                f"reset_state_ids {[int(i) for i, t in zip(np.reshape(reset_state_ids, -1), tasks) if t in missing]} "
                f"are of tasks {[f'{self.suite}/{t}' for t in missing]}, which the job does not serve"
            )
        requests = {int(slot): self._job_tasks[int(t)] for slot, t in zip(env_idx, tasks)}
        row_of = {int(slot): int(row) for slot, row in zip(env_idx, rows)}
        keys = [self._keys[int(slot)] for slot in env_idx]
        deadline = time.monotonic() + self._heal_wait_s
        wait = _HEAL_BACKOFF_S
        while True:
            self._follow_routing()
            self._place(requests, row_of)
            try:
                batch = self._client.reset_stage(self.stage_id, keys).result()
                if self._settle_steps:
                    batch = self._settle(keys)
                break
            except (PodUnavailableError, RoutingChangedError) as exc:
                # A pod of the stage restarted (or is restarting): its envs come back at a new
                # generation, and these resets go there once it serves again.
                if time.monotonic() + wait > deadline:
                    raise
                logger.warning("reset of slots %s waits for the job to heal: %s", sorted(row_of), exc)
                time.sleep(wait)
                wait = min(2 * wait, _HEAL_BACKOFF_MAX_S)
        self._lost[env_idx] = False
        _raise_errors(batch)
        self._store_obs(env_idx, batch.obs)
        self.task_ids[env_idx] = tasks
        self.trial_ids[env_idx] = rows
        descriptions = list(self.task_descriptions)
        for slot, task in zip(env_idx, tasks):
            descriptions[int(slot)] = self._instruction(task)
        self.task_descriptions = descriptions

    def _place(self, requests: Mapping[int, str], row_of: Mapping[int, int]) -> None:
        """Route each requesting slot to an env of its task (``place_slots``), every other slot
        to the env it holds, in the client."""
        placed = place_slots(self._stage_envs, self._held, requests, self.stage_id)
        held = {**self._held, **placed}
        self._check_open()
        live = self._client.routes
        routes = {}
        for slot, env in sorted(held.items()):
            key = self._keys[slot]
            state_id = row_of.get(slot, live[key].state_id if key in live else int(self.trial_ids[slot]))
            routes[key] = TrajRoute(env.pod, env.env_index, env.task_id, self.stage_id, state_id)
        self._client.set_routes(routes)
        self._held = held

    def _follow_routing(self) -> None:
        """Take the stage's envs from the client's routing table (re-read after a 409); slots
        whose env is no longer the job's let it go."""
        envs = [e for e in routed_envs(self._client.routing) if e.stage_id == self.stage_id]
        if envs != self._stage_envs:
            self._stage_envs = envs
            self._held = {slot: env for slot, env in self._held.items() if env in envs}

    def _settle(self, keys: list[str]) -> StageBatch:
        action = np.zeros(ACTION_DIM)
        if self.cfg.reset_gripper_open:
            action[-1] = -1
        left, batch = self._settle_steps, None
        while left:
            k = min(left, SETTLE_CHUNK)
            batch = self._client.step_stage(self.stage_id, {key: np.tile(action, (k, 1)) for key in keys}).result()
            left -= k
        return batch

    def reset(self, env_idx: Any = None, reset_state_ids: Any = None) -> tuple[dict[str, Any], dict[str, Any]]:
        """Reset slots ``env_idx`` (all) to ``reset_state_ids`` (RLinf's draw), as libero_env.py:675-716.

        Raises:
            ValueError: an env index or reset id out of range, ids of a task the job does not
                serve, or no free env of a task on the stage; no env is changed then.
            ClosedEnvironmentError: the env is closed.
        """
        self._check_open()
        env_idx = np.arange(self.num_envs) if env_idx is None else self._check_env_idx(env_idx)
        if reset_state_ids is not None:
            self._get_task_and_trial_ids_from_reset_state_ids(reset_state_ids)
        if self.is_start:
            if self.is_eval:
                self._task_success_stats = {}
                self._eval_seen_trials = set()
                self.start_idx = 0
                pool = self.reset_state_ids_all[self.seed_offset]
                self._eval_reset_pool = pool[pool >= 0].copy()
                self.update_reset_state_ids()
            reset_state_ids = self.reset_state_ids if self.use_fixed_reset_state_ids else None
            self._is_start = False
        if reset_state_ids is None:
            reset_state_ids = self._get_random_reset_state_ids(len(env_idx))
        self._reconfigure(reset_state_ids, env_idx)
        obs = self._wrap_obs()
        self._reset_metrics(env_idx)
        return obs, {}

    # -- steps ------------------------------------------------------------------------------------

    def _check_actions(self, actions: Any, ndim: int) -> np.ndarray:
        if hasattr(actions, "detach"):
            actions = actions.detach().cpu().numpy()
        actions = np.asarray(actions)
        name = "chunk_actions" if ndim == 3 else "actions"
        want = "[num_envs, K, 7]" if ndim == 3 else "[num_envs, 7]"
        if actions.ndim != ndim or actions.shape[0] != self.num_envs or actions.shape[-1] != ACTION_DIM:
            raise ValueError(f"{name} must be {want} with num_envs={self.num_envs}, got shape {actions.shape}")
        if ndim == 3 and actions.shape[1] < 1:
            raise ValueError(f"{name}: a chunk holds at least 1 action (K >= 1), got shape {actions.shape}")
        if actions.dtype.kind not in "fiu" or not np.isfinite(actions).all():
            raise ValueError(f"{name} must be finite numbers, got dtype {actions.dtype}")
        if self.current_raw_obs is None:
            raise ValueError("reset() the env before stepping it")
        return actions.reshape(self.num_envs, -1, ACTION_DIM)

    def _send_chunk(self, chunk: np.ndarray) -> np.ndarray:
        """Step every live slot through ``chunk`` in one call a pod; keep their observations and
        return their per-action success ``[num_envs, K]``. A pod that fails the call (killed,
        restarted: ``PodUnavailableError``, ``RoutingChangedError``) loses its slots' episodes
        alone: they are marked in ``self._lost`` and stepped no more until their next reset; the
        other slots' rows stand."""
        success = np.zeros(chunk.shape[:2], dtype=bool)
        live = [i for i in range(self.num_envs) if not self._lost[i]]
        if not live:
            return success
        try:
            batch = self._client.step_stage(self.stage_id, {self._keys[i]: chunk[i] for i in live}).result()
        except (PodUnavailableError, RoutingChangedError) as exc:
            struck = set(exc.traj_keys)
            logger.warning("slots %s lost their episodes: %s", sorted(self._keys.index(k) for k in struck), exc)
            self._lost[[self._keys.index(key) for key in struck]] = True
            batch = exc.answered
            if batch is None:
                return success
        _raise_errors(batch)
        rows = [self._keys.index(key) for key in batch.traj_keys]
        if rows:
            success[rows] = np.asarray(batch.success, dtype=bool).reshape(len(rows), chunk.shape[1])
            self._store_obs(rows, batch.obs)
        return success

    def _step_chunk(self, chunk: np.ndarray) -> tuple[list, list, list, list, list]:
        """Step every slot through ``chunk`` in one call a pod; RLinf's ``step`` bookkeeping per
        action. A lost slot's episode ends truncated, ``infos["lost"]`` marking it."""
        self._check_open()
        success = self._send_chunk(chunk)
        obs_list, rewards, terms, truncs, infos_list = [], [], [], [], []
        for k in range(chunk.shape[1]):
            # libero_env.py:723-736, the env's `done` being the pod's success of that action
            self._elapsed_steps += 1
            terminations = success[:, k].copy()
            truncations = (self.elapsed_steps >= self.cfg.max_episode_steps) | self._lost
            step_reward = self._calc_step_reward(terminations)
            # RLinf's vector env tags every env's step info with its index (envs/venv/venv.py:808)
            infos = self._record_metrics(step_reward, terminations, {"env_id": list(range(self.num_envs))})
            if self._lost.any():  # only then: a fault-free chunk's infos are RLinf's own, key for key
                infos["lost"] = to_tensor(self._lost.copy())
            if self.ignore_terminations:
                infos["episode"]["success_at_end"] = to_tensor(terminations)
                terminations[:] = False
            obs_list.append(self._wrap_obs() if k == chunk.shape[1] - 1 else None)
            infos_list.append(infos)
            rewards.append(to_tensor(step_reward))
            terms.append(to_tensor(terminations))
            truncs.append(to_tensor(truncations))
        return obs_list, rewards, terms, truncs, infos_list

    def step(self, actions: Any = None, auto_reset: bool = True) -> tuple[Any, Any, Any, Any, dict]:
        """One action per slot (libero_env.py:718-747)."""
        self._check_open()
        chunk = self._check_actions(actions, 2)
        obs_list, rewards, terms, truncs, infos_list = self._step_chunk(chunk)
        obs, infos = obs_list[-1], infos_list[-1]
        dones = terms[-1].numpy() | truncs[-1].numpy()
        if dones.any() and auto_reset and self.auto_reset:
            obs, infos, _ = self._handle_auto_reset(dones, obs, infos)
        return obs, rewards[-1], terms[-1], truncs[-1], infos

    def chunk_step(self, chunk_actions: Any) -> tuple[list, Any, Any, Any, list]:
        """K actions per slot in one call a pod (libero_env.py:749-814 for flags and auto-reset).

        Raises:
            ValueError: ``chunk_actions`` not ``[num_envs, K, 7]`` finite numbers, or no reset yet.
            ClosedEnvironmentError: the env is closed.
        """
        import torch

        self._check_open()
        chunk = self._check_actions(chunk_actions, 3)
        obs_list, rewards, terms, truncs, infos_list = self._step_chunk(chunk)
        chunk_rewards = torch.stack(rewards, dim=1)
        raw_terminations = torch.stack(terms, dim=1)
        raw_truncations = torch.stack(truncs, dim=1)
        past_terminations = raw_terminations.any(dim=1)
        past_truncations = raw_truncations.any(dim=1)
        past_dones = torch.logical_or(past_terminations, past_truncations)
        eval_count_mask = None
        if past_dones.any() and self.auto_reset:
            obs_list[-1], infos_list[-1], eval_count_mask = self._handle_auto_reset(
                past_dones.cpu().numpy(), obs_list[-1], infos_list[-1]
            )
        if self.auto_reset or self.ignore_terminations:
            chunk_terminations = torch.zeros_like(raw_terminations)
            chunk_terminations[:, -1] = past_terminations
            chunk_truncations = torch.zeros_like(raw_truncations)
            chunk_truncations[:, -1] = past_truncations
            if eval_count_mask is not None:
                mask = torch.tensor(eval_count_mask, dtype=torch.bool)
                chunk_terminations[:, -1] &= mask
                chunk_truncations[:, -1] &= mask
        else:
            chunk_terminations = raw_terminations.clone()
            chunk_truncations = raw_truncations.clone()
        return obs_list, chunk_rewards, chunk_terminations, chunk_truncations, infos_list

    # -- life -------------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise ClosedEnvironmentError(f"VecsimLiberoEnv (seed_offset {self.seed_offset}) is closed")

    def close(self) -> None:
        """Close the job's client (the pods keep running); later resets and steps raise."""
        if not self._closed:
            self._closed = True
            self._client.close()


def _raise_errors(batch: StageBatch) -> None:
    if batch.errors:
        raise RuntimeError("; ".join(f"{key}: {kind}: {message}" for key, kind, message in batch.errors))


def _connect(vcfg: Any) -> StageClient:
    """The job's client: ``vcfg.pod_urls``, ``vcfg.controller_url`` or ``$VECSIM_CONTROLLER_URL``."""
    timeout_s = float(_opt(vcfg, "timeout_s", 120.0))
    ended = str(_opt(vcfg, "ended_envs", "step"))
    pod_urls = _opt(vcfg, "pod_urls")
    if pod_urls:
        return StageClient.from_pods(list(pod_urls), timeout_s=timeout_s, ended_envs=ended)
    url = _opt(vcfg, "controller_url") or os.environ.get(CONTROLLER_URL_ENV)
    if not url:
        raise ValueError(
            f"the env config's vecsim block names no job: set vecsim.controller_url or vecsim.pod_urls, "
            f"or ${CONTROLLER_URL_ENV}"
        )
    return StageClient.from_controller(
        str(url), timeout_s=timeout_s, wait_ready_s=float(_opt(vcfg, "wait_ready_s", 0.0)), ended_envs=ended
    )


def register() -> None:
    """Make RLinf's ``get_env_cls("libero", cfg)`` return :class:`VecsimLiberoEnv` when ``cfg`` has
    a ``vecsim`` block (RLinf's own LIBERO env otherwise). Idempotent.

    RLinf has no registry for env classes (``rlinf/envs/__init__.py``: an enum and an if-chain),
    and its workers bind ``get_env_cls`` at import, so this wraps the function in ``rlinf.envs``
    and in the worker modules already imported. Run it in each process that builds envs (under
    Ray, e.g. ``runtime_env={"worker_process_setup_hook": "vecsim.trainers.rlinf.register"}``).
    """
    import sys

    import rlinf.envs

    original = rlinf.envs.get_env_cls
    if getattr(original, "_vecsim_wraps", None) is None:

        def get_env_cls(env_type: str, env_cfg: Any = None) -> Any:
            if env_type == "libero" and env_cfg is not None and _opt(env_cfg, "vecsim") is not None:
                return VecsimLiberoEnv
            return original(env_type, env_cfg)

        get_env_cls._vecsim_wraps = original  # type: ignore[attr-defined]
        rlinf.envs.get_env_cls = get_env_cls
    for name in ("rlinf.workers.env.env_worker", "rlinf.workers.env.async_env_worker"):
        module = sys.modules.get(name)
        if module is not None and hasattr(module, "get_env_cls"):
            module.get_env_cls = rlinf.envs.get_env_cls
