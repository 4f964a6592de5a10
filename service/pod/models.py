"""Pydantic models of every pod request and response.

Reset and step bodies arrive as JSON (arrays as nested lists) or as the binary wire (arrays as
numpy arrays); the request models accept both and hand numpy arrays on. The response models
describe the JSON form of each answer for the OpenAPI page; wire answers carry the same keys.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PlainValidator, WithJsonSchema

from vecsim import wire


def _generation(value: Any) -> int:
    # The wire may carry a scalar as a 0-d array rather than a JSON number.
    if isinstance(value, np.ndarray) and value.ndim == 0 and value.dtype.kind in "iu":
        return int(value)
    if type(value) is int:
        return value
    raise ValueError(f"must be an integer, got {type(value).__name__}")


def _json_array(value: Any, dtype: type[np.generic]) -> np.ndarray:
    # A wire array goes on as it is; JSON lists become arrays by the wire's JSON rules ("NaN" and
    # "Infinity" spelled as strings, no float -> int truncation). The simulation then checks
    # shapes, ranges and finiteness, naming the env.
    if isinstance(value, np.ndarray):
        return value
    try:
        return wire.from_jsonable(value, like=dtype)
    except wire.WireError as exc:
        raise ValueError(str(exc)) from None


def _int_vector(value: Any) -> np.ndarray:
    return _json_array(value, np.int64)


def _action_matrix(value: Any) -> np.ndarray:
    if isinstance(value, np.ndarray) and value.dtype != np.float32:
        raise ValueError(f"must be float32 on the wire, got {value.dtype}")
    return _json_array(value, np.float32)


Generation = Annotated[int, PlainValidator(_generation), WithJsonSchema({"type": "integer", "minimum": 0})]
IntVector = Annotated[
    np.ndarray,
    PlainValidator(_int_vector),
    WithJsonSchema({"type": "array", "items": {"type": "integer"}}),
]
_NUMBERS = {"type": "array", "items": {"type": "number"}}
ActionMatrix = Annotated[
    np.ndarray,
    PlainValidator(_action_matrix),
    WithJsonSchema(
        {
            "oneOf": [
                {"type": "array", "items": _NUMBERS, "description": "[n, action dim]: one action per env"},
                {
                    "type": "array",
                    "items": {"type": "array", "items": _NUMBERS},
                    "description": "[n, K, action dim]: a chunk per env",
                },
            ]
        }
    ),
]


class _Request(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, arbitrary_types_allowed=True)


class ResetRequest(_Request):
    """``POST /v1/reset``: put ``env_ids[i]`` in fixed initial state ``state_ids[i]``."""

    generation: Generation = Field(description="the assignment generation the caller routes by")
    env_ids: IntVector = Field(description="env indices of this pod, no duplicates")
    state_ids: IntVector = Field(description="one state id per env id")


class StepRequest(_Request):
    """``POST /v1/step``: apply ``actions[i]`` (one action, or a chunk of K in order) to
    ``env_ids[i]``; other envs do not move."""

    generation: Generation = Field(description="the assignment generation the caller routes by")
    env_ids: IntVector = Field(description="env indices of this pod, no duplicates")
    actions: ActionMatrix = Field(
        description="[n, action dim], or a chunk [n, K, action dim] with K up to /v1/info's max_chunk; "
        "finite numbers (float32 on the wire)"
    )
    record_env_ids: IntVector = Field(
        default_factory=lambda: np.zeros(0, dtype=np.int64),
        description="chunks only: env ids (among env_ids) whose camera frame after every applied action "
        "is answered in frames",
    )


class ResetInfo(BaseModel):
    success: list[bool]
    task_id: list[str]


class ResetResponse(BaseModel):
    """JSON form of a reset answer (the wire form has the same keys, arrays as arrays)."""

    env_ids: list[int]
    obs: dict[str, Any] = Field(description="batched observation, leading dim n")
    info: ResetInfo


class StepInfo(BaseModel):
    success: list[bool]


class StepResponse(BaseModel):
    """JSON form of a step answer (the wire form has the same keys, arrays as arrays)."""

    env_ids: list[int]
    obs: dict[str, Any] = Field(description="batched observation, leading dim n")
    reward: list[float]
    terminated: list[bool]
    truncated: list[bool]
    info: StepInfo


class ChunkStepInfo(BaseModel):
    success: list[list[bool]]


class ChunkStepResponse(BaseModel):
    """JSON form of the answer to a chunk step (``actions`` ``[n, K, action dim]``): entry
    ``[i][k]`` belongs to action k of env i, 0/false after env i stopped."""

    env_ids: list[int]
    obs: dict[str, Any] = Field(description="observation after each env's last applied action, leading dim n")
    reward: list[list[float]] = Field(description="[n, K]")
    terminated: list[list[bool]] = Field(description="[n, K]")
    truncated: list[list[bool]] = Field(description="[n, K]")
    num_steps: list[int] = Field(description="[n] actions applied: K unless the env terminated or truncated first")
    info: ChunkStepInfo
    frames: dict[str, Any] | None = Field(
        None, description="with record_env_ids: {camera: uint8 [m, K, H, W, 3]}, the frame after each applied action"
    )


class TaskInfo(BaseModel):
    task_id: str
    instruction: str
    env_start: int
    num_envs: int


class InfoResponse(BaseModel):
    """``GET /v1/info``: who the pod is and what it runs; spaces and instance are null until the
    envs are built."""

    pod: str
    stage_id: int | None
    generation: int | None
    ready: bool
    num_envs: int
    tasks: list[TaskInfo]
    observation_space: dict[str, Any] | None
    action_space: dict[str, Any] | None
    max_chunk: int = Field(description="the most actions per env one POST /v1/step takes (a chunk's K)")
    instance: str | None = Field(
        description="names this build of the envs: new when they are built anew, kept when only the generation moves on"
    )


class AssignmentResponse(BaseModel):
    """``PUT /v1/assignment``: the generation now held and whether the envs are being rebuilt."""

    generation: int
    rebuilt: bool


class HealthResponse(BaseModel):
    status: str


class ReadyResponse(BaseModel):
    status: str
    generation: int | None
    num_envs: int


class ErrorResponse(BaseModel):
    detail: str
