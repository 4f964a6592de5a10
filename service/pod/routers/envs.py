"""The data plane: reset and step envs, and look at one env's camera."""

from __future__ import annotations

import io
import time
from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
from fastapi import APIRouter, Depends, Path, Query, Request, Response
from PIL import Image

from vecsim import sim, wire

from ..bodies import JSON_TYPE, encode_answer, parse_body, wants_json
from ..deps import get_state
from ..errors import InvalidRequestError, SimCrashedError, UnknownEnvError
from ..models import ChunkStepResponse, ErrorResponse, ResetRequest, ResetResponse, StepRequest, StepResponse
from ..state import PodState

router = APIRouter(tags=["envs"])
T = TypeVar("T")

_ERRORS: dict[int | str, dict[str, Any]] = {
    400: {"model": ErrorResponse, "description": "body is not valid JSON or wire"},
    404: {"model": ErrorResponse, "description": "unknown env id"},
    409: {"model": ErrorResponse, "description": "generation is not the pod's"},
    413: {"model": ErrorResponse, "description": "body over the pod's limit"},
    415: {"model": ErrorResponse, "description": "Content-Type neither JSON nor wire"},
    422: {"model": ErrorResponse, "description": "wrong field, shape, dtype, NaN/inf, duplicate env"},
    503: {"model": ErrorResponse, "description": "envs not built, rebuilding, or crashed"},
}


def _body_doc(model: type[Any]) -> dict[str, Any]:
    """OpenAPI request body for a route that reads its body itself (JSON or wire)."""
    return {
        "requestBody": {
            "required": True,
            "content": {
                JSON_TYPE: {"schema": model.model_json_schema()},
                wire.CONTENT_TYPE: {"schema": {"type": "string", "format": "binary"}},
            },
        }
    }


