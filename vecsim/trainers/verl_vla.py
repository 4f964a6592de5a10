"""verl-vla's ``BaseEnv`` contract over a vecsim job (verl-vla itself is never imported here).

verl-vla (github.com/verl-project/verl-vla, read at 8a18e3f) runs a chunk ``[B, T, D]`` through
``BaseEnv.step`` (src/verl_vla/envs/base.py:98-114): its serial action executor calls the
one-action hook ``env_step(action, env_ids)`` T times, then ``_finish_execution_slice``
(base.py:282-309) stacks the per-action flags and, with auto-reset, resets the envs that ended
through ``env_reset``. :class:`VecsimLiberoEnv` gives those hooks (``env_init``, ``env_reset``,
``env_step``, ``env_close``, ``env_benchmark_size``) and what its env manager calls
(``get_state``, ``load_state``) over a vecsim job, and takes over ``step`` to send the whole
chunk in one HTTP call per pod wherever nothing may act between two actions (no teleop, no
recorder, the serial executor without interpolation, smoothing or pacing); otherwise
``BaseEnv.step`` runs as it is, one call per action. Use it ahead of ``BaseEnv``::

    from verl_vla.envs.base import BaseEnv
    from vecsim.trainers.verl_vla import VecsimLiberoEnv

    class LiberoEnv(VecsimLiberoEnv, BaseEnv):   # in place of verl_vla.envs.libero.libero_env.LiberoEnv
        pass

and name the job: a ``vecsim`` block (:class:`VecsimSettings`) in verl-vla's simulator config,
through a config class that has one, or ``$VECSIM_CONTROLLER_URL`` / ``$VECSIM_POD_URLS``.
docs/trainers.md says what a user changes and what differs from verl-vla's own LIBERO env.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import types
from dataclasses import dataclass
from typing import Any, List, Optional

import numpy as np

from vecsim.client.conventions import env_indices, suite_of, suite_task_index
from vecsim.client.vla_env import VLAEnv

__all__ = [
    "CONTROLLER_URL_ENV",
    "POD_URLS_ENV",
    "TOKEN_ENV",
    "LiberoEnv",  # noqa: F822 - made on first use, by __getattr__ below
    "VecsimLiberoEnv",
    "VecsimSettings",
    "VecsimSimulatorConfig",  # noqa: F822 - made on first use, by __getattr__ below
    "register",
]

# Where the job is named when verl-vla's simulator config has no ``vecsim`` block.
CONTROLLER_URL_ENV = "VECSIM_CONTROLLER_URL"
POD_URLS_ENV = "VECSIM_POD_URLS"  # comma-separated
TOKEN_ENV = "VECSIM_TOKEN"
# The module whose LiberoEnv verl-vla's env worker builds (env_worker.py:180-181).
VERL_VLA_LIBERO_MODULE = "verl_vla.envs.libero.libero_env"


@dataclass(frozen=True)
class _Executed:
    """One applied action's flags, shaped as verl-vla's ``ExecutedStep`` (action_executor.py:74-78)."""

    feedback: dict[str, np.ndarray]


@dataclass
class VecsimSettings:
    """The ``vecsim`` block of verl-vla's simulator config: which job, and how to use it.

    verl-vla's typed ``SimulatorConfig`` (src/verl_vla/workers/env/config.py:33-50) takes no
    unknown key; a subclass with a field ``vecsim: VecsimSettings`` does, and verl-vla builds it
    from the config's ``_target_`` (config.py:80-84; docs/trainers.md).
    """

    controller_url: Optional[str] = None
    """The job's controller; or ``pod_urls``."""
    pod_urls: Optional[List[str]] = None
    """The job's pods, in job order, without a controller."""
    token: Optional[str] = None
    """The job's bearer token, if it has one."""
    timeout_s: float = 60.0
    """Seconds one request may take."""
    seed: int = 0
    """Seeds the train resets' draws of initial states (with the process id)."""
    whole_chunks: bool = True
    """Send a chunk in one request per pod where :meth:`VecsimLiberoEnv.whole_chunks` allows it."""


