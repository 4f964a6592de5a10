"""Which envs of the job an :class:`~vecsim.client.vector_env.HTTPVectorEnv` holds, and the route
of each.

Env ``i`` of the vector env is ``routed_envs(table)[i]`` (stage-major:
:func:`vecsim.client.routing.routed_envs`), one fixed ``(pod, env_index)`` for its whole life,
stepped under the traj_key ``"env<i>"``. :class:`EnvRoutes` picks the envs, routes each key to
its env on the client, and routes the envs that a routing change took away back to their own env
when they are reset.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from vecsim.client.errors import ClientError
from vecsim.client.routing import RoutedEnv, TrajRoute, routed_envs
from vecsim.client.stage import StageClient

__all__ = ["EnvRoutes"]


class EnvRoutes:
    """The envs a vector env holds on ``client``'s job: the first ``num_envs`` of the routing
    table's envs (None: all of them). ``routed[i]`` is env ``i``, ``keys[i]`` its traj_key."""

    def __init__(self, client: StageClient, num_envs: int | None) -> None:
        """Pick the envs and route each key to its own env.

        Raises:
            ValueError: a job without envs, or a ``num_envs`` that is not ``1..`` the job's.
        """
        routed = routed_envs(client.routing)
        if not routed:
            raise ValueError(f"routing table generation {client.routing.generation} has no envs; is the job ready?")
        if num_envs is not None:
            if (
                isinstance(num_envs, bool)
                or not isinstance(num_envs, (int, np.integer))
                or not 1 <= num_envs <= len(routed)
            ):
                raise ValueError(
                    f"num_envs={num_envs!r} but the job has {len(routed)} envs; ask for 1..{len(routed)} "
                    "(the first num_envs of them) or leave num_envs out (all)"
                )
            routed = routed[: int(num_envs)]
        self.client = client
        self.routed: list[RoutedEnv] = routed
        self.keys = [f"env{i}" for i in range(len(routed))]
        self._route({})

    def place_lost(self, mask: np.ndarray) -> None:
        """Route the masked envs whose pod's envs went away with a routing change back to their
        own ``(pod, env_index)``, if the job still has the same envs (a pod that came back into
        its plan slot).

        Raises:
            ClientError: the job's envs are no longer these (names the generation).
        """
        live = self.client.routes
        lost = [int(i) for i in np.flatnonzero(mask) if self.keys[i] not in live]
        if not lost:
            return
        table = self.client.routing
        if routed_envs(table) != self.routed:
            raise ClientError(
                f"the job's envs changed at routing generation {table.generation}: envs {lost} "
                f"({', '.join(self.keys[i] for i in lost)}) lost their envs; close this HTTPVectorEnv "
                "and make a new one"
            )
        self._route(live)

    def by_env(self) -> dict[int, TrajRoute]:
        """Env index -> its route; an env whose pod's envs went away is left out until reset."""
        routes = self.client.routes
        return {i: routes[key] for i, key in enumerate(self.keys) if key in routes}

    def _route(self, live: Mapping[str, TrajRoute]) -> None:
        """Route each key to its own ``(pod, env_index)``: ``live``'s route where it has one."""
        self.client.set_routes(
            {
                key: live.get(key) or TrajRoute(routed.pod, routed.env_index, routed.task_id, routed.stage_id, 0)
                for key, routed in zip(self.keys, self.routed)
            }
        )
