"""Prometheus metrics of the pod."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ..deps import get_metrics
from ..metrics import PodMetrics

router = APIRouter(tags=["metrics"])


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}, "description": "Prometheus text format"}},
    summary="Prometheus metrics",
)
async def metrics(pod_metrics: PodMetrics = Depends(get_metrics)) -> Response:
    """Env steps and resets, step latency, envs, readiness and errors by kind."""
    return Response(generate_latest(pod_metrics.registry), media_type=CONTENT_TYPE_LATEST)