def _answer_doc(model: type[Any]) -> dict[int | str, dict[str, Any]]:
    return {
        200: {
            "model": model,
            "description": f"wire ({wire.CONTENT_TYPE}) unless Accept asks for {JSON_TYPE}",
            "content": {wire.CONTENT_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        },
        **_ERRORS,
    }


async def _simulate(state: PodState, env: sim.TaskGroupedVectorEnv, work: Callable[[], T]) -> T:
    """Run ``work`` on the worker thread, or right here for cheap scenes (``state.inline``),
    turning the simulation's errors into HTTP errors."""
    try:
        if state.inline:
            return work()
        return await state.run(work)
    except sim.UnknownEnvError as exc:
        raise UnknownEnvError(f"pod {state.settings.name}: {exc}") from None
    except sim.InvalidRequestError as exc:
        raise InvalidRequestError(f"pod {state.settings.name}: {exc}") from None
    except sim.SimCrashedError as exc:
        state.rebuild_after_crash(env, str(exc))
        raise SimCrashedError(f"pod {state.settings.name}: simulation crashed, rebuilding its envs: {exc}") from None


@router.post(
    "/v1/reset",
    response_class=Response,
    responses=_answer_doc(ResetResponse),
    openapi_extra=_body_doc(ResetRequest),
    summary="Reset envs to fixed initial states",
)
async def reset(request: Request, state: PodState = Depends(get_state)) -> Response:
    """Put ``env_ids[i]`` in fixed initial state ``state_ids[i]`` of its task; answers their
    observations. Other envs do not change; no env ids is a no-op answering empty arrays."""
    req = parse_body(request, await request.body(), ResetRequest)
    env = state.serving_env(req.generation)
    as_json = wants_json(request)

    def work() -> Response:
        obs, info = env.reset_envs(req.env_ids, req.state_ids)
        return encode_answer(
            {
                "env_ids": req.env_ids.astype(np.int32),
                "obs": obs,
                "info": {"success": np.asarray(info["success"], dtype=bool), "task_id": list(info["task_id"])},
            },
            as_json,
        )

    response = await _simulate(state, env, work)
    state.metrics.env_resets.inc(len(req.env_ids))
    return response


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
    openapi_extra=_body_doc(StepRequest),
    summary="Step some envs one action or one chunk of actions each",
)
async def step(request: Request, state: PodState = Depends(get_state)) -> Response:
    """Apply ``actions[i]`` to ``env_ids[i]``; answers their observations, rewards, termination
    and truncation flags and success. A chunk (``actions`` ``[n, K, action dim]``) is applied in
    order, each env stopping at its first termination or truncation, its cameras rendered once
    after its last applied action; the answer's per-action arrays are ``[n, K]`` and
    ``num_steps`` says how many actions each env took. Other envs do not move; the pod never
    autoresets; no env ids (or K = 0) is a no-op."""
    req = parse_body(request, await request.body(), StepRequest)
    env = state.serving_env(req.generation)
    as_json = wants_json(request)
    is_chunk = req.actions.ndim == len(env.single_action_space.shape) + 2
    if req.record_env_ids.size and not is_chunk:
        raise InvalidRequestError(
            f"record_env_ids: pod {state.settings.name} records frames of chunks only; "
            "send actions as [n, K, action dim]"
        )

    def work() -> tuple[Response, float, sim.CallTiming, int]:
        start = time.perf_counter()
        if is_chunk:
            result = env.chunk_step_envs(req.env_ids, req.actions, req.record_env_ids)
            elapsed = time.perf_counter() - start
            answer: dict[str, Any] = {
                "env_ids": req.env_ids.astype(np.int32),
                "obs": result.obs,
                "reward": result.reward,
                "terminated": result.terminated,
                "truncated": result.truncated,
                "num_steps": result.num_steps,
                "info": {"success": result.success},
            }
            if req.record_env_ids.size:
                answer["frames"] = result.frames
            applied = int(result.num_steps.sum())
        else:
            obs, reward, terminated, truncated, info = env.step_envs(req.env_ids, req.actions)
            elapsed = time.perf_counter() - start
            answer = {
                "env_ids": req.env_ids.astype(np.int32),
                "obs": obs,
                "reward": np.asarray(reward, dtype=np.float32),
                "terminated": np.asarray(terminated, dtype=bool),
                "truncated": np.asarray(truncated, dtype=bool),
                "info": {"success": np.asarray(info["success"], dtype=bool)},
            }
            applied = len(req.env_ids)
        # Read on this thread, before another call can replace it.
        timing = env.last_timing
        return encode_answer(answer, as_json), elapsed, timing, applied

    response, elapsed, timing, applied = await _simulate(state, env, work)
    state.metrics.env_steps.inc(applied)
    state.metrics.env_renders.inc(timing.renders)
    state.metrics.step_seconds.observe(elapsed)
    state.metrics.physics_seconds.inc(timing.physics_s)
    state.metrics.render_seconds.inc(timing.render_s)
    return response


@router.get(
    "/v1/envs/{env_id}/frame.png",
    response_class=Response,
    responses={200: {"content": {"image/png": {}}, "description": "the camera image as PNG"}, **_ERRORS},
    summary="One env's camera image, as it is now",
)
async def frame(
    env_id: int = Path(description="env index on this pod"),
    camera: str | None = Query(None, description="camera name; the first camera when left out"),
    state: PodState = Depends(get_state),
) -> Response:
    """A PNG (height x width of the assignment's camera) of what ``camera`` of ``env_id`` saw at
    its last reset or step; nothing is stepped or reset."""
    env = state.current_env()
    if camera is None:
        images = env.single_observation_space.spaces.get("images")
        if images is None or not images.spaces:
            raise InvalidRequestError(f"camera: pod {state.settings.name} renders no cameras")
        camera = next(iter(images.spaces))
    name = camera

    def work() -> bytes:
        pixels = env.frame(env_id, name)
        out = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(pixels, dtype=np.uint8)).save(out, format="PNG")
        return out.getvalue()

    return Response(await _simulate(state, env, work), media_type="image/png")
