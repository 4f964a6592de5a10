"""HTTPVectorEnv: a gymnasium ``VectorEnv`` over every env of a vecsim job.

Env ``i`` of the vector env is one fixed ``(pod, env_index)`` for the env's whole life, in
stage-major order (stage, then pod, then env index: :func:`vecsim.client.routing.routed_envs`).
Pods never autoreset; this class does gymnasium's three autoreset modes on the client, with
explicit pod resets. The async protocol is an explicit state machine like ``AsyncVectorEnv``'s.
"""

from __future__ import annotations

import concurrent.futures
import logging
import multiprocessing
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import httpx
import numpy as np
from gymnasium.error import AlreadyPendingCallError, ClosedEnvironmentError, NoAsyncCallError
from gymnasium.vector.async_vector_env import AsyncState
from gymnasium.vector.utils import batch_space
from gymnasium import logger as gym_logger
from gymnasium.spaces import Box
from gymnasium.vector.vector_env import AutoresetMode, VectorEnv

from vecsim.client.gym_values import rendered, served_render_mode, wire_actions
from vecsim.client.conventions import env_indices
from vecsim.client.errors import PodUnavailableError, RoutingChangedError, builtin_exception
from vecsim.client.routing import TrajRoute
from vecsim.client.stage import PendingCall, StageBatch, StageClient, check_ended_envs
from vecsim.client.vector_autoreset import Autoresets
from vecsim.client.vector_resets import StateDraws, autoreset_mode_of, env_seeds, reset_mask
from vecsim.client.vector_results import EnvResults, without_errors
from vecsim.client.vector_routes import EnvRoutes
from vecsim.config import JobConfig, RoutingTable, load_job_config

logger = logging.getLogger(__name__)

__all__ = ["HTTPVectorEnv"]

_RESET_OPTIONS = {"reset_mask", "state_ids"}


class WaitTimeoutError(multiprocessing.TimeoutError, TimeoutError):
    """A ``reset_wait``/``step_wait`` not answered within its timeout: gymnasium's
    ``multiprocessing.TimeoutError``, and a builtin ``TimeoutError`` too. The call stays pending."""


# The errors that fail a call for one pod's envs alone, handing over the other pods' rows.
_PARTIAL = (PodUnavailableError, RoutingChangedError)


def _env_mask(env_ids: Any, num_envs: int) -> np.ndarray:
    """The mask of ``env_ids`` (None: every env).

    Raises:
        ValueError: ids that are not distinct ints in ``0..num_envs-1`` (names them).
    """
    mask = np.zeros(num_envs, dtype=bool)
    if env_ids is None:
        mask[:] = True
        return mask
    mask[env_indices(env_ids, num_envs)] = True
    return mask


def _controller_url_of(job_config: JobConfig | str | Path) -> str:
    config = job_config if isinstance(job_config, JobConfig) else load_job_config(job_config)
    return f"http://{config.controller.host}:{config.controller.port}"


