"""Errors of the trainer-side client; each names the pod, stage, task or traj_keys at fault."""

from __future__ import annotations

import builtins
from collections.abc import Iterable, Mapping
from typing import Any

__all__ = [
    "CapacityError",
    "ClientError",
    "PodRequestError",
    "PodUnavailableError",
    "RoutingChangedError",
    "StaleGenerationError",
]


def _keys(keys: Iterable[str], limit: int = 8) -> str:
    keys = list(keys)
    shown = ", ".join(keys[:limit])
    return shown + (f", ... ({len(keys)} in all)" if len(keys) > limit else "")


class ClientError(Exception):
    """Base of the client's errors.

    ``failed_envs`` and ``result`` are set by ``HTTPVectorEnv`` on an error that ends its reset or
    step: the indices of the envs that got no answer, and the call's result for the others (see
    its docstring). ``None`` for errors raised anywhere else. An env's own exception, which
    ``HTTPVectorEnv`` gives the same two attributes, is never a ``ClientError``.
    """

    failed_envs: list[int] | None = None
    result: Any = None


class CapacityError(ClientError, ValueError):
    """A batch asks a stage for more envs of a task than its pods hold (or for a task it lacks)."""

    def __init__(self, task_id: str, stage_id: int, capacity: int, requested: list[int], pods: list[str]) -> None:
        self.task_id, self.stage_id, self.capacity, self.requested, self.pods = (
            task_id,
            stage_id,
            capacity,
            requested,
            pods,
        )
        where = f"on pods {', '.join(pods)}" if pods else "on no pod"
        super().__init__(
            f"stage {stage_id} has {capacity} env(s) of task {task_id!r} ({where}) but the batch puts "
            f"{len(requested)} request(s) of it there (requests {_keys(map(str, requested))}); draw "
            "batches with TaskBalancedSampler(group_size <= the job's group_size, num_stages = the job's stages) "
            "or raise the job's group_size"
        )


class PodUnavailableError(ClientError):
    """Pods that gave no usable answer in time (dead, partitioned, rebuilding, or answering
    something broken: a bad HTTP message, an answer over the cap or not decodable, not valid wire,
    of the wrong shape); names the traj_keys they held.

    ``answered``, when the error ends a stage call, is what the pods that did answer returned:
    the call's result (a ``StageBatch``, or the ``(reset_batch, step_batch)`` pair of
    ``StageClient.call``) holding only their trajectories' rows. Those envs did reset or step, so
    their trajectories go on from these rows. ``None`` for errors outside a stage call.
    """

    def __init__(self, held: Mapping[str, list[str]], reason: str, *, answered: Any = None) -> None:
        self.held = {pod: list(keys) for pod, keys in held.items()}
        self.pods = list(self.held)
        self.traj_keys = [k for keys in self.held.values() for k in keys]
        self.reason = reason
        self.answered = answered
        parts = "; ".join(f"pod {pod} (traj_keys: {_keys(keys) or 'none'})" for pod, keys in self.held.items())
        super().__init__(f"unavailable: {parts}: {reason}")


class PodRequestError(ClientError):
    """A pod refused a request (4xx other than 409), or the controller or a pod's ``/v1/info``
    answered something malformed."""

    def __init__(self, pod: str, status: int | None, detail: str) -> None:
        self.pod, self.status, self.detail = pod, status, detail
        code = f" ({status})" if status is not None else ""
        super().__init__(f"pod {pod} refused the request{code}: {detail}")


class StaleGenerationError(ClientError):
    """A pod answered 409: it holds another generation than the request carried. The client
    re-reads the routing table and retries once; this reaches the caller when the pod still
    answers 409 after that."""

    def __init__(self, pod: str, generation: int | None, detail: str) -> None:
        self.pod, self.generation, self.detail = pod, generation, detail
        super().__init__(f"pod {pod} refused generation {generation} (409): {detail}")


class RoutingChangedError(ClientError):
    """The routing table changed under live trajectories; they must be reset on their new envs.

    ``answered``: as :class:`PodUnavailableError`'s (the rows of the trajectories whose pods did
    answer the stage call; ``None`` when the call was refused before it was sent).
    """

    def __init__(self, generation: int, traj_keys: list[str], *, answered: Any = None) -> None:
        self.generation, self.traj_keys = generation, list(traj_keys)
        self.answered = answered
        super().__init__(
            f"routing changed at generation {generation} under live trajectories "
            f"{_keys(self.traj_keys)}: their envs moved or went away; place and reset them again "
            "(StageClient.reset_trajectories)"
        )


def call_error(errors: list[BaseException], answered: Any) -> BaseException:
    """The one error a stage call raises for what its pods raised.

    Pods that were unavailable, or whose envs moved with the routing, fail alone: the error
    names their trajectories and carries ``answered``, the other pods' rows (a pod whose answer
    was broken counts as unavailable). Anything else (a refusal of the request, a 409 after the
    re-read) fails the call whole, as a bug in the request would. When both kinds of lone failure meet in one call, the
    ``PodUnavailableError`` is raised; ``answered`` still holds exactly the rows delivered.
    """
    unavailable = [e for e in errors if isinstance(e, PodUnavailableError)]
    moved = [e for e in errors if isinstance(e, RoutingChangedError)]
    others = [e for e in errors if not isinstance(e, (PodUnavailableError, RoutingChangedError))]
    if others:
        return others[0]
    if unavailable:
        held = {pod: keys for e in unavailable for pod, keys in e.held.items()}
        return PodUnavailableError(held, "; ".join(e.reason for e in unavailable), answered=answered)
    keys = [key for e in moved for key in e.traj_keys]
    return RoutingChangedError(max(e.generation for e in moved), keys, answered=answered)


def builtin_exception(type_name: str, message: str) -> BaseException:
    """The exception of builtin type ``type_name`` with ``message``; a ``RuntimeError`` naming the
    type for any other (a type is never rebuilt from anything but its builtin name)."""
    kind = getattr(builtins, type_name, None)
    if isinstance(kind, type) and issubclass(kind, Exception):
        try:
            return kind(message)
        except Exception:  # noqa: BLE001 - a builtin that takes other arguments (UnicodeDecodeError)
            pass
    return RuntimeError(f"{type_name}: {message}")
