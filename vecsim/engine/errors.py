"""What the pod engine raises, and what an env raised inside it.

The pod answers these as they are (``service.pod.errors.LIBRARY_ERRORS``): ``UnknownEnvError``
404, ``InvalidRequestError`` 422, ``SimCrashedError`` 503. An exception an env itself raises does
not end the call: it travels back as an :class:`EnvError` beside the other envs' results.
"""

from __future__ import annotations

from dataclasses import dataclass


class UnknownEnvError(LookupError):
    """An env index this pod does not have (HTTP 404)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class InvalidRequestError(ValueError):
    """A request that cannot be served as given: shape, dtype, value or length (HTTP 422)."""


class SpacesDifferError(InvalidRequestError, RuntimeError):
    """An assignment whose tasks' observation or action spaces differ (HTTP 422). A RuntimeError
    too: what gymnasium's vector envs raise for envs whose spaces differ."""


class SimCrashedError(RuntimeError):
    """A worker process died, hung or failed; the envs must be rebuilt (pod not ready)."""


class SimBuildError(RuntimeError):
    """Building the envs failed; the message names the task and what went wrong."""


@dataclass(frozen=True)
class EnvError:
    """An exception an env raised in a reset, step or attribute call: ``row`` of the answer (the
    env ``env_indices[row]``), the exception's type name and its message. The env stays as the
    exception left it; the pod's other envs are not touched."""

    row: int
    type_name: str
    message: str
