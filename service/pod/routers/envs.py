"""The data plane: reset and step envs, read, call and set their attributes, and look at one
env's camera."""

from __future__ import annotations

import io
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

import gymnasium
import numpy as np
from fastapi import APIRouter, Depends, Path, Query, Request, Response
from PIL import Image

from vecsim import wire
from vecsim.engine import CallTiming, EnvError, InvalidRequestError, PodEngine, SimCrashedError, UnknownEnvError
from vecsim.info import batch_infos
from vecsim.spaces import tuples_as_dicts

from ...models import Problem
from ..bodies import JSON_TYPE, Answer, encode_answer, parse_body, wants_json
from ..deps import get_state
from ..models import (
    AttrRequest,
    AttrResponse,
    ChunkStepResponse,
    ResetRequest,
    ResetResponse,
    StepRequest,
    StepResponse,
)
from ..idempotency import IDEMPOTENCY_KEY_PARAMETER
from ..state import PodState

router = APIRouter(tags=["envs"])
T = TypeVar("T")

_ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"model": Problem, "description": "body is not valid JSON or wire"},
    404: {"model": Problem, "description": "unknown env id"},
    409: {"model": Problem, "description": "generation is not the pod's"},
    413: {"model": Problem, "description": "body over the pod's limit"},
    415: {"model": Problem, "description": "Content-Type neither JSON nor wire"},
    422: {"model": Problem, "description": "wrong field, shape, dtype, NaN/inf, duplicate env"},
    503: {"model": Problem, "description": "envs not built, rebuilding, or crashed"},
}


def _body_doc(model: type[Any], keyed: bool = False) -> dict[str, Any]:
    """OpenAPI request body for a route that reads its body itself (JSON or wire); ``keyed``: the
    route also takes an ``Idempotency-Key`` header."""
    doc: dict[str, Any] = {
        "requestBody": {
            "required": True,
            "content": {
                JSON_TYPE: {"schema": model.model_json_schema()},
                wire.CONTENT_TYPE: {"schema": {"type": "string", "format": "binary"}},
            },
        }
    }
    if keyed:
        doc["parameters"] = [IDEMPOTENCY_KEY_PARAMETER]
    return doc


