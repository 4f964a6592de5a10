"""The client's route book: the routing table in use, where each live trajectory runs, which
trajectories lost their envs when the routing changed, and which ended and were not reset since. Pure (no I/O): the rules of placing are
:mod:`vecsim.client.routing`'s; this keeps their result and answers questions about it.

Thread-safe: the caller's thread places and checks, the client's loop records state ids and
routing changes.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from vecsim.client.errors import RoutingChangedError
from vecsim.client.routing import TrajRoute, changed_routes, check_request, place_requests, stage_by_id, validate_routes
from vecsim.config import RoutingTable

__all__ = ["RouteBook"]


class RouteBook:
    """Live trajectories' routes over one routing table at a time.

    Raises ``ValueError`` (as :func:`~vecsim.client.routing.stage_by_id`) for a table whose stage
    ids are not ``0..S-1`` or that puts a pod in two stages.
    """

    def __init__(self, table: RoutingTable) -> None:
        stage_by_id(table)
        self._lock = threading.Lock()
        self._table = table
        self._routes: dict[str, TrajRoute] = {}
        self._lost: dict[str, int] = {}  # traj_key -> generation at which its env went away
        # traj_key -> what its env was when its episode ended (a calls.Ended), until it is reset.
        self._ended: dict[str, Any] = {}

    # -- reading --------------------------------------------------------------------------------

    @property
    def table(self) -> RoutingTable:
        return self._table

    @property
    def generation(self) -> int:
        return self._table.generation

    @property
    def num_stages(self) -> int:
        return len(self._table.stages)

    def routes(self) -> dict[str, TrajRoute]:
        """A copy of the live routes, in placement order."""
        with self._lock:
            return dict(self._routes)

    def stage_keys(self, stage_id: int) -> list[str]:
        """The live traj_keys of a stage, in placement order."""
        with self._lock:
            return [key for key, route in self._routes.items() if route.stage_id == stage_id]

    def pods_with_envs(self) -> list[str]:
        """The table's pods that have envs, stage by stage, each once."""
        return list(dict.fromkeys(p.pod for stage in self._table.stages for p in stage.pods if p.num_envs > 0))

    def ended(self) -> dict[str, Any]:
        """A copy of the trajectories whose env ended and was not reset since, with what their env
        was when it ended."""
        with self._lock:
            return dict(self._ended)

    def holders(self) -> list[str]:
        """The sorted names of the pods that run live trajectories."""
        with self._lock:
            return sorted({route.pod for route in self._routes.values()})

    # -- checks ---------------------------------------------------------------------------------

    def check_stage(self, stage_id: int) -> None:
        """Raises ``ValueError``: ``stage_id`` is not a stage of the table."""
        if stage_id not in {s.stage_id for s in self._table.stages}:
            raise ValueError(f"stage {stage_id} is not in the routing table (stages 0..{self.num_stages - 1})")

    def check_lost(self, keys: Iterable[str]) -> None:
        """Raises ``RoutingChangedError``: some of ``keys`` lost their envs (names them all)."""
        with self._lock:
            lost = [key for key in keys if key in self._lost]
            if lost:
                raise RoutingChangedError(self._lost[lost[0]], lost)

    def check_on_stage(self, keys: Sequence[str], stage_id: int) -> None:
        """Raises ``RoutingChangedError`` (a key lost its env) or ``ValueError`` (a key not live,
        or live on another stage), naming the key."""
        self.check_lost(keys)
        with self._lock:
            for key in keys:
                route = self._routes.get(key)
                if route is None:
                    raise ValueError(
                        f"traj_key {key!r} is not a live trajectory; place it with reset_trajectories first"
                    )
                if route.stage_id != stage_id:
                    raise ValueError(f"traj_key {key!r} runs on stage {route.stage_id}, not stage {stage_id}")

    def check_on_pod(self, keys: Sequence[str], pod: str) -> None:
        """Raises ``RoutingChangedError`` (a key lost its env) or ``ValueError`` (a pod not in the
        table, a key not live, or live on another pod), naming the key or pod."""
        self.check_lost(keys)
        routes = self.live(keys)
        if pod not in {routed.pod for stage in self._table.stages for routed in stage.pods}:
            raise ValueError(f"pod {pod!r} is not in the routing table")
        elsewhere = [key for key in keys if routes[key].pod != pod]
        if elsewhere:
            raise ValueError(f"traj_key {elsewhere[0]!r} runs on pod {routes[elsewhere[0]].pod}, not {pod}")

    def live(self, keys: Iterable[str]) -> dict[str, TrajRoute]:
        """A copy of the live routes, checked to hold every key of ``keys``.

        Raises:
            ValueError: naming the first key that is not live.
        """
        routes = self.routes()
        for key in keys:
            if key not in routes:
                raise ValueError(f"traj_key {key!r} is not a live trajectory; place it with reset_trajectories first")
        return routes

    # -- changes --------------------------------------------------------------------------------

    def place(
        self, requests: Sequence[tuple[str, int]], keys: Sequence[str], stages: Sequence[int] | None = None
    ) -> dict[str, TrajRoute]:
        """Routes for a new batch on the table in use (:func:`~vecsim.client.routing.place_requests`);
        nothing is replaced yet (see :meth:`replace`)."""
        return place_requests(self._table, requests, keys, stages)

    def admit(
        self, key: str, request: tuple[str, int], stage_id: int, pods: Sequence[str] | None = None
    ) -> TrajRoute | None:
        """Add one live trajectory for ``request`` ``(task_id, state_id)`` on the lowest env of its
        task that no live trajectory holds, on the first of ``pods`` (pods of stage ``stage_id``,
        in the caller's order of preference; None: the stage's in table order) that has one;
        return its route, or None (nothing changes) when none has.

        Raises:
            ValueError: a malformed request, a pod not of the stage, or ``key`` live already.
        """
        task_id, state_id = check_request(0, request)
        stage = stage_by_id(self._table)[stage_id]
        envs = {routed.pod: routed for routed in stage.pods}
        strangers = [pod for pod in pods or () if pod not in envs]
        if strangers:
            raise ValueError(f"pods {strangers} are not pods of stage {stage_id} ({list(envs)})")
        pods = list(envs) if pods is None else pods
        with self._lock:
            if key in self._routes:
                raise ValueError(f"traj_key {key!r} is live already")
            held = {(route.pod, route.env_index) for route in self._routes.values()}
            for pod in pods:
                routed = envs.get(pod)
                blocks = [block for block in routed.tasks if block.task_id == task_id] if routed else []
                for block in blocks:
                    for env in range(block.env_start, block.env_start + block.num_envs):
                        if (pod, env) not in held:
                            route = TrajRoute(pod, env, task_id, stage_id, int(state_id))
                            self._routes[key] = route
                            self._lost.pop(key, None)
                            self._ended.pop(key, None)
                            return route
        return None

    def retire(self, keys: Sequence[str]) -> None:
        """Drop live trajectories (their envs are free for :meth:`admit`).

        Raises:
            ValueError: a key that is not live (nothing changes).
        """
        with self._lock:
            unknown = [key for key in keys if key not in self._routes]
            if unknown:
                raise ValueError(f"traj_keys {unknown} are not live trajectories")
            for key in keys:
                del self._routes[key]
                self._ended.pop(key, None)

    def check_routes(self, routes: Mapping[str, TrajRoute]) -> None:
        """Raises ``ValueError`` for routes that do not fit the table (see ``validate_routes``)."""
        validate_routes(self._table, routes)

    def replace(self, routes: Mapping[str, TrajRoute]) -> None:
        """Make ``routes`` the live trajectories; no trajectory counts as lost any more, and an
        ended one stays ended only while it keeps its env."""
        with self._lock:
            for key in list(self._ended):
                before, now = self._routes.get(key), routes.get(key)
                if now is None or before is None or (before.pod, before.env_index) != (now.pod, now.env_index):
                    del self._ended[key]
            self._routes = dict(routes)
            self._lost = {}

    def note_ended(self, reset: Iterable[str], ended: Mapping[str, Any]) -> None:
        """Note a call's answer: the trajectories ``reset`` did not end, those in ``ended`` did
        (with what their env was then; one that had ended already keeps its first record)."""
        with self._lock:
            for key in reset:
                self._ended.pop(key, None)
            for key, record in ended.items():
                self._ended.setdefault(key, record)

    def set_state_ids(self, keys: Sequence[str], state_ids: Sequence[int]) -> None:
        """Record the state ids live trajectories were just reset to (keys no longer live are skipped)."""
        with self._lock:
            for key, state_id in zip(keys, state_ids):
                if key in self._routes:
                    self._routes[key] = dataclasses.replace(self._routes[key], state_id=int(state_id))

    def take_table(self, table: RoutingTable) -> list[str]:
        """Adopt a newer routing table; return (and lose) the live traj_keys whose pod changed
        (:func:`~vecsim.client.routing.changed_routes`).

        Raises:
            ValueError: as :func:`~vecsim.client.routing.stage_by_id`; nothing changes then.
        """
        stage_by_id(table)
        with self._lock:
            moved = changed_routes(self._table, table, self._routes)
            self._table = table
            self._lose(moved)
        return moved

    def lose_pod(self, pod: str) -> list[str]:
        """Lose every live trajectory on ``pod`` (its envs were built anew); return their keys."""
        with self._lock:
            keys = [key for key, route in self._routes.items() if route.pod == pod]
            self._lose(keys)
        return keys

    def _lose(self, keys: list[str]) -> None:
        for key in keys:
            del self._routes[key]
            self._lost[key] = self._table.generation