class HTTPVectorEnv(VectorEnv):
    """Every env of a vecsim job as one gymnasium vector env.

    Give exactly one of ``controller_url``, ``job_config`` (a :class:`JobConfig` or its YAML
    path; the controller is at its ``controller.host:port``), ``routing`` (a routing table) or
    ``pod_urls`` (standalone pods). ``num_envs`` is set by the job; passing it only checks it.
    ``timeout_s`` bounds every request to a pod; ``transport``, ``max_answer_bytes`` and ``token``
    are as in :class:`StageClient`. With a controller, ``wait_ready_s`` is how long to wait for
    its routing table to be ready (through a controller that is down or restarting meanwhile).

    ``num_envs`` left out (None) takes every env of the job; a number takes the first
    ``num_envs`` envs (stage-major order) and more than the job has is an error.
    ``autoreset_mode`` is an :class:`AutoresetMode` or its name in any spelling (``"same_step"``).

    Observations are the pods' in the job's observation space: a served gymnasium env's own
    (Box, Discrete, Dict, Tuple, ...), the robot suites' ``{"images": {...}, "proprio": ...}``.
    ``info`` holds a gym task's own keys only (and ``state_id`` after fixed-state resets), a
    robot task's ``success`` and ``task_id``, with gymnasium's ``_key`` masks. ``reset(seed=, options=)`` follows
    gymnasium's rule: env ``i`` gets ``seed + i`` (int), ``seed[i]`` (list) or None. A gym task
    resets as the env's own ``reset(seed=..., options=...)`` (every option but ``reset_mask`` and
    ``state_ids`` goes to the envs; autoresets are ``reset()`` with no seed, as locally); a robot
    task resets to a fixed initial state drawn from the env's own generator, which a seed
    reseeds (as a gymnasium env's ``np_random``), and so do its autoresets. ``options``
    ``reset_mask`` (bool array) resets only those envs, ``state_ids`` (one per env; with a mask
    only the masked ones are used) puts envs in fixed initial states, gym tasks too. Options no
    env here reads (a robot task's, or any beside ``state_ids``) are ignored, as gymnasium envs
    ignore options they do not know. :attr:`np_random_seed` is one seed per env.

    An env that raises (in its reset, step or an attribute call) raises its exception here, its
    type rebuilt when it is a builtin one (``ValueError``, ...; any other comes as a
    ``RuntimeError`` naming the type). :meth:`get_attr`, :meth:`call` and :meth:`set_attr` reach
    the envs' attributes as JSON values.

    :meth:`chunk_step` takes a chunk of K actions per env (``[num_envs, K, action dim]``), the
    contract of VLA trainers: each env applies its actions in order and stops at its first
    termination or truncation; rewards and flags come back per action, ``[num_envs, K]`` (0/false
    after an env stopped), the observation after each env's last applied action, and
    ``info["num_steps"]`` the actions each env applied; the pods render once per env per chunk.
    Autoreset works on chunks as on single steps (an env reset in place of its chunk applies none).

    A step or reset answers every env or raises. When pods of the call fail alone
    (``PodUnavailableError``, ``RoutingChangedError``) or envs raise, the other envs did step or
    reset: their rows go into the vector env's observation buffer and autoreset bookkeeping
    before the error is raised, and the error carries ``failed_envs`` (the sorted indices of the
    envs without an answer: those of the failed pods, or those that raised) and ``result`` (what
    the call would have returned, with only the answered envs' rows meaningful and only theirs
    marked in the info's ``_key`` masks). When several envs raise in one call, the lowest env's
    exception is raised, ``failed_envs`` names them all and a note gives the others' messages.
    The failed envs must then be reset (``reset(options={"reset_mask": m})`` with ``m``
    covering them) before the next step; the others go on as they are::

        try:
            obs, reward, terminated, truncated, info = env.step(actions)
        except Exception as exc:
            if getattr(exc, "failed_envs", None) is None:
                raise  # the call failed whole
            obs, reward, terminated, truncated, info = exc.result
            env.reset(options={"reset_mask": np.isin(np.arange(env.num_envs), exc.failed_envs)})

    ``ended_envs`` (as :class:`StageClient`'s) says what stepping an env that terminated or
    truncated and was not reset does when nothing autoresets it (``autoreset_mode`` DISABLED):
    ``"raise"`` (``ResetNeeded``), ``"step"`` (the env is stepped on; a chunk applies all K
    actions, also past an end) or ``"freeze"`` (not stepped: its observation stays, reward 0,
    its flags held, ``num_steps`` 0). ``chunk_step(actions, env_ids=...)`` steps only some envs.
    """

    def __init__(
        self,
        controller_url: str | None = None,
        *,
        job_config: JobConfig | str | Path | None = None,
        routing: RoutingTable | None = None,
        pod_urls: Sequence[str] | None = None,
        num_envs: int | None = None,
        autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP,
        timeout_s: float = 30.0,
        wait_ready_s: float = 60.0,
        transport: httpx.AsyncBaseTransport | None = None,
        max_answer_bytes: int | None = None,
        token: str | None = None,
        ended_envs: str = "raise",
    ) -> None:
        """Connect to the job and read its envs and spaces.

        Raises:
            ValueError: not exactly one source given, a ``num_envs`` that is not the job's, a job
                without envs, an unknown autoreset mode or ``ended_envs``.
            PodUnavailableError, PodRequestError: the controller or a pod did not answer well.
            TimeoutError: the controller's routing table was not ready within ``wait_ready_s``.
        """
        sources = {"controller_url": controller_url, "job_config": job_config, "routing": routing, "pod_urls": pod_urls}
        given = [name for name, value in sources.items() if value is not None]
        if len(given) != 1:
            raise ValueError(f"give exactly one of {', '.join(sources)}; got {given or 'none'}")
        self.autoreset_mode = autoreset_mode_of(autoreset_mode)
        self.ended_envs = check_ended_envs(ended_envs)
        # StageClient's own arguments, the same whatever the source.
        options: dict[str, Any] = {
            "timeout_s": timeout_s,
            "transport": transport,
            "max_answer_bytes": max_answer_bytes,
            "token": token,
            "ended_envs": self.ended_envs,
        }
        if job_config is not None:
            controller_url = _controller_url_of(job_config)
        if controller_url is not None:
            self.client = StageClient.from_controller(controller_url, wait_ready_s=wait_ready_s, **options)
        elif routing is not None:
            self.client = StageClient(routing, **options)
        else:
            self.client = StageClient.from_pods(list(pod_urls or ()), **options)
        try:
            self._setup(num_envs)
        except BaseException:
            self.client.close()
            self.closed = True  # nothing left to close: __del__ must not try again
            raise

    def _setup(self, num_envs: int | None) -> None:
        self._envs = EnvRoutes(self.client, num_envs)
        self.routed_envs = self._envs.routed
        self.num_envs = len(self.routed_envs)
        self.single_observation_space = self.client.observation_space
        self.single_action_space = self.client.served_action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self.metadata = {"autoreset_mode": self.autoreset_mode}
        self.task_ids = [routed.task_id for routed in self.routed_envs]
        # Gym tasks without cameras reset as the envs' own reset (seeds), the others to fixed
        # initial states, as the pods say. A gym task is not looked up here: its module (a
        # user's package) need not exist on this machine.
        kinds = self.client.reset_kinds
        self._native = all(kinds.get(t) == "seed" for t in self.task_ids)
        known = self.client.num_states
        missing = sorted(set(self.task_ids) - set(known))
        if missing:
            raise ValueError(f"the pods' /v1/info names no number of initial states for task(s) {missing}")
        self._draws = self._state_draws(self.task_ids, {t: known[t] for t in set(self.task_ids)})
        self._keys = self._envs.keys
        self._results = EnvResults(
            self.single_observation_space, self._keys, self.task_ids, self._native, self.autoreset_mode
        )
        self._autoresets = Autoresets(self.client, self._keys, self._draws, self._native, self.autoreset_mode)
        self._state = AsyncState.DEFAULT
        self._pending: PendingCall[Any] | None = None
        self._pending_mask: np.ndarray | None = None
        self._pending_fixed = True  # the reset in flight puts envs in fixed initial states
        self.render_mode = served_render_mode(self) if self._native else None

    # -- reset ----------------------------------------------------------------------------------

    def reset(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Reset all envs (or ``options["reset_mask"]``'s) and return ``(obs, info)``.

        Raises:
            as :meth:`reset_async` and :meth:`reset_wait`.
        """
        self.reset_async(seed=seed, options=options)
        return self.reset_wait()

    def reset_async(
        self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> None:
        """Send the reset and return at once; :meth:`reset_wait` takes the answer.

        Raises:
            ClosedEnvironmentError: the env is closed.
            AlreadyPendingCallError: a reset or step is still waiting to be taken.
            TypeError, ValueError: a bad seed, ``reset_mask`` or ``state_ids`` (named).
        """
        self._assert_open()
        seeds = env_seeds(seed, self.num_envs)
        if self._state != AsyncState.DEFAULT:
            raise AlreadyPendingCallError(
                f"Calling `reset_async` while waiting for a pending call to `{self._state.value}` to complete",
                str(self._state.value),
            )
        options = dict(options or {})
        env_options = {k: v for k, v in options.items() if k not in _RESET_OPTIONS}
        resets_itself = self._resets_itself(options)
        if env_options and not resets_itself:
            # As a gymnasium env ignores options it does not know (LeRobot's rollout passes its
            # own), those that no env here reads are dropped; vecsim's own are still checked.
            logger.debug("reset options %s go to no env here; ignored", sorted(env_options))
            env_options = {}
        mask = reset_mask(options.get("reset_mask"), self.num_envs)
        indices = np.flatnonzero(mask)
        # One generator per env, as each of gymnasium's envs has its own: a seed reseeds it.
        reseeded = self._draws.reseeded(seeds, indices)
        if resets_itself:
            self._envs.place_lost(mask)
            self._draws.take(reseeded)
            self._pending = self.client.call(seeds={self._keys[i]: seeds[i] for i in indices}, options=env_options)
            self._pending_fixed = False
        else:
            state_ids = self._draws.state_ids(reseeded, options.get("state_ids"), mask)
            self._envs.place_lost(mask)
            self._draws.take(reseeded)
            self._pending = self.client.call(reset={self._keys[i]: int(state_ids[i]) for i in indices})
            self._pending_fixed = True
        self._pending_mask = mask
        self._state = AsyncState.WAITING_RESET

    def _state_draws(self, task_ids: list[str], num_states: dict[str, int]) -> StateDraws:
        """How the envs' state ids are drawn for resets and autoresets that name none (a subclass
        may count them as its trainer's own env does)."""
        return StateDraws(task_ids, num_states)

    def _resets_itself(self, options: dict[str, Any]) -> bool:
        """Whether a reset with ``options`` is each env's own reset (seeds and the env's options go
        to the env), not one to fixed initial states (``state_ids``, drawn or given)."""
        return self._native and options.get("state_ids") is None

    def reset_wait(self, timeout: float | None = None) -> tuple[Any, dict[str, Any]]:
        """Wait for the reset sent by :meth:`reset_async`; return ``(obs, info)``.

        Raises:
            ClosedEnvironmentError: the env is closed.
            NoAsyncCallError: no reset is pending.
            TimeoutError: not answered within ``timeout`` seconds (the reset stays pending).
            PodUnavailableError, PodRequestError, RoutingChangedError: from the client. The first
                and last carry ``failed_envs`` and ``result`` (see the class docstring); the
                envs that answered are reset.
            the exception an env raised in its reset (see the class docstring), carrying
                ``failed_envs`` and ``result`` too; the other envs are reset.
        """
        self._assert_open()
        if self._state != AsyncState.WAITING_RESET:
            raise NoAsyncCallError(
                "Calling `reset_wait` without any prior call to `reset_async`.", AsyncState.WAITING_RESET.value
            )
        mask = self._pending_mask
        try:
            batch, _ = self._take(timeout)
        except _PARTIAL as error:
            answered = error.answered[0] if error.answered is not None else None
            raised = answered.errors if answered is not None else []
            result, done = self._results.take_reset(
                None if answered is None else without_errors(answered), self._pending_fixed
            )
            self._results.fail(error, mask & ~done, result, raised)
            raise
        with self._results.failing_if_interrupted(mask):
            result = self._results.take_reset(without_errors(batch), self._pending_fixed)[0]
        self._results.raise_env_errors(batch.errors, result)
        return result

    @property
    def np_random_seed(self) -> tuple[int, ...]:
        """Each env's seed, as gymnasium's vector envs give it (one per env): a gym task's own
        ``np_random_seed``; for a robot task the seed of the generator its state ids are drawn
        from (``seed + i`` after ``reset(seed=seed)``; a seed of fresh entropy before any)."""
        if self._native:
            return self.get_attr("np_random_seed")
        return tuple(int(self._draws.rng(i)[1]) for i in range(self.num_envs))

    # -- step -----------------------------------------------------------------------------------

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every env with its row of ``actions``; autoreset per :attr:`autoreset_mode`.

        Raises:
            as :meth:`step_async` and :meth:`step_wait`.
        """
        self.step_async(actions)
        return self.step_wait()

    def chunk_step(
        self, actions: Any, env_ids: Sequence[int] | np.ndarray | None = None
    ) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every env with its chunk ``actions[i]`` (``[num_envs, K, action dim]``), or only
        the envs ``env_ids`` (``actions`` ``[len(env_ids), K, action dim]``, row j for
        ``env_ids[j]``): the others are not touched, and pods with none of them get no request.

        Returns:
            ``(obs, reward float64[num_envs, K], terminated bool[num_envs, K], truncated
            bool[num_envs, K], info)``: entries after an env stopped are 0/false; ``obs`` is after
            each env's last applied action; ``info`` adds ``num_steps`` (actions applied, with
            its ``_num_steps`` mask) to ``step``'s keys, ``success`` being after the last action.
            Arrays stay ``[num_envs, ...]``; envs left out of ``env_ids`` answer 0/false and are
            unmarked in the info's masks.

        Raises:
            as :meth:`step_async` (for chunks) and :meth:`step_wait`; ``ValueError`` for
            ``env_ids`` out of range or repeated.
        """
        self.chunk_step_async(actions, env_ids)
        return self.step_wait()

    def chunk_step_async(self, actions: Any, env_ids: Sequence[int] | np.ndarray | None = None) -> None:
        """Send a chunk step (``[num_envs, K, action dim]``, or ``[len(env_ids), K, action dim]``
        for the envs ``env_ids``) and return at once; :meth:`step_wait` takes the answer, shaped
        as :meth:`chunk_step` says.

        Raises:
            as :meth:`step_async`; ``ValueError`` for a chunk of the wrong shape or bad ``env_ids``.
        """
        if not isinstance(self.single_action_space, Box):
            raise TypeError(
                f"chunk_step takes chunks of Box actions; this job's action space is {self.single_action_space}"
            )
        envs = _env_mask(env_ids, self.num_envs)
        actions = np.asarray(actions, dtype=self.single_action_space.dtype)
        n = int(envs.sum())
        expected = (n, "K", *self.single_action_space.shape)
        if actions.ndim != len(expected) or actions.shape[0] != n or actions.shape[2:] != expected[2:]:
            raise ValueError(f"chunk actions must have shape {list(expected)}, got {list(actions.shape)}")
        if env_ids is not None:  # one row per env, rows of envs left out unused
            full = np.zeros((self.num_envs, *actions.shape[1:]), dtype=actions.dtype)
            full[np.asarray(env_ids, dtype=np.int64).reshape(-1)] = actions
            actions = full
        self._send_step(actions, envs)

    def step_async(self, actions: Any) -> None:
        """Send the step and return at once; :meth:`step_wait` takes the answer.

        NEXT_STEP resets (instead of stepping) the envs that ended on the previous step;
        SAME_STEP steps all and resets those that end, in the same call; DISABLED steps all and
        refuses envs that ended and were not reset with ``reset(options={"reset_mask": ...})``.

        Raises:
            ClosedEnvironmentError: the env is closed.
            AlreadyPendingCallError: a reset or step is still waiting to be taken.
            ResetNeeded: an env was never reset, got no answer in its last call, or (DISABLED)
                ended and was not reset.
            ValueError: ``actions`` of the wrong shape or not finite (names the env).
            TypeError: a scalar in place of a batch of actions.
        """
        self._send_step(wire_actions(self.single_action_space, self.action_space, actions, self.num_envs))

    def _send_step(self, actions: np.ndarray, envs: np.ndarray | None = None) -> None:
        """Send a step of the envs ``envs`` marks (None: all); ``actions`` has a row per env (one
        action or a chunk each: the call's answer says which)."""
        envs = np.ones(self.num_envs, dtype=bool) if envs is None else envs
        self._assert_open()
        if self._state != AsyncState.DEFAULT:
            raise AlreadyPendingCallError(
                f"Calling `step_async` while waiting for a pending call to `{self._state.value}` to complete.",
                str(self._state.value),
            )
        ended = self._results.steppable(
            envs, refuse_ended=self.autoreset_mode == AutoresetMode.DISABLED and self.ended_envs == "raise"
        )
        self._pending = self._autoresets.step(actions, envs, ended)
        self._pending_mask = envs
        self._state = AsyncState.WAITING_STEP

    def step_wait(self, timeout: float | None = None) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Wait for the step sent by :meth:`step_async`; return ``(obs, reward, terminated, truncated, info)``.

        Raises:
            ClosedEnvironmentError: the env is closed.
            NoAsyncCallError: no step is pending.
            TimeoutError: not answered within ``timeout`` seconds (the step stays pending).
            PodUnavailableError, PodRequestError, RoutingChangedError: from the client. The first
                and last carry ``failed_envs`` and ``result`` (see the class docstring); the
                envs that answered have stepped (or autoreset) and go on from there.
            the exception an env raised in its step or autoreset (see the class docstring),
                carrying ``failed_envs`` and ``result`` too; the other envs go on.
        """
        self._assert_open()
        if self._state != AsyncState.WAITING_STEP:
            raise NoAsyncCallError(
                "Calling `step_wait` without any prior call to `step_async`.", AsyncState.WAITING_STEP.value
            )
        sent = self._pending_mask
        try:
            reset_batch, step_batch = self._take(timeout)
        except _PARTIAL as error:
            if error.answered is None:
                result, done, raised = None, np.zeros(self.num_envs, dtype=bool), []
            else:
                raised = error.answered[1].errors + error.answered[0].errors
                result, done = self._results.take_step(*map(without_errors, error.answered))
            self._results.fail(error, sent & ~done, result, raised)
            raise
        with self._results.failing_if_interrupted(sent):
            result = self._results.take_step(without_errors(reset_batch), without_errors(step_batch))[0]
        self._results.raise_env_errors(step_batch.errors + reset_batch.errors, result)
        return result

    # -- shared ---------------------------------------------------------------------------------

    def _take(self, timeout: float | None) -> tuple[StageBatch, StageBatch]:
        try:
            answer = self._pending.result(timeout)  # type: ignore[union-attr]
        except TimeoutError:
            raise WaitTimeoutError(
                f"The call to `{self._state.value}_wait` has timed out after {timeout} second(s); it is still pending"
            ) from None
        except BaseException as exc:
            if not isinstance(exc, Exception) or isinstance(exc, concurrent.futures.CancelledError):
                # Interrupted (Ctrl-C; the call is cancelled): whether its envs reset or stepped
                # is unknown, so they must be reset before the next step.
                results = self._results
                results.failed |= self._pending_mask
                results.autoreset[results.failed] = False
            self._state, self._pending = AsyncState.DEFAULT, None
            raise
        self._state, self._pending = AsyncState.DEFAULT, None
        return answer

    def _assert_open(self) -> None:
        if self.closed:
            raise ClosedEnvironmentError(f"Trying to operate on `{type(self).__name__}`, after a call to `close()`.")

    # -- attributes -----------------------------------------------------------------------------

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Return attribute ``name`` of every env, as JSON values (a gym env's through its wrappers).

        A robot task's ``np_random_seed`` is :attr:`np_random_seed`'s; a spec comes as a dict.

        Raises:
            ClosedEnvironmentError, AlreadyPendingCallError: as gymnasium's vector envs.
            PodRequestError: the pods refused the name (private, or one vecsim keeps).
            the env's own exception (builtin types by name), or ``ValueError`` for an attribute
            that JSON cannot hold.
        """
        if name == "np_random_seed" and not self._native:
            self._assert_open()
            return self.np_random_seed
        return tuple(self._attr("get_attr", name, None))

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Call method ``name(*args, **kwargs)`` of every env (or read it, if it is not callable);
        return the JSON results. Arguments must be JSON values.

        Raises:
            as :meth:`get_attr`.
        """
        return tuple(self._attr("call", name, (list(args), kwargs)))

    def set_attr(self, name: str, values: list[Any] | tuple[Any, ...] | object) -> None:
        """Set attribute ``name`` of every env: ``values[i]`` for env i (a list or tuple), or one
        value for all. Only JSON-valued attributes may be set (an array keeps its dtype and shape).

        Raises:
            ValueError: a list of the wrong length.
            as :meth:`get_attr`.
        """
        if not isinstance(values, (list, tuple)):
            values = [values for _ in range(self.num_envs)]
        if len(values) != self.num_envs:
            raise ValueError(
                "Values must be a list or tuple with length equal to the number of environments. "
                f"Got `{len(values)}` values for {self.num_envs} environments."
            )
        self._attr("set_attr", name, list(values))

    def _attr(self, op: str, name: str, payload: Any) -> list[Any]:
        self._assert_open()
        if self._state != AsyncState.DEFAULT:
            raise AlreadyPendingCallError(
                f"Calling `{op}` while waiting for a pending call to `{self._state.value}` to complete.",
                str(self._state.value),
            )
        results, errors = self.client.env_attr(op, self._keys, name, payload).result()
        if errors:
            key, type_name, message = errors[0]
            raise builtin_exception(type_name, message)
        return results

    def render(self) -> tuple[Any, ...] | None:
        """Each gym env's own ``render()`` (gymnasium's ``AsyncVectorEnv.render``), an
        ``rgb_array`` frame as uint8. Raises NotImplementedError for robot tasks (cameras instead)."""
        if not self._native:
            return super().render()
        return rendered(self.render_mode, self.call("render"))

    def close_extras(self, **kwargs: Any) -> None:
        """Close the client: pod connections and its event loop thread (a call still pending is
        dropped, with gymnasium's warning)."""
        if self._state != AsyncState.DEFAULT:
            gym_logger.warn(f"Calling `close` while waiting for a pending call to `{self._state.value}` to complete.")
        self._state, self._pending = AsyncState.DEFAULT, None
        self.client.close()

    def __del__(self) -> None:
        if not getattr(self, "closed", True) and hasattr(self, "client"):
            self.close()

    @property
    def routes(self) -> Mapping[int, TrajRoute]:
        """Env index -> its fixed ``(pod, env_index, task_id, stage_id, state_id)``; an env whose
        pod's envs went away with a routing change is left out until it is reset."""
        return self._envs.by_env()
