"""The ``mjwarp`` engine's settings: the pod's ``VECSIM_MJWARP_*`` environment variables (but the
scenes' folder, :data:`vecsim.engine.mjwarp.scene.ROOT_ENV`), read when an engine is built.

A value the engine cannot use fails the build, the variable and the value named; the pod's
``/readyz`` then says so. docs/mjwarp.md (Settings) lists them. Imports without warp, so the CPU
stack checks them too::

    settings = MjwarpSettings.from_env()  # os.environ
    settings.njmax, settings.turns_dir
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, field_validator

from vecsim.envsettings import from_environ

ALLOW_CPU_ENV = "VECSIM_MJWARP_ALLOW_CPU"
GPU_ENV = "VECSIM_MJWARP_GPU"
TURNS_ENV = "VECSIM_MJWARP_TURNS"
DEFAULT_TURNS_DIR = "/dev/shm/vecsim-turns"
DEFAULT_TURN_WAIT_S = 120.0


def turns_directory(value: str | None) -> str | None:
    """The GPUs' lock files' directory that a ``VECSIM_MJWARP_TURNS`` value names, or None for
    no turns (``None``, ``""`` or ``"off"``)."""
    return None if value in (None, "", "off") else value


# environment variable -> settings field
ENV_VARS: dict[str, str] = {
    "VECSIM_MJWARP_NCONMAX": "nconmax",
    "VECSIM_MJWARP_NJMAX": "njmax",
    "VECSIM_MJWARP_DETERMINISTIC": "deterministic",
    ALLOW_CPU_ENV: "allow_cpu",
    GPU_ENV: "gpu",
    TURNS_ENV: "turns",
    "VECSIM_MJWARP_TURN_WAIT_S": "turn_wait_s",
}


class MjwarpSettings(BaseModel):
    """How the engine builds its worlds and shares its GPU. An empty variable is an unset one,
    but for ``VECSIM_MJWARP_TURNS``, where it means no turns."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    # CPU MuJoCo holds about 99 constraint rows on LIBERO-10 task 0; MuJoCo Warp's defaults
    # overflowed there, these did not.
    nconmax: int = Field(96, ge=1, description="contacts per world (MuJoCo Warp's nconmax)")
    njmax: int = Field(600, ge=1, description="constraint rows per world (MuJoCo Warp's njmax)")
    deterministic: bool = Field(
        False,
        description="1: MuJoCo Warp's deterministic mode (contact order, constraint rows, atomics); on "
        "LIBERO-10 task 0 it shrank, not removed, the run-to-run spread (docs/mjwarp.md, Determinism)",
    )
    allow_cpu: bool = Field(
        False,
        description="1: build on warp's CPU device where warp sees no CUDA GPU (tests and debugging: the "
        "first build compiles for minutes); 0: such a pod fails its build, saying why",
    )
    # One pod a GPU or several: the local runner sets it from the job's pods.render_gpus (pod i on
    # render_gpus[i % len]); Kubernetes gives a pod its GPU, the first it sees.
    gpu: int | None = Field(
        None,
        ge=0,
        description="the CUDA device (warp's cuda:N, N as CUDA_VISIBLE_DEVICES leaves them) the engine "
        "runs on; unset: warp's default, the first one",
    )
    # Pods that share a GPU take turns only if they see the same directory: on one machine the
    # default does; Kubernetes pods that share a GPU need a hostPath volume there.
    turns: str = Field(
        DEFAULT_TURNS_DIR, description='the directory of the GPUs\' lock files; "" or "off": no turns (time-sliced)'
    )
    # A pod stuck in a GPU call slows the others down to time-slicing, it never stops them.
    turn_wait_s: float = Field(
        DEFAULT_TURN_WAIT_S, gt=0, description="a turn waited for longer than this is taken anyway, with a warning"
    )

    @field_validator("deterministic", "allow_cpu", mode="before")
    @classmethod
    def _one_or_zero(cls, value: Any) -> Any:
        if isinstance(value, str) and value not in ("0", "1"):
            raise ValueError("must be 1 (on) or 0 (off)")
        return value

    @property
    def turns_dir(self) -> str | None:
        """The lock files' directory, or None where turns are off."""
        return turns_directory(self.turns)

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> MjwarpSettings:
        """The settings in ``environ`` (default ``os.environ``; see :data:`ENV_VARS`), defaults
        for the variables not set.

        Raises:
            vecsim.envsettings.SettingsError: the variables at fault, with their values.
        """
        return from_environ(cls, ENV_VARS, environ, keep_empty=(TURNS_ENV,))