def _answer_doc(model: type[Any]) -> dict[int | str, dict[str, Any]]:
    return {
        200: {
            "model": model,
            "description": f"wire ({wire.CONTENT_TYPE}) unless Accept asks for {JSON_TYPE}",
            "content": {wire.CONTENT_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        },
        **_ERRORS,
    }


def _own(
    answer: dict[str, Any], ids: np.ndarray, env_info: list[dict[str, Any]], errors: list[EnvError]
) -> dict[str, Any]:
    """Add the envs' own info and the envs that raised to ``answer``; return it."""
    batched = batch_infos(env_info)
    if batched:
        answer["env_info"] = batched
    if errors:
        answer["errors"] = {
            "env_indices": np.array([int(ids[e.row]) for e in errors], dtype=np.int32),
            "type": [e.type_name for e in errors],
            "message": [e.message for e in errors],
        }
    return answer


def step_answer(ids: np.ndarray, result: tuple[Any, Any, Any, Any, dict[str, Any]]) -> dict[str, Any]:
    """``/v1/step``'s answer to one action per env, before it is encoded: built from what
    ``PodEngine.step_envs(ids, ...)`` returned (``result``)."""
    obs, reward, terminated, truncated, info = result
    answer = {
        "env_indices": ids.astype(np.int32),
        "obs": tuples_as_dicts(obs),
        "reward": np.asarray(reward, dtype=np.float64),
        "terminated": np.asarray(terminated, dtype=bool),
        "truncated": np.asarray(truncated, dtype=bool),
        "info": {"success": np.asarray(info["success"], dtype=bool)},
    }
    return _own(answer, ids, info["env_info"], info["errors"])


def reset_answer(ids: np.ndarray, obs: Any, info: dict[str, Any]) -> dict[str, Any]:
    """``/v1/reset``'s answer (and a step's ``reset``), before it is encoded: built from what
    ``PodEngine.reset_envs(ids, ...)`` returned."""
    answer = {
        "env_indices": ids.astype(np.int32),
        "obs": tuples_as_dicts(obs),
        "info": {"success": np.asarray(info["success"], dtype=bool), "task_id": list(info["task_id"])},
    }
    return _own(answer, ids, info["env_info"], info["errors"])


async def _simulate(state: PodState, env: PodEngine, work: Callable[[], T]) -> T:
    """Run ``work`` on the worker thread, or right here for cheap scenes (``state.inline``),
    turning the simulation's errors into HTTP errors."""
    try:
        if state.inline:
            return work()
        return await state.run(work)
    except (UnknownEnvError, InvalidRequestError) as exc:
        raise type(exc)(f"pod {state.settings.name}: {exc}") from None
    except SimCrashedError as exc:
        state.rebuild_after_crash(env, str(exc))
        raise SimCrashedError(f"pod {state.settings.name}: simulation crashed, rebuilding its envs: {exc}") from None


@router.post(
    "/v1/reset",
    response_class=Response,
    responses=_answer_doc(ResetResponse),
    openapi_extra=_body_doc(ResetRequest, keyed=True),
    summary="Reset envs to fixed initial states",
)
async def reset(request: Request, state: PodState = Depends(get_state)) -> Response:
    """Put ``env_indices[i]`` in fixed initial state ``state_ids[i]`` of its task, or (``seeds``
    instead) reset it as the env's own ``reset(seed=seeds[i], options=options)``; answers their
    observations, success, the envs' own info (``env_info``) and the envs that raised
    (``errors``). Other envs do not change; no env ids is a no-op answering empty arrays."""
    req = parse_body(request, await request.body(), ResetRequest)

    async def apply() -> tuple[Response, np.ndarray]:
        env = state.serving_env(req.generation)
        as_json = wants_json(request)

        def work() -> Response:
            obs, info = env.reset_envs(req.env_indices, req.state_ids, seeds=req.seeds, options=req.options)
            return encode_answer(reset_answer(req.env_indices, obs, info), as_json)

        response = await _simulate(state, env, work)
        state.metrics.env_resets.inc(len(req.env_indices))
        state.metrics.episodes_started(req.env_indices)
        return response, req.env_indices

    return await _once(state, request, req, apply)


@router.post(
    "/v1/step",
    response_class=Response,
    responses={
        **_answer_doc(StepResponse),
        200: {
            **_answer_doc(StepResponse)[200],
            "description": f"StepResponse for one action per env, ChunkStepResponse for chunks; "
            f"wire ({wire.CONTENT_TYPE}) unless Accept asks for {JSON_TYPE}",
            "content": {
                JSON_TYPE: {
                    "schema": {"oneOf": [StepResponse.model_json_schema(), ChunkStepResponse.model_json_schema()]}
                },
                wire.CONTENT_TYPE: {"schema": {"type": "string", "format": "binary"}},
            },
        },
    },
    openapi_extra=_body_doc(StepRequest, keyed=True),
    summary="Step some envs one action or one chunk of actions each",
)
async def step(request: Request, state: PodState = Depends(get_state)) -> Response:
    """Apply ``actions[i]`` to ``env_indices[i]``; answers their observations, rewards, termination
    and truncation flags and success. A chunk (``actions`` ``[n, K, action dim]``) is applied in
    order, each env stopping at its first termination or truncation (``step_past_end``: applying
    all K, as trainers that step ended envs and mask afterwards expect), its cameras rendered once
    after its last applied action; the answer's per-action arrays are ``[n, K]`` and
    ``num_steps`` says how many actions each env took. Other envs do not move; the pod never
    autoresets; no env ids (or K = 0) is a no-op. With ``reset_env_indices`` and
    ``reset_state_ids``, those envs (none of ``env_indices``) are reset to fixed states in the
    same call, their ``/v1/reset`` answer under ``reset``: a rollout's refill, whose resets so run
    beside the steps of the pod's other envs."""
    req = parse_body(request, await request.body(), StepRequest)

    async def apply() -> tuple[Response, np.ndarray]:
        return await _step(state, request, req), np.concatenate([req.env_indices, req.reset_env_indices])

    return await _once(state, request, req, apply)


Apply = Callable[[], Awaitable[tuple[Answer, np.ndarray]]]


async def _once(state: PodState, request: Request, req: ResetRequest | StepRequest, apply: Apply) -> Response:
    """Apply a keyed request once (:class:`~service.pod.idempotency.AnswerMemory`); count repeats."""
    answers = state.answers
    response, repeat = await answers.once(request, req, apply)
    if repeat:
        state.metrics.idempotency_key_repeats.inc()
    state.metrics.idempotency_key_answers.set(len(answers))
    return response


async def _step(state: PodState, request: Request, req: StepRequest) -> Response:
    env = state.serving_env(req.generation)
    as_json = wants_json(request)
    is_chunk = wire.chunk_length(req.actions.shape, env.single_action_space.shape or ()) is not None
    if req.step_past_end and not is_chunk:
        raise InvalidRequestError(
            f"step_past_end: pod {state.settings.name} steps past an env's end in chunks only; "
            "send actions as [n, K, action dim]"
        )
    if req.record_env_indices.size and not is_chunk:
        raise InvalidRequestError(
            f"record_env_indices: pod {state.settings.name} records frames of chunks only; "
            "send actions as [n, K, action dim]"
        )

    resetting = bool(req.reset_env_indices.size or req.reset_state_ids.size)

    def work() -> tuple[Response, float, CallTiming, int, tuple[np.ndarray, np.ndarray]]:
        start = time.perf_counter()
        reset: tuple[Any, dict[str, Any]] | None = None
        if resetting:
            reset, result = env.reset_and_step_envs(
                req.reset_env_indices,
                req.reset_state_ids,
                req.env_indices,
                req.actions,
                chunked=is_chunk,
                record_env_indices=req.record_env_indices,
                step_past_end=req.step_past_end,
            )
            if not is_chunk:  # one action per env: the answer's arrays are [n]
                result = (
                    result.obs,
                    result.reward[:, 0],
                    result.terminated[:, 0],
                    result.truncated[:, 0],
                    {"success": result.success[:, 0], "env_info": result.env_info, "errors": result.errors},
                )
        elif is_chunk:
            result = env.chunk_step_envs(req.env_indices, req.actions, req.record_env_indices, req.step_past_end)
        else:
            result = env.step_envs(req.env_indices, req.actions)
        elapsed = time.perf_counter() - start
        if is_chunk:
            answer: dict[str, Any] = {
                "env_indices": req.env_indices.astype(np.int32),
                "obs": tuples_as_dicts(result.obs),
                "reward": result.reward,
                "terminated": result.terminated,
                "truncated": result.truncated,
                "num_steps": result.num_steps,
                "info": {"success": result.success},
            }
            if req.record_env_indices.size:
                answer["frames"] = result.frames
            _own(answer, req.env_indices, result.env_info, result.errors)
            applied = int(result.num_steps.sum())
        else:
            answer = step_answer(req.env_indices, result)
            applied = len(req.env_indices)
        if reset is not None:
            answer["reset"] = reset_answer(req.reset_env_indices, *reset)
        # Read on this thread, before another call can replace it.
        timing = env.last_timing
        return encode_answer(answer, as_json), elapsed, timing, applied, (answer["terminated"], answer["truncated"])

    response, elapsed, timing, applied, ended = await _simulate(state, env, work)
    if resetting:
        state.metrics.env_resets.inc(len(req.reset_env_indices))
        state.metrics.episodes_started(req.reset_env_indices)
    state.metrics.episodes_ended(req.env_indices, *ended)
    state.metrics.env_steps.inc(applied)
    state.metrics.env_renders.inc(timing.renders)
    state.metrics.step_seconds.observe(elapsed)
    state.metrics.physics_seconds.inc(timing.physics_s)
    state.metrics.render_seconds.inc(timing.render_s)
    state.metrics.gpu_turn_wait_seconds.inc(timing.turn_wait_s)
    return response


@router.get(
    "/v1/envs/{env_index}/frame.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "the camera image as PNG"}, **_ERRORS},
    summary="One env's camera image, as it is now",
)
async def frame(
    env_index: int = Path(description="env index on this pod"),
    camera: str | None = Query(None, description="camera name; the first camera when left out"),
    state: PodState = Depends(get_state),
) -> Response:
    """A PNG (height x width of the assignment's camera) of what ``camera`` of ``env_index`` saw at
    its last reset or step; nothing is stepped or reset."""
    env = state.current_env()
    if camera is None:
        space = env.single_observation_space
        images = space.spaces.get("images") if isinstance(space, gymnasium.spaces.Dict) else None
        if images is None or not images.spaces:
            raise InvalidRequestError(f"camera: pod {state.settings.name} renders no cameras")
        camera = next(iter(images.spaces))
    name = camera

    def work() -> bytes:
        pixels = env.frame(env_index, name)
        out = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(pixels, dtype=np.uint8)).save(out, format="PNG")
        return out.getvalue()

    return Response(await _simulate(state, env, work), media_type="image/png")


