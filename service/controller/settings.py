"""The controller's settings: where it listens, how long pods live without a heartbeat, how
often it reconciles, and optionally the job it starts with."""

from __future__ import annotations

from pydantic import Field

from vecsim.config import ControllerConfig, JobConfig, JobSpec

from ..settings import ServerSettings

# Registrations, heartbeats and job specs are small JSON documents.
DEFAULT_MAX_BODY_BYTES = 1024 * 1024


class ControllerSettings(ServerSettings, ControllerConfig):
    """Everything the controller needs before it starts serving: the token and uvicorn's limits
    (:class:`service.settings.ServerSettings`), the job file's ``controller`` section
    (:class:`vecsim.config.ControllerConfig`: host, port, heartbeat and reconcile timing), and
    what only the server has."""

    stall_threshold_s: float = Field(
        1.0,
        gt=0,
        description="a gap this long (at most half the TTL) in which the controller's own event loop did not "
        "run is a stall: pods could not be heard meanwhile, so their heartbeat deadlines move on by it",
    )
    push_timeout_s: float = Field(10.0, gt=0, description="bound on one PUT /v1/assignment to a pod")
    push_backoff_max_s: float = Field(5.0, gt=0, description="longest wait before retrying a failed push")
    repush_after_s: float = Field(
        5.0, gt=0, description="push again when a pod accepted an assignment but has not reported it since"
    )
    adopt_grace_s: float = Field(
        30.0,
        ge=0,
        description="after a start, how long to wait for pods to report what they run before planning "
        "anew (sooner once every pod has reported and every unclaimed slot can go to a restarted pod); pods "
        "retry an unreachable controller with a backoff of up to 2 s, so this spans many of "
        "their retries and a restarted controller hears every pod before it plans",
    )
    job: JobSpec | None = None
    max_body_bytes: int = Field(DEFAULT_MAX_BODY_BYTES, ge=1, description="largest request body accepted (413 above)")

    @property
    def stall_after_s(self) -> float:
        """The gap between two ticks of the controller's loop that counts as a stall."""
        return min(self.stall_threshold_s, self.heartbeat_ttl_s / 2)

    @classmethod
    def from_job_config(cls, config: JobConfig, **overrides: object) -> ControllerSettings:
        """Returns settings taken from a job config's ``controller`` section and ``job``.

        ``overrides`` whose value is ``None`` are ignored (unset command-line flags).
        """
        # Every field of the section is a setting of the same name: one list of them, the config's.
        values: dict[str, object] = {**config.controller.model_dump(), "job": config.job}
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls.model_validate(values)
