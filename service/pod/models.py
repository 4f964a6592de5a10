"""Pydantic models of every pod request and response.

Reset and step bodies arrive as JSON (arrays as nested lists) or as the binary wire (arrays as
numpy arrays); the request models accept both and hand numpy arrays on. The response models
describe the JSON form of each answer for the OpenAPI page; wire answers carry the same keys.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PlainValidator, StrictBool, WithJsonSchema

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
    # The simulation casts to the action space's dtype and checks values against the space.
    if isinstance(value, np.ndarray) and value.dtype.kind not in "biuf":
        raise ValueError(f"must be numbers, got {value.dtype}")
    return _json_array(value, np.float64)


def _seed_list(value: Any) -> list[int | None] | None:
    if value is None:
        return None
    if isinstance(value, np.ndarray) and value.ndim == 1 and value.dtype.kind in "iu":
        return [int(v) for v in value]
    if not isinstance(value, list):
        raise ValueError(f"must be a list of ints or nulls, got {type(value).__name__}")
    for i, seed in enumerate(value):
        if seed is not None and type(seed) is not int:
            raise ValueError(f"seed {i} is {seed!r:.50}, not an int or null")
    return value


def _options(value: Any) -> dict[str, Any] | None:
    if value is None:
        return None
    if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
        raise ValueError(f"must be an object with string keys, got {type(value).__name__}")
    return value


SeedList = Annotated[
    list[int | None] | None,
    PlainValidator(_seed_list),
    WithJsonSchema({"type": "array", "items": {"type": ["integer", "null"], "minimum": 0}}),
]
ResetOptions = Annotated[dict[str, Any] | None, PlainValidator(_options), WithJsonSchema({"type": "object"})]
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
    """``POST /v1/reset``: put ``env_indices[i]`` in fixed initial state ``state_ids[i]``, or (with
    ``seeds`` instead) reset it as the env's own ``reset(seed=seeds[i], options=options)``."""

    generation: Generation = Field(description="the assignment generation the caller routes by")
    env_indices: IntVector = Field(description="env indices of this pod, no duplicates")
    state_ids: IntVector | None = Field(None, description="one state id per env id (fixed initial states)")
    seeds: SeedList = Field(
        None, description="instead of state_ids: one seed (int >= 0, or null) per env id, the envs' own reset"
    )
    options: ResetOptions = Field(None, description="with seeds: the options every named env's reset takes")


class StepRequest(_Request):
    """``POST /v1/step``: apply ``actions[i]`` (one action, or a chunk of K in order) to
    ``env_indices[i]``; other envs do not move."""

    generation: Generation = Field(description="the assignment generation the caller routes by")
    env_indices: IntVector = Field(description="env indices of this pod, no duplicates")
    actions: ActionMatrix = Field(
        description="[n, action dim], or a chunk [n, K, action dim] with K up to /v1/info's max_chunk; "
        "finite numbers (float32 on the wire)"
    )
    record_env_indices: IntVector = Field(
        default_factory=lambda: np.zeros(0, dtype=np.int64),
        description="chunks only: env ids (among env_indices) whose camera frame after every applied action "
        "is answered in frames",
    )
    step_past_end: StrictBool = Field(
        False,
        description="chunks only: apply all K actions to every env, also after it terminated or truncated "
        "(its flags and reward as the scene computes them, its episode limit counting on; num_steps K); "
        "left false, each env stops at its first termination or truncation",
    )
    reset_env_indices: IntVector = Field(
        default_factory=lambda: np.zeros(0, dtype=np.int64),
        description="env ids (none of env_indices) reset in the same call, as /v1/reset does, "
        "beside the steps (a rollout's refill); their answer is the answer's reset",
    )
    reset_state_ids: IntVector = Field(
        default_factory=lambda: np.zeros(0, dtype=np.int64),
        description="one fixed initial state id per reset_env_indices entry",
    )


class ResetInfo(BaseModel):
    success: list[bool]
    task_id: list[str]


_OBS_DOC = (
    "batched observation, leading dim n: an array for a Box/Discrete space, an object for a Dict "
    "space, an object keyed '0', '1', ... for a Tuple space"
)
_ENV_INFO_DOC = (
    "the envs' own info keys, batched as gymnasium's vector envs batch them (key k: [n] values, "
    "_k: bool [n] mask of the envs that gave it); left out when no env gave any"
)