async def _attr(request: Request, state: PodState, op: str) -> Response:
    req = parse_body(request, await request.body(), AttrRequest)
    env = state.serving_env(req.generation)
    if op == "set" and req.values is None:
        raise InvalidRequestError(f"values: pod {state.settings.name}: set_attr needs one value per env id")
    payload: Any = req.values if op == "set" else (req.args, req.kwargs)

    def work() -> Response:
        results, errors = env.env_attr(req.env_indices, op, req.name, payload)
        answer = {"env_indices": req.env_indices.astype(np.int32).tolist(), "results": results}
        return encode_answer(_own(answer, req.env_indices, [], errors), True)

    return await _simulate(state, env, work)


_ATTR_DOC = {
    "response_class": Response,
    "responses": {200: {"model": AttrResponse, "description": "JSON, one result per env id"}, **_ERRORS},
    "openapi_extra": _body_doc(AttrRequest),
}


@router.post("/v1/get_attr", summary="Read an attribute of some envs", **_ATTR_DOC)
async def get_attr(request: Request, state: PodState = Depends(get_state)) -> Response:
    """Answers attribute ``name`` of each env (a gym env's through its wrappers) as JSON; an
    attribute that JSON cannot hold is that env's error (``errors``), not a failure of the call."""
    return await _attr(request, state, "get")


@router.post("/v1/call", summary="Call a method of some envs", **_ATTR_DOC)
async def call(request: Request, state: PodState = Depends(get_state)) -> Response:
    """Calls ``name(*args, **kwargs)`` on each env (or reads it, if it is not callable) and
    answers the JSON results; what an env raises is answered in ``errors``, the others' results
    stand. ``close``, ``reset``, ``step`` and private names are refused (422)."""
    return await _attr(request, state, "call")


@router.post("/v1/set_attr", summary="Set an attribute of some envs", **_ATTR_DOC)
async def set_attr(request: Request, state: PodState = Depends(get_state)) -> Response:
    """Sets attribute ``name`` of env ``env_indices[i]`` to ``values[i]``; only an attribute whose
    value is JSON data (an array keeps its dtype and shape) may be set, never a method or a space."""
    return await _attr(request, state, "set")