def _settings(cfg: Any) -> VecsimSettings:
    """The ``simulator.vecsim`` block of ``cfg``; without one naming a job, the job named by
    ``$VECSIM_CONTROLLER_URL`` or ``$VECSIM_POD_URLS`` (and ``$VECSIM_TOKEN``).

    Raises:
        ValueError: no job named, or both a controller and pods (names the settings).
    """
    block = _get(_get(cfg, "simulator", {}), "vecsim", {})
    settings = VecsimSettings(
        controller_url=_get(block, "controller_url"),
        pod_urls=None if _get(block, "pod_urls") is None else [str(url) for url in _get(block, "pod_urls")],
        token=_get(block, "token"),
        timeout_s=float(_get(block, "timeout_s", 60.0)),
        seed=int(_get(block, "seed", 0)),
        whole_chunks=bool(_get(block, "whole_chunks", True)),
    )
    if settings.controller_url is None and settings.pod_urls is None:
        pods = os.environ.get(POD_URLS_ENV)
        settings.controller_url = os.environ.get(CONTROLLER_URL_ENV) or None
        settings.pod_urls = [url for url in pods.split(",") if url] if pods else None
        settings.token = settings.token or os.environ.get(TOKEN_ENV) or None
        where = f"${CONTROLLER_URL_ENV} and ${POD_URLS_ENV}"
    else:
        where = "simulator.vecsim.controller_url and simulator.vecsim.pod_urls"
    if (settings.controller_url is None) == (settings.pod_urls is None):
        raise ValueError(
            f"{where}: give exactly one (a job is named by simulator.vecsim in a config class with a "
            f"vecsim: VecsimSettings field, or by ${CONTROLLER_URL_ENV} / ${POD_URLS_ENV})"
        )
    return settings


def register() -> None:
    """Make verl-vla's env worker build vecsim's :data:`LiberoEnv` where it imports its own
    (``from verl_vla.envs.libero.libero_env import LiberoEnv``, env_worker.py:180-181). Returns None.

    Call it in every process that runs verl-vla's env worker, before ``init_worker`` (with Ray:
    ``runtime_env={"worker_process_setup_hook": "vecsim.trainers.verl_vla.register"}``). verl-vla's
    own module, which imports LIBERO, is not imported: where it is not loaded yet, a module of
    that name holding vecsim's class stands in for it; where it is, its ``LiberoEnv`` is replaced.
    Idempotent.

    Raises:
        ImportError: verl-vla is not importable.
    """
    module = sys.modules.get(VERL_VLA_LIBERO_MODULE)
    if module is None:
        module = types.ModuleType(VERL_VLA_LIBERO_MODULE, "vecsim's LIBERO env for verl-vla (vecsim.trainers.verl_vla)")
        sys.modules[VERL_VLA_LIBERO_MODULE] = module
    module.LiberoEnv = __getattr__("LiberoEnv")


def __getattr__(name: str) -> Any:
    """``LiberoEnv`` (``VecsimLiberoEnv`` ahead of verl-vla's ``BaseEnv``) and
    ``VecsimSimulatorConfig`` (verl-vla's ``SimulatorConfig`` with a ``vecsim`` field), made from
    verl-vla's own classes on first use: importing this module needs no verl-vla, and both pickle
    by name into verl-vla's spawned simulator processes (env_manager.py:183-205)."""
    if name == "LiberoEnv":
        from verl_vla.envs.base import BaseEnv

        made: type = types.new_class(
            name, (VecsimLiberoEnv, BaseEnv), exec_body=lambda ns: ns.update(__module__=__name__)
        )
        made.__doc__ = (
            "verl-vla's LIBERO env on a vecsim job: :class:`VecsimLiberoEnv` ahead of verl-vla's ``BaseEnv``."
        )
    elif name == "VecsimSimulatorConfig":
        from verl_vla.workers.env.config import SimulatorConfig

        def __post_init__(self: Any) -> None:
            SimulatorConfig.__post_init__(self)
            if not isinstance(self.vecsim, VecsimSettings):
                object.__setattr__(self, "vecsim", _settings_block(self.vecsim))

        made = dataclasses.make_dataclass(
            name,
            [("vecsim", VecsimSettings, dataclasses.field(default_factory=VecsimSettings))],
            bases=(SimulatorConfig,),
            namespace={"__module__": __name__, "__post_init__": __post_init__},
        )
        made.__doc__ = "verl-vla's ``SimulatorConfig`` with the job's :class:`VecsimSettings` as ``vecsim``."
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = made
    return made


