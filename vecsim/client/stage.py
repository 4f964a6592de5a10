"""StageClient: trajectories routed to pods, stepped one pipeline stage at a time.

Usage, top to bottom::

    client = StageClient.from_controller("http://127.0.0.1:8000")
    routes = client.reset_trajectories([("tiny/lift", 0), ("tiny/stack", 3), ...])
    first = client.reset_stage(0).result()          # or: await client.reset_stage(0)
    pending = client.step_stage(0, {key: action for key, action in ...})
    ...                                             # work on another stage meanwhile
    batch = pending.result()
    pending = client.step_stage(0, {key: chunk for key, chunk in ...})   # chunks [K, action dim]
    pending = client.step_stage(0, client.step_actions(keys, chunks))   # one array [n, K, action dim]

Every call returns a :class:`PendingCall` at once (awaitable, or ``.result()`` from sync code);
the HTTP runs on the client's own event loop thread, all pods of a call concurrently, over one
keep-alive connection pool per pod, and the answers land in batch arrays allocated before the
requests go out. Each stage is a small state machine like gymnasium's ``AsyncVectorEnv``: idle, or
waiting on one call; a second call on a waiting stage raises ``AlreadyPendingCallError``. A
:meth:`StageClient.pod_call` holds one pod of its stage only, so pods of a stage can each wait on
a call of their own (no lockstep over a stage's pods).

This class is the facade over the parts, each its own module: the route book
(:mod:`~vecsim.client.routebook`, pure), the stages' states (:mod:`~vecsim.client.stagestate`,
pure), what the pods said of the job (:mod:`~vecsim.client.jobinfo`), one call carried out
(:mod:`~vecsim.client.calls`: whether its actions are one or a chunk each is said there once,
:func:`~vecsim.client.calls.step_actions`), the routing re-read (:mod:`~vecsim.client.refresh`)
and the pod connections on the loop thread (:mod:`~vecsim.client.pods`, whose ``PodSet`` is
the one way a call reaches a pod). Its base, :class:`~vecsim.client.jobclient.JobClient`, holds
the connection to the job (loop thread, transport, pods, re-read, spaces); this class adds the
trajectories and the stages.

A pod that fails a call (no answer in time, refused connection, 503, envs moved by the routing)
fails it for its own trajectories only: the error names them and carries the rows of the pods
that did answer (``error.answered``), whose envs have advanced and must not be lost.
"""

from __future__ import annotations

import atexit
import itertools
import weakref
from collections.abc import Mapping, Sequence
from typing import Any

import httpx

from vecsim.client.calls import (
    PendingCall,
    StageBatch,
    StepActions,
    check_actions,
    check_attr,
    check_call,
    completed,
    empty_batch,
    run_attr,
    run_call,
    step_actions,
)
from vecsim.client.jobclient import JobClient
from vecsim.client.refresh import fetch_routing, read_pod_info
from vecsim.client.routing import TrajRoute, routing_from_pod_infos
from vecsim.client.stagestate import StageState, StageStates
from vecsim.config import RoutingTable

__all__ = ["ENDED_ENVS", "PendingCall", "StageBatch", "StageClient", "StepActions", "check_ended_envs", "fetch_routing"]

# What stepping a trajectory whose env terminated or truncated (and was not reset since) does:
# "raise" refuses it with ResetNeeded before anything is sent; "step" steps the env on, and a
# chunk applies all its K actions, also past an end (as RLinf's and LIBERO's own envs are
# stepped, the trainer masking afterwards); "freeze" sends nothing for it and answers its
# observation at the end, reward 0, its termination and truncation held at every action,
# num_steps 0. Under "raise" and "freeze" a chunk stops each env at its first end.
ENDED_ENVS = ("raise", "step", "freeze")


def check_ended_envs(value: str) -> str:
    """Return ``value`` if it is one of :data:`ENDED_ENVS`.

    Raises:
        ValueError: any other value (names the valid ones).
    """
    if value not in ENDED_ENVS:
        raise ValueError(f"ended_envs must be one of {list(ENDED_ENVS)}, got {value!r}")
    return value


def _keys_of(step: Mapping[str, Any] | StepActions) -> list[str]:
    return step.traj_keys if isinstance(step, StepActions) else list(step)


# Clients not closed yet: closed at interpreter exit while their loop threads still run, so
# that a script ending in an exception or Ctrl-C exits quietly, its connections closed.
_open_clients: weakref.WeakSet[StageClient] = weakref.WeakSet()


@atexit.register
def _close_open_clients() -> None:
    for client in list(_open_clients):
        client.close()