class EnvErrors(BaseModel):
    """The envs of the call whose own code raised; every other env of the call did its work."""

    env_indices: list[int]
    type: list[str] = Field(description="the exception's type name, e.g. ValueError")
    message: list[str]


class ResetResponse(BaseModel):
    """JSON form of a reset answer (the wire form has the same keys, arrays as arrays)."""

    env_indices: list[int]
    obs: Any = Field(description=_OBS_DOC)
    info: ResetInfo
    env_info: dict[str, Any] | None = Field(None, description=_ENV_INFO_DOC)
    errors: EnvErrors | None = Field(None, description="present when an env raised")


class StepInfo(BaseModel):
    success: list[bool]


class StepResponse(BaseModel):
    """JSON form of a step answer (the wire form has the same keys, arrays as arrays)."""

    env_indices: list[int]
    obs: Any = Field(description=_OBS_DOC)
    reward: list[float]
    terminated: list[bool]
    truncated: list[bool]
    info: StepInfo
    env_info: dict[str, Any] | None = Field(None, description=_ENV_INFO_DOC)
    errors: EnvErrors | None = Field(None, description="present when an env raised")
    reset: ResetResponse | None = Field(None, description="with reset_env_indices: the reset envs' answer")


class ChunkStepInfo(BaseModel):
    success: list[list[bool]]


class ChunkStepResponse(BaseModel):
    """JSON form of the answer to a chunk step (``actions`` ``[n, K, action dim]``): entry
    ``[i][k]`` belongs to action k of env i, 0/false after env i stopped."""

    env_indices: list[int]
    obs: Any = Field(description="observation after each env's last applied action, leading dim n")
    reward: list[list[float]] = Field(description="[n, K]")
    terminated: list[list[bool]] = Field(description="[n, K]")
    truncated: list[list[bool]] = Field(description="[n, K]")
    num_steps: list[int] = Field(description="[n] actions applied: K unless the env terminated or truncated first")
    info: ChunkStepInfo
    frames: dict[str, Any] | None = Field(
        None,
        description="with record_env_indices: {camera: uint8 [m, K, H, W, 3]}, the frame after each applied action",
    )
    env_info: dict[str, Any] | None = Field(None, description=_ENV_INFO_DOC + "; after each env's last applied action")
    errors: EnvErrors | None = Field(None, description="present when an env raised")
    reset: ResetResponse | None = Field(None, description="with reset_env_indices: the reset envs' answer")


class AttrRequest(_Request):
    """``POST /v1/get_attr``, ``/v1/call``, ``/v1/set_attr``: one attribute of some envs."""

    generation: Generation = Field(description="the assignment generation the caller routes by")
    env_indices: IntVector = Field(description="env indices of this pod, no duplicates")
    name: str = Field(description="a public attribute of the envs (through a gym env's wrappers)")
    args: list[Any] = Field(default_factory=list, description="call only: positional arguments (JSON)")
    kwargs: dict[str, Any] = Field(default_factory=dict, description="call only: keyword arguments (JSON)")
    values: list[Any] | None = Field(None, description="set_attr only: one JSON value per env id")


class AttrResponse(BaseModel):
    """JSON answer of the attribute endpoints: one result per env id (null for set_attr and for
    an env that raised)."""

    env_indices: list[int]
    results: list[Any]
    errors: EnvErrors | None = Field(None, description="present when an env raised")


class TaskInfo(BaseModel):
    task_id: str
    instruction: str
    env_start: int
    num_envs: int
    stage_id: int | None = Field(
        None, description="the stage this block's envs serve; null: the pod's stage_id (a pod of one stage)"
    )
    num_states: int = Field(description="how many fixed initial states the task has (state ids 0..num_states-1)")
    reset: str = Field(
        "state_id",
        description="how the client resets this task's envs by default: 'seed' (a gym task without cameras: "
        "the env's own seeded reset) or 'state_id' (fixed initial states)",
    )


class InfoResponse(BaseModel):
    """``GET /v1/info``: who the pod is and what it runs; spaces and instance are null until the
    envs are built."""

    pod: str
    stage_id: int | None = Field(
        description="the pod's stage; null when it has no assignment or holds several stages ('slices': see each task block)"
    )
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
