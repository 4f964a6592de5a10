"""What the pod's and the controller's settings share: the job's token and how uvicorn serves
them (connection limits, logging). Each server's own settings subclass :class:`ServerSettings`
(``service.pod.settings.PodSettings``, ``service.controller.settings.ControllerSettings``)."""

from __future__ import annotations

from pydantic import Field, field_validator

from vecsim.auth import check_token
from vecsim.config import HeartbeatConfig


class ServerSettings(HeartbeatConfig):
    """The settings both servers read alike, with one default each (the heartbeat interval is the
    job file's: :class:`vecsim.config.HeartbeatConfig`)."""

    token: str | None = Field(
        None,
        repr=False,
        description="the job's shared token (VECSIM_TOKEN): required on every request that changes state, "
        "and sent with every request to the other server (a pod's heartbeats, the controller's pushes); "
        "None turns checking off (local development)",
    )
    header_timeout_s: float = Field(
        10.0,
        gt=0,
        description="a connection that sends no whole request head this soon after opening (or after its "
        "first byte, when kept alive) is closed",
    )
    keep_alive_s: float = Field(5.0, gt=0, description="an idle kept-alive connection is closed after this long")
    max_connections: int = Field(
        1024, ge=4, description="connections kept at most (lowered to half the fd limit); the idlest goes for a new one"
    )
    access_log: bool = False
    log_level: str = "info"

    @field_validator("token")
    @classmethod
    def _usable_token(cls, token: str | None) -> str | None:
        return check_token(token)