def _settings_block(block: Any) -> VecsimSettings:
    """A ``vecsim`` mapping (a dict or OmegaConf node) as :class:`VecsimSettings`.

    Raises:
        ValueError: a key that is not a setting (names it and the settings).
    """
    values = dict(block.items()) if hasattr(block, "items") else dict(block)
    known = [f.name for f in dataclasses.fields(VecsimSettings)]
    unknown = sorted(set(values) - set(known) - {"_target_"})
    if unknown:
        raise ValueError(f"simulator.vecsim: unknown setting(s) {unknown}; the settings are {known}")
    values.pop("_target_", None)
    if values.get("pod_urls") is not None:
        values["pod_urls"] = [str(url) for url in values["pod_urls"]]
    return VecsimSettings(**values)


def _get(cfg: Any, name: str, default: Any = None) -> Any:
    """``cfg.name`` of an OmegaConf node, a dict or any object; ``default`` if absent or None."""
    value = cfg.get(name, default) if hasattr(cfg, "get") else getattr(cfg, name, default)
    return default if value is None else value


class VecsimLiberoEnv:
    """verl-vla's LIBERO env hooks over a vecsim job; put it before ``BaseEnv`` in the bases.

    The constructor is verl-vla's ``LiberoEnv``'s (libero_env.py:260-275), as its env manager
    calls it (src/verl_vla/workers/env/env_manager.py:359-361). With ``P = world_size *
    stage_num`` processes (verl-vla's ``global_process_count``) and ``p = rank * stage_num +
    stage_id`` (its global process id, libero_env.py:272), the train simulator of process ``p``
    takes the job's envs ``[p * num_envs, (p + 1) * num_envs)``; an eval simulator
    (``only_eval``, env_worker.py:200-211) takes ``[(P + p) * num_envs, (P + p + 1) * num_envs)``
    when the env worker's ``modes`` hold ``train`` too, else the train range: train and eval
    never share an env. The job is named by :class:`VecsimSettings` (``cfg.simulator.vecsim``)
    or the environment (:data:`CONTROLLER_URL_ENV`, :data:`POD_URLS_ENV`).
    """

    env_type = "libero"

    def __init__(
        self, cfg: Any, rank: int, world_size: int, stage_id: int = 0, stage_num: int = 1, only_eval: bool = False
    ) -> None:
        self.only_eval = bool(only_eval)
        self.stage_num = int(stage_num)  # verl-vla's name (vecsim's is num_stages), as its LiberoEnv keeps it
        self.global_process_id = int(rank) * self.stage_num + int(stage_id)
        self.global_process_count = int(world_size) * self.stage_num
        super().__init__(cfg, rank, world_size, stage_id=stage_id)  # type: ignore[call-arg]

    # -- BaseEnv's hooks ------------------------------------------------------------------------

    def env_init(self) -> None:
        """Connect to the job and take this process's envs.

        Raises:
            ValueError: no job named, or the job has too few envs for this process (names both).
        """
        self.settings = _settings(self.cfg)
        # verl-vla's LIBERO env steps ended envs on and reads every action's flags (libero_env.py:378-400).
        self.vla = VLAEnv(
            self.settings.controller_url,
            pod_urls=self.settings.pod_urls,
            keys="lerobot",
            camera_keys="verl_vla",
            reward_dtype=np.float32,
            ended_envs="step",
            timeout_s=self.settings.timeout_s,
            token=self.settings.token,
        )
        # Eval simulators come after every train simulator's envs when the worker runs both.
        modes = [str(mode) for mode in _get(self.cfg, "modes", ["train"])]
        first_process = self.global_process_count if self.only_eval and "train" in modes else 0
        role_envs = np.arange(
            first_process * self.num_envs, (first_process + self.global_process_count) * self.num_envs
        )
        start = (first_process + self.global_process_id) * self.num_envs
        if role_envs[-1] >= self.vla.num_envs:
            self.vla.close()
            role = "eval" if self.only_eval else "train"
            raise ValueError(
                f"num_envs: {role} process {self.global_process_id} takes job envs {start}..{start + self.num_envs - 1} "
                f"({role} simulators take {role_envs[0]}..{role_envs[-1]}), but the job has {self.vla.num_envs}"
            )
        self.job_env_ids = np.arange(start, start + self.num_envs)
        tasks = [self.vla.task_ids[i] for i in self.job_env_ids]
        self.task_ids = np.array([suite_task_index(t) for t in tasks], dtype=np.int64)
        self.task_descriptions = [self.vla.instructions[i] for i in self.job_env_ids]
        self._tasks = tasks
        role_tasks = [self.vla.task_ids[i] for i in role_envs]
        self._numbering = {suite: self.vla.state_numbering(suite) for suite in {suite_of(t) for t in role_tasks}}
        self._rng = np.random.default_rng(self.settings.seed + self.global_process_id)
        self.reset_state_ids = np.zeros(self.num_envs, dtype=np.int64)  # suite-global, as verl-vla's
        self.eval_episode_ids = np.full(self.num_envs, -1, dtype=np.int64)
        # The benchmark: every state of the role's tasks once, numbered as verl-vla's own env
        # numbers its benchmark list (tasks in suite order, rows in order; libero_env.py:69-91).
        self._benchmark_first: dict[str, int] = {}
        for task in sorted(set(role_tasks), key=lambda t: (suite_of(t), suite_task_index(t))):
            self._benchmark_first[task] = sum(self.vla.num_states[t] for t in self._benchmark_first)
        self._eval_queues = self._build_eval_queues(role_envs.tolist(), role_tasks)
        self._eval_cursor = np.zeros(self.num_envs, dtype=np.int64)

    def env_benchmark_size(self) -> int:
        """The eval benchmark's episodes: every initial state of the tasks this role's simulators
        (eval, or train where the worker runs no eval) serve, once."""
        return int(sum(self.vla.num_states[task] for task in self._benchmark_first))

    def env_reset(
        self, *, env_ids: Any, reset_eval: bool = False, extra: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        """Reset this process's envs ``env_ids`` to states of their own tasks (train: drawn;
        eval: each env's next state of its eval queue; ``extra["info.reset_state_id"]``: that
        suite-global id) and return verl-vla's reset observation (libero_env.py:320-376).

        Raises:
            ValueError: env ids that are not distinct ints in ``0..num_envs-1``, a reset state id
                that is not one integer, out of range or of another task than its env's (names
                the field); nothing is reset.
        """
        ids = env_indices(env_ids, self.num_envs)
        if extra is not None:
            gids = np.full(ids.size, _reset_state_id(extra), dtype=np.int64)
        elif self.only_eval:
            cursor = np.zeros_like(self._eval_cursor) if reset_eval else self._eval_cursor
            gids = np.array([self._eval_state(i, cursor[i]) for i in ids], dtype=np.int64)
        else:
            gids = np.array([self._draw_state(i) for i in ids], dtype=np.int64)
        obs, _info = self.vla.reset(env_ids=self.job_env_ids[ids], global_state_ids=gids)
        if reset_eval:
            self._eval_cursor[:] = 0
        self.reset_state_ids[ids] = gids
        self.eval_episode_ids[ids] = (
            [self._episode_id(i, g) for i, g in zip(ids, gids)] if self.only_eval or extra is not None else -1
        )
        if self.only_eval and extra is None:
            self._eval_cursor[ids] += 1
        return self._observations(obs, self.job_env_ids[ids], ids)

    def env_step(self, action: Any, *, env_ids: Any) -> dict[str, Any]:
        """Step this process's envs ``env_ids`` one action each (``action`` ``[B, D]``) and return
        verl-vla's step-result dict (libero_env.py:378-400); ended envs are stepped on, as
        verl-vla's own LIBERO env does, their truncation held by the episode limit.

        Raises:
            ValueError: ``action`` not ``[len(env_ids), action dim]``, or bad ``env_ids``.
            ClosedEnvironmentError: after ``env_close``.
        """
        ids = env_indices(env_ids, self.num_envs)
        action = _numpy(action)
        if action.shape != (ids.size, self.vla.action_dim):
            raise ValueError(
                f"action must have shape [{ids.size}, {self.vla.action_dim}] for env_ids {ids.tolist()}, "
                f"got {list(action.shape)}"
            )
        obs, rewards, terminations, truncations, _ = self.vla.chunk_step(
            action[:, None, :], env_ids=self.job_env_ids[ids]
        )
        return self._step_result(obs, ids, rewards[:, 0], terminations[:, 0], truncations[:, 0])

    def env_close(self) -> None:
        """Close the job's connections (idempotent)."""
        if hasattr(self, "vla"):
            self.vla.close()

    # -- the whole chunk in one call per pod ----------------------------------------------------

    def whole_chunks(self) -> bool:
        """Whether ``step`` may send a whole chunk at once: nothing of ``BaseEnv`` acts between two
        actions of a chunk (base.py:519-585 without teleop; no recorder; action_executor.py:143-168
        with neither interpolation nor smoothing; no ``target_step_hz`` pacing of ``mask_step``)."""
        execution = _get(self.cfg, "action_execution", {})
        return (
            not getattr(self, "teleops", None)
            and getattr(self, "recorder", None) is None
            and getattr(self, "target_step_hz", None) is None
            and _get(execution, "mode", "serial") == "serial"
            and not _get(_get(execution, "interpolation", {}), "enable", False)
            and not _get(_get(execution, "serial_smoothing", {}), "enable", False)
            and self.settings.whole_chunks
        )

    def step(self, action: Any, **kwargs: Any) -> Any:
        """``BaseEnv.step`` with the chunk ``[num_envs, T, D]`` sent at once where
        :meth:`whole_chunks` holds: every env applies all T actions in one call per pod, the
        per-action flags are handed to ``BaseEnv._finish_execution_slice`` as its executor hands
        them (auto-reset and the result there); else ``BaseEnv.step`` itself.

        Raises:
            ValueError: ``action`` not ``[num_envs, T >= 1, action dim]``; no env is stepped.
        """
        if not self.whole_chunks():
            return super().step(action, **kwargs)  # type: ignore[misc]
        action = _numpy(action)
        if (
            action.ndim != 3
            or action.shape[0] != self.num_envs
            or action.shape[1] < 1
            or action.shape[2] != self.vla.action_dim
        ):
            raise ValueError(
                f"action must have shape [{self.num_envs}, T >= 1, {self.vla.action_dim}], got {list(action.shape)}"
            )
        every = np.arange(self.num_envs)
        obs, rewards, terminations, truncations, _ = self.vla.chunk_step(action, env_ids=self.job_env_ids)
        # What the executor leaves after T one-action steps (base.py:254-280): the merged result
        # of the last action, the done mask over the chunk, one feedback per action.
        last = self._step_result(obs, every, rewards[:, -1], terminations[:, -1], truncations[:, -1])
        self._update_latest_obs(every, last)  # type: ignore[attr-defined]
        self._execution_merged_step_result = {key: value for key, value in last.items() if key != "extra"}
        self._execution_done |= (terminations | truncations).any(axis=1)
        steps = [
            _Executed(
                {
                    "next.reward": rewards[:, k].copy(),
                    "next.terminated": terminations[:, k].copy(),
                    "next.truncated": truncations[:, k].copy(),
                    "next.success": terminations[:, k].copy(),
                }
            )
            for k in range(action.shape[1])
        ]
        result, _reset_mask = self._finish_execution_slice(steps)  # type: ignore[attr-defined]
        return result

    # -- helpers --------------------------------------------------------------------------------

    def _draw_state(self, i: int) -> int:
        task = self._tasks[i]
        row = int(self._rng.integers(self.vla.num_states[task]))
        return self._numbering[suite_of(task)].global_state_id(suite_task_index(task), row)

    def _build_eval_queues(self, role_envs: list[int], role_tasks: list[str]) -> list[np.ndarray]:
        """Each env's eval states (suite-global ids): the role's envs that run one task share its
        states round robin, so every state of the role's tasks is evaluated once a round."""
        by_task: dict[str, list[int]] = {}
        for job_env, task in zip(role_envs, role_tasks):
            by_task.setdefault(task, []).append(job_env)
        queues = []
        for job_env, task in zip(self.job_env_ids.tolist(), self._tasks):
            sharing = by_task[task]
            rows = np.arange(sharing.index(job_env), self.vla.num_states[task], len(sharing))
            numbering = self._numbering[suite_of(task)]
            queues.append(
                np.array([numbering.global_state_id(suite_task_index(task), r) for r in rows], dtype=np.int64)
            )
        return queues

    def _eval_state(self, i: int, cursor: int) -> int:
        queue = self._eval_queues[i]
        return int(queue[cursor % len(queue)])

    def _episode_id(self, i: int, global_state_id: int) -> int:
        """The benchmark's number of env ``i``'s state ``global_state_id`` (-1 outside it)."""
        task = self._tasks[i]
        if task not in self._benchmark_first:
            return -1
        _, row = self._numbering[suite_of(task)].split_global_state_id(int(global_state_id))
        return self._benchmark_first[task] + row

    # -- what verl-vla's env manager calls --------------------------------------------------------

    def get_state(self) -> bytes:
        """This process's reset bookkeeping as JSON bytes: the train draws' generator and the eval
        cursors. verl-vla's env manager asks for it when it stops the simulator
        (env_manager.py:239-245) and hands it to :meth:`load_state` when it starts it again
        (env_manager.py:363-364); the envs themselves live on the pods and keep their state."""
        return json.dumps({"rng": self._rng.bit_generator.state, "eval_cursor": self._eval_cursor.tolist()}).encode()

    def load_state(self, state_buffer: bytes) -> None:
        """Take up what :meth:`get_state` gave (a restarted simulator continues its draws).

        Raises:
            ValueError: ``state_buffer`` is not what :meth:`get_state` gives for ``num_envs``
                envs (names what is wrong); nothing changes.
        """
        try:
            saved = json.loads(bytes(state_buffer))
            cursor = np.asarray(saved["eval_cursor"], dtype=np.int64)
            rng = np.random.default_rng()
            rng.bit_generator.state = saved["rng"]
        except (TypeError, ValueError, KeyError) as exc:
            raise ValueError(f"state_buffer: not a vecsim verl-vla env state ({exc})") from exc
        if cursor.shape != (self.num_envs,) or (cursor < 0).any():
            raise ValueError(f"state_buffer: eval_cursor must hold {self.num_envs} counts >= 0, got {cursor.tolist()}")
        self._rng, self._eval_cursor = rng, cursor

    def _observations(self, obs: dict[str, Any], rows: np.ndarray, ids: np.ndarray) -> dict[str, Any]:
        """verl-vla's observation block for local envs ``ids`` from VLAEnv's batched ``obs``
        (rows ``rows`` of it): per-env dicts (libero_env.py:285-301), tasks, int ids."""
        keys = [k for k in obs if k.startswith("observation.")]
        return {
            "observation": [{k: _as_verl_vla(k, obs[k][r]) for k in keys} for r in rows],
            "task": [self.task_descriptions[i] for i in ids],
            "task_id": self.task_ids[ids].astype(np.int64, copy=True),
            "eval_episode_id": self.eval_episode_ids[ids].astype(np.int64, copy=True),
        }

    def _step_result(
        self, obs: dict[str, Any], ids: np.ndarray, reward: np.ndarray, terminated: np.ndarray, truncated: np.ndarray
    ) -> dict[str, Any]:
        import torch  # verl-vla's env hands torch tensors (libero_env.py:396-399)

        result = self._observations(obs, np.arange(ids.size), ids)
        result["extra"] = [{"info.reset_state_id": np.asarray([self.reset_state_ids[i]], dtype=np.int64)} for i in ids]
        result["next.reward"] = torch.as_tensor(np.asarray(reward, dtype=np.float32))
        result["next.terminated"] = torch.as_tensor(np.asarray(terminated, dtype=bool))
        result["next.truncated"] = torch.as_tensor(np.asarray(truncated, dtype=bool))
        # LIBERO's termination is its success (libero_env.py:399).
        result["next.success"] = torch.as_tensor(np.asarray(terminated, dtype=bool))
        return result


def _as_verl_vla(key: str, value: Any) -> np.ndarray:
    """An observation entry in the dtype verl-vla's own env builds: ``observation.state`` is
    float64 there (a concatenation of LIBERO's float64 observables, libero_env.py:292-298)."""
    return np.asarray(value, dtype=np.float64) if key == "observation.state" else np.asarray(value)


def _reset_state_id(extra: Any) -> int:
    """The one integer of ``extra["info.reset_state_id"]`` (verl-vla's replay hands ``[id]``).

    Raises:
        ValueError: absent, not exactly one value, not an integer (``1.7``, ``"x"``, NaN, a bool).
    """
    field = "extra['info.reset_state_id']"
    if not hasattr(extra, "get") or extra.get("info.reset_state_id") is None:
        raise ValueError(
            f"{field} must hold one integer state id; extra has {sorted(extra) if hasattr(extra, 'keys') else extra!r}"
        )
    value = extra.get("info.reset_state_id")
    values = np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value).reshape(-1)
    if values.size != 1 or values.dtype.kind not in "iuf":
        raise ValueError(f"{field} must hold one integer state id, got {values.tolist()}")
    number = values[0].item()
    if values.dtype.kind == "f" and not (math.isfinite(number) and float(number).is_integer()):
        raise ValueError(f"{field} must hold one integer state id, got {number!r}")
    return int(number)


def _numpy(value: Any) -> np.ndarray:
    """A copy of an action array or tensor, as float32 (``BaseEnv.step`` copies too, base.py:106).

    Raises:
        ValueError: ``value`` is not an array of finite numbers (names ``action``).
    """
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    try:
        array = np.array(value, dtype=np.float32)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"action must be an array of numbers, got {type(value).__name__}: {exc}") from exc
    if not np.isfinite(array).all():
        raise ValueError("action must be finite, got NaN or infinity")
    return array