class _Held:
    """What holds a call's stages in :class:`StageStates`: the call, whose handle comes after."""

    __slots__ = ("pending",)

    def __init__(self) -> None:
        self.pending: PendingCall[Any] | None = None


class StageClient(JobClient):
    """Routes trajectories to pod envs and steps them stage by stage (see the module docstring).

    ``routing`` is the job's routing table; ``controller_url``, when given, is where the table is
    re-read after a pod answers 409 (stale generation) and before each new batch is placed.
    ``timeout_s`` bounds every HTTP request as a whole, answer included: a pod that does not
    answer within it raises :class:`PodUnavailableError`. ``transport`` is how bytes reach the
    pods (and the controller, for those re-reads): a :class:`vecsim.transport.Transport`, or
    an in-process httpx transport (``httpx.ASGITransport(app)`` runs a pod in-process), which
    the client wraps as :func:`vecsim.transport.as_transport` does; left out,
    ``vecsim.transport.make_transport()``. The client closes it. ``max_answer_bytes``
    caps one pod's answer; left out, each pod's cap follows from the job's observation space
    and the pod's env count (twice what its envs can produce, plus a MiB). ``token`` is the
    job's shared token, sent with every reset and step; left out, ``VECSIM_TOKEN`` is used
    (none: the pods must run without one).

    ``ended_envs`` (one of :data:`ENDED_ENVS`, which says what each does) is what a step of a
    trajectory whose env terminated or truncated (and was not reset since) does.
    """

    def __init__(
        self,
        routing: RoutingTable,
        *,
        controller_url: str | None = None,
        timeout_s: float = 30.0,
        transport: httpx.AsyncBaseTransport | None = None,
        max_answer_bytes: int | None = None,
        token: str | None = None,
        ended_envs: str = "raise",
    ) -> None:
        self.ended_envs = check_ended_envs(ended_envs)
        super().__init__(
            routing,
            controller_url=controller_url,
            timeout_s=timeout_s,
            transport=transport,
            max_answer_bytes=max_answer_bytes,
            token=token,
        )
        self._states = StageStates()
        self._batches = itertools.count()
        _open_clients.add(self)

    @classmethod
    def from_controller(
        cls,
        controller_url: str,
        *,
        timeout_s: float = 30.0,
        wait_ready_s: float = 0.0,
        transport: httpx.AsyncBaseTransport | None = None,
        max_answer_bytes: int | None = None,
        token: str | None = None,
        ended_envs: str = "raise",
    ) -> StageClient:
        """Return a client over the controller's routing table (see :func:`fetch_routing`, which
        waits up to ``wait_ready_s`` for a controller that is down, restarting or not planned).

        Raises:
            PodUnavailableError, PodRequestError, TimeoutError: as :func:`fetch_routing`.
        """
        table = fetch_routing(controller_url, timeout_s=timeout_s, wait_ready_s=wait_ready_s)
        return cls(
            table,
            controller_url=controller_url,
            timeout_s=timeout_s,
            transport=transport,
            max_answer_bytes=max_answer_bytes,
            token=token,
            ended_envs=ended_envs,
        )

    @classmethod
    def from_pods(
        cls,
        urls: Sequence[str],
        *,
        timeout_s: float = 30.0,
        transport: httpx.AsyncBaseTransport | None = None,
        max_answer_bytes: int | None = None,
        token: str | None = None,
        ended_envs: str = "raise",
    ) -> StageClient:
        """Return a client over standalone pods (no controller), reading each pod's ``/v1/info``.

        Raises:
            PodUnavailableError: a pod did not answer, or answered 503.
            PodRequestError: a pod refused, or its answer is not JSON.
            ValueError: the pods do not make a routing table (names the problem).
        """

        infos = [read_pod_info(u, timeout_s) for u in urls]
        client = cls(
            routing_from_pod_infos(infos),
            timeout_s=timeout_s,
            transport=transport,
            max_answer_bytes=max_answer_bytes,
            token=token,
            ended_envs=ended_envs,
        )
        try:
            client._adopt_info({i["pod"]: i for _, i in infos if i.get("num_envs")})
        except BaseException:
            client.close()
            raise
        return client

    # -- what the client routes over ------------------------------------------------------------

    @property
    def num_stages(self) -> int:
        return self._book.num_stages

    @property
    def routes(self) -> dict[str, TrajRoute]:
        """A copy of the live trajectories' routes, in placement order."""
        return self._book.routes()

    def stage_traj_keys(self, stage_id: int) -> list[str]:
        """Return the live traj_keys of a stage, in placement order.

        Raises:
            ValueError: no such stage.
        """
        self._check_stage(stage_id)
        return self._book.stage_keys(stage_id)

    # -- placing trajectories -------------------------------------------------------------------

    def reset_trajectories(
        self,
        requests: Sequence[tuple[str, int]],
        traj_keys: Sequence[str] | None = None,
        stages: Sequence[int] | None = None,
    ) -> dict[str, TrajRoute]:
        """Place a new batch of trajectories: request ``i`` on stage ``stage_of(i, S)`` (or on
        ``stages[i]``: a part of a larger batch placed now, keeping the whole batch's stages).

        Replaces the live trajectories (no HTTP here; :meth:`reset_stage` puts the envs in their
        state ids). ``traj_keys`` defaults to fresh keys ``"<batch>-<i>"``. Returns
        ``{traj_key: TrajRoute}`` in request order. An empty batch is a no-op returning ``{}``.

        Raises:
            CapacityError: a stage lacks envs for a task (names task, stage and requests).
            ValueError: a malformed request or traj_keys.
            AlreadyPendingCallError: a call is still in flight.
            ClosedEnvironmentError: the client is closed.
        """
        self._check_open()
        # Before a new batch: the controller's table if it has moved on and is ready, so that a
        # reassignment finished before the batch costs the batch nothing (not while calls run).
        if not self._states.busy():
            self._refresher.before_batch(self._loop, self._pods)
        keys = list(traj_keys) if traj_keys is not None else self.new_traj_keys(len(requests))
        routes = self._book.place(requests, keys, stages)
        self._states.while_idle("placing a new batch", lambda: self._book.replace(routes))
        return dict(routes)

    def new_traj_keys(self, n: int) -> list[str]:
        """Fresh traj_keys ``"<batch>-<i>"`` for a batch of ``n`` requests (what
        :meth:`reset_trajectories` uses when given none)."""
        batch = next(self._batches)
        return [f"{batch}-{i}" for i in range(n)]

    def place_trajectory(
        self, traj_key: str, request: tuple[str, int], stage_id: int, pods: Sequence[str] | None = None
    ) -> TrajRoute | None:
        """Add one live trajectory to the batch (no HTTP; a reset puts its env in its state id):
        request ``(task_id, state_id)`` on the lowest env of its task that no live trajectory
        holds, on the first of ``pods`` (default: the stage's pods in table order) that has one.
        Returns its route, or None (nothing placed) when no such env is free. For refilling the
        envs of ended trajectories (see :meth:`retire_trajectories`) while other calls run.

        Raises:
            ValueError: a malformed request, no such stage, a pod not of the stage, or a
                traj_key live already.
            ClosedEnvironmentError: the client is closed.
        """
        self._check_stage(stage_id)
        return self._book.admit(traj_key, request, stage_id, pods)

    def retire_trajectories(self, traj_keys: Sequence[str]) -> None:
        """Drop live trajectories (ended ones): their envs become free for
        :meth:`place_trajectory`. The rest of the batch and the calls in flight are untouched.

        Raises:
            ValueError: a key that is not live.
            AlreadyPendingCallError: a key's pod (or stage) waits on a call.
            ClosedEnvironmentError: the client is closed.
        """
        self._check_open()
        traj_keys = list(dict.fromkeys(traj_keys))
        routes = self._book.live(traj_keys)
        self._states.check_idle({(routes[k].stage_id, routes[k].pod) for k in traj_keys}, "retiring their trajectories")
        self._book.retire(traj_keys)

    def set_routes(self, routes: Mapping[str, TrajRoute]) -> None:
        """Make ``routes`` the live trajectories, as given (for callers that place envs themselves).

        Raises:
            ValueError: a route that does not fit the routing table, or two sharing an env.
            AlreadyPendingCallError, ClosedEnvironmentError: as :meth:`reset_trajectories`.
        """
        self._check_open()
        self._book.check_routes(routes)
        self._states.while_idle("placing a new batch", lambda: self._book.replace(routes))

    @property
    def ended_traj_keys(self) -> list[str]:
        """The trajectories whose env terminated or truncated and was not reset since."""
        return sorted(self._book.ended())

    # -- calls ----------------------------------------------------------------------------------

    def reset_stage(self, stage_id: int, traj_keys: Sequence[str] | None = None) -> PendingCall[StageBatch]:
        """Reset a stage's trajectories (all, or ``traj_keys``) to their state ids; don't wait.

        A stage without trajectories (or an empty ``traj_keys``) is a no-op: an empty batch.

        Raises:
            ValueError: no such stage, or a key not live on it.
            RoutingChangedError: a key whose env went away when the routing changed.
            AlreadyPendingCallError: the stage already waits on a call.
            ClosedEnvironmentError: the client is closed.

        The result raises what the call met: ``PodUnavailableError`` (no answer within
        ``timeout_s``), ``PodRequestError`` (refused), ``StaleGenerationError`` (409 after a
        re-read, or no controller to re-read from), ``RoutingChangedError`` (the re-read routing
        moved these trajectories' envs). A ``PodUnavailableError`` or ``RoutingChangedError``
        names only the failed pods' trajectories and carries the other pods' rows in its
        ``answered`` (a ``StageBatch``): their envs did reset or step, and they go on from there.
        """
        self._check_stage(stage_id)
        keys = self.stage_traj_keys(stage_id) if traj_keys is None else list(traj_keys)
        self._check_keys(keys, stage_id)
        return self._submit(reset=keys, step={}, pick=0)

    def step_stage(
        self, stage_id: int, actions_by_traj_key: Mapping[str, Any] | StepActions, record: Sequence[str] = ()
    ) -> PendingCall[StageBatch]:
        """Step the given trajectories of a stage, one action or one chunk each; don't wait.

        Each value is one action (``[action dim]``) or a chunk of K actions (``[K, action dim]``,
        the same K for every trajectory of the call, at most the pods' ``max_chunk``): a chunk
        is applied in order and stops at the trajectory's first termination or truncation, and
        the pod renders once, after the last applied action. ``record`` names traj_keys (of a
        chunk call) whose frame after every applied action the answer carries in ``frames``.
        An empty mapping is a no-op (an empty batch). Rows of the answer follow the mapping's order.
        In place of the mapping, :meth:`step_actions` of the keys and one array of all their
        actions or chunks (no per-key values to stack).

        Raises:
            ValueError: no such stage, a key not live on it, an action of the wrong shape or not
                finite, or chunks of different lengths (names the traj_key).
            ResetNeeded: (``ended_envs="raise"``) a trajectory whose env ended and was not reset.
            RoutingChangedError, AlreadyPendingCallError, ClosedEnvironmentError: as
                :meth:`reset_stage`, whose notes on the result's errors hold here too.
        """
        self._check_stage(stage_id)
        self._check_keys(_keys_of(actions_by_traj_key), stage_id)
        return self._submit(reset=(), step=actions_by_traj_key, pick=1, record=record)

    def call(
        self,
        *,
        reset: Sequence[str] | Mapping[str, int] = (),
        step: Mapping[str, Any] | StepActions | None = None,
        record: Sequence[str] = (),
        seeds: Mapping[str, int | None] | None = None,
        options: Mapping[str, Any] | None = None,
    ) -> PendingCall[tuple[StageBatch, StageBatch]]:
        """Reset some trajectories and step others in one round, over any stages; don't wait.

        ``reset`` lists traj_keys to reset to their route's state id, or maps traj_keys to new
        state ids (their routes take them on success). ``step`` maps traj_keys to actions or
        chunks (or is :meth:`step_actions`'s), and ``record`` names stepped keys whose every frame is wanted, as in
        :meth:`step_stage`. ``seeds`` (instead of ``reset``) maps traj_keys to a seed or None:
        their envs reset as the envs' own ``reset(seed=..., options=options)``, not to a fixed
        state (the routes keep their state ids). Each pod gets its resets first, then its steps; pods run
        concurrently. The result is the pair
        ``(reset_batch, step_batch)``; nothing to do is a no-op answering two empty batches. The
        result's errors are :meth:`reset_stage`'s; ``answered`` is a pair here too.

        Raises:
            ValueError: unknown traj_keys, a key both reset and stepped, bad state ids or actions.
            RoutingChangedError: a key whose env went away when the routing changed.
            AlreadyPendingCallError: a stage involved already waits on a call.
            ClosedEnvironmentError: the client is closed.
        """
        return self._submit(reset=reset, step=step or {}, pick=None, record=record, seeds=seeds, options=options)

    def pod_call(
        self,
        pod: str,
        *,
        reset: Sequence[str] | Mapping[str, int] = (),
        step: Mapping[str, Any] | StepActions | None = None,
        record: Sequence[str] = (),
    ) -> PendingCall[tuple[StageBatch, StageBatch]]:
        """:meth:`call` on the trajectories of one pod, holding only that pod: the other pods of
        its stage take calls meanwhile, so each pod's answer is usable when it lands and a slow
        pod holds up only its own trajectories. Answers, errors and arguments as :meth:`call`'s.

        Raises:
            ValueError: an unknown pod, a key not on ``pod``, or as :meth:`call`.
            AlreadyPendingCallError: the pod (or its whole stage) already waits on a call.
            RoutingChangedError, ClosedEnvironmentError: as :meth:`call`.
        """
        self._check_open()
        step = step or {}
        self._book.check_on_pod([*reset, *_keys_of(step)], pod)
        return self._submit(reset=reset, step=step, pick=None, record=record, pod=pod)

    def step_actions(self, traj_keys: Sequence[str], actions: Any) -> StepActions:
        """The actions of ``traj_keys`` as one call's, from one array (row ``j`` for
        ``traj_keys[j]``): ``[n, action dim]``, or chunks ``[n, K, action dim]``. Pass the result as
        a call's ``step``: the array goes to the pods as it is, cut per pod.

        Raises:
            ValueError: as :func:`vecsim.client.calls.step_actions` (shape, count, NaN, names the key).
        """
        return step_actions(self.action_space, traj_keys, actions)

    def env_attr(
        self, op: str, keys: Sequence[str], name: str, payload: Any = None
    ) -> PendingCall[tuple[list[Any], list[tuple[str, str, str]]]]:
        """Get (``op`` ``get_attr``), call (``call``; ``payload`` ``(args, kwargs)``) or set
        (``set_attr``; ``payload`` one value per key) attribute ``name`` of the envs of ``keys``,
        all their pods concurrently; don't wait.

        The result is ``(results, errors)``: one JSON result per key (None where its env raised or
        for ``set_attr``) and ``(traj_key, exception type name, message)`` per env that raised.
        It raises what a call's result raises (``PodRequestError`` for a 4xx: a bad name or value).

        Raises:
            ValueError: an unknown op or key.
            ClosedEnvironmentError: the client is closed.
        """
        self._check_open()
        routes = check_attr(self._book, op, keys)
        return self.submit(run_attr(self._pods, op, list(keys), name, payload, routes))

    def _submit(
        self,
        *,
        reset: Sequence[str] | Mapping[str, int],
        step: Mapping[str, Any] | StepActions,
        pick: int | None,
        record: Sequence[str] = (),
        seeds: Mapping[str, int | None] | None = None,
        options: Mapping[str, Any] | None = None,
        pod: str | None = None,
    ) -> PendingCall[Any]:
        self._check_open()
        args = check_call(self._book, reset, _keys_of(step), record, seeds, options, self.ended_envs)
        # Spaces first, so even an empty answer has the job's observation structure (0 rows).
        self._job()
        if isinstance(step, StepActions):
            actions: StepActions | None = step
        else:
            actions = check_actions(self.action_space, step) if step else None
        if args.recorded and (actions is None or actions.chunk is None):
            raise ValueError("record: frames are recorded for chunk steps only; send [K, action dim] per traj_key")
        if actions is None or not actions.traj_keys:
            if not args.reset_keys:
                space = self._info.observation_space
                return completed(
                    (empty_batch(space), empty_batch(space, chunk=None if actions is None else actions.chunk)), pick
                )
        resetting = {args.routes[k].stage_id for k in args.reset_keys}
        stepping = {args.routes[k].stage_id for k in (actions.traj_keys if actions is not None else ())}
        states = {
            stage: StageState.waiting_for(stage in resetting, stage in stepping) for stage in resetting | stepping
        }
        token = _Held()  # what holds the stages: the call, named before its future exists

        async def run() -> tuple[StageBatch, StageBatch]:
            try:
                return await run_call(self._pods, args, actions, pick, self.ended_envs == "step")
            finally:
                # Before the answer is handed over: a caller whose result() returned finds its
                # stages idle.
                self._states.end(states, token)

        future = self._states.begin(states, token, lambda: self._loop.submit(run()), pod=pod)
        # A call cancelled before it started never runs its finally.
        future.add_done_callback(lambda _f: self._states.end(states, token))
        token.pending = PendingCall(future, pick, self._loop)
        return token.pending

    def stage_state(self, stage_id: int) -> StageState:
        """What a stage is doing: ``IDLE`` or waiting on a reset, a step or a mixed call.

        Raises:
            ValueError: no such stage.
        """
        self._check_stage(stage_id)
        return self._states.state(stage_id)

    def close(self) -> None:
        """Close every pod connection and the loop thread; later calls raise ClosedEnvironmentError."""
        if self._closed:
            return
        self._closed = True
        _open_clients.discard(self)
        for held in self._states.end_all():
            if held.pending is not None:
                held.pending.cancel()
        self._disconnect()

    def __enter__(self) -> StageClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- checks ---------------------------------------------------------------------------------

    def _check_stage(self, stage_id: int) -> None:
        self._check_open()
        self._book.check_stage(stage_id)

    def _check_keys(self, keys: list[str], stage_id: int) -> None:
        self._book.check_on_stage(keys, stage_id)
