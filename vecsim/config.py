"""Data models shared by the pod, the controller, the runner and the client.

Pure pydantic: no I/O except :func:`load_job_config`, which reads one YAML file. Every model
forbids unknown fields so that a typo in a config is an error naming the field, not a silent
default.
"""

from __future__ import annotations

import re
from collections.abc import Collection
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import AliasChoices, BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

RenderPreset = Literal["full", "fast", "lean", "lowpoly"]
# How a camera image's pixels are laid out: "upright" (row 0 is the top of the picture),
# "rotate180" (upright turned half a turn: LIBERO's raw frame as ``raw[::-1, ::-1]``, what LIBERO's
# published evaluation scripts feed their policies), "raw" (bottom row first, as OpenGL reads it
# back: the frame robosuite and LIBERO return themselves).
ImageOrientation = Literal["upright", "rotate180", "raw"]
# Where a LIBERO task's fixtures stand after a reset to state id k (docs/libero.md, "Fixtures"):
# ``published``: where LIBERO's env has them in episode k of the published evaluation loop (one
# env per task, seeded once, reset once per episode); ``first_reset``: where a freshly built env's
# first reset puts them, for every k. (LeRobot's placements come per reset, from the seed its eval
# loop gives each reset: vecsim.trainers.lerobot.)
FixtureRule = Literal["published", "first_reset"]
# The reset option that asks a LIBERO env for LeRobot's reset, sent with each env's seed (what
# vecsim.trainers.lerobot.LeRobotVectorEnv sends): {str(seed): {"state_id": k, "resets_before": r}}.
# The env reset with ``seed`` sets init state ``k`` as LeRobot's ``LiberoEnv`` does after ``r``
# earlier resets under ``env.seed(seed)``: fixtures and arm pose. Keyed by seed because one reset's
# options go to every env of the call, and LeRobot's eval seeds each env of a reset differently.
LEROBOT_RESETS = "lerobot_resets"
# How a job's pipeline stages sit on its pods (docs/control-plane.md, "Stage layouts"):
# ``slices``: every pod holds envs of every stage, so a stage is a slice of every pod (RLinf's
# layout: while the policy works on one stage, every pod simulates another); ``pods``: each pod
# holds one stage's envs (the seed's layout, for sim nodes apart from the trainer's).
StageLayout = Literal["slices", "pods"]
# What simulates a job's envs on its pods (vecsim.engine.base.ENGINES, docs/mjwarp.md): ``cpu``,
# the worker processes on the pod's cores (LIBERO's bit-exact reference); ``mjwarp``, MuJoCo Warp
# worlds on the pod's GPU.
EngineName = Literal["cpu", "mjwarp"]
ENGINE_DOC = (
    "what simulates the envs on the job's pods: 'cpu' (worker processes, LIBERO's reference) or "
    "'mjwarp' (MuJoCo Warp on one GPU per pod, scenes exported from the CPU engine: docs/mjwarp.md)"
)
STAGE_LAYOUT_DOC = (
    "how stages sit on pods: 'slices' (every pod holds envs of every stage; pods_per_stage counts "
    "all the job's pods) or 'pods' (each pod holds one stage; pods_per_stage pods per stage)"
)


# A pod's name: a Kubernetes DNS label (a StatefulSet pod's name, e.g. sim-0). The one definition
# every model and route that takes a pod name uses.
POD_NAME_PATTERN = r"^[a-z0-9]([-a-z0-9]*[a-z0-9])?$"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraConfig(_Model):
    """Which cameras every env of a job renders, and at what size (uint8 HxWx3 each)."""

    names: tuple[str, ...] = ("agentview", "robot0_eye_in_hand")
    height: int = Field(128, ge=8, le=1024)
    width: int = Field(128, ge=8, le=1024)

    @field_validator("names")
    @classmethod
    def _unique_names(cls, names: tuple[str, ...]) -> tuple[str, ...]:
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {list(names)}")
        return names


class LiberoProtocol(_Model):
    """The conventions LIBERO tasks follow: by default, those of LIBERO's published evaluations.

    Each one is one setting, so a job can take another (docs/libero.md compares them):

    - ``image_orientation``: how LIBERO tasks' camera images are laid out (:data:`ImageOrientation`).
    - ``settle_steps``: no-op steps (arm still, gripper opening: ``[0, 0, 0, 0, 0, 0, -1]``) run
      after every reset, before the observation is returned; they are not counted in the
      episode's steps.
    - ``fixture_seed``: the seed LIBERO's reset is run under (``env.seed(fixture_seed);
      env.reset()``) before the init state is set. Fixtures (cabinets, racks, microwaves) live in
      the model, not in the init state, so this seed places them: the same for every state id of
      a task, on every pod, whatever ran before. LIBERO's own evaluations seed 0 (OpenVLA-OFT)
      or 7 (openpi).
    - ``fixture_rule``: which of LIBERO's placements of those fixtures a reset to state id ``k``
      restores (:data:`FixtureRule`): by default ``published``, the one LIBERO's env has in
      episode ``k`` of the published evaluation loop after ``env.seed(fixture_seed)``;
      ``first_reset``, the one of a freshly built env's first reset, whatever ``k``. Both are
      functions of (task, ``k``, ``fixture_seed``) alone.

    Episode limits are not here: ``max_episode_steps`` left unset gives each LIBERO suite its own.
    """

    image_orientation: ImageOrientation = "rotate180"
    settle_steps: int = Field(10, ge=0, le=10_000)
    fixture_seed: int = Field(0, ge=0, lt=2**32)
    fixture_rule: FixtureRule = "published"


MAX_EPISODE_STEPS_DOC = (
    "steps after which every env truncates; unset: each LIBERO suite's own limit (spatial 220, "
    "object 280, goal 300, libero_10 520, libero_90 400) for LIBERO tasks, a gym id's own limit for gym "
    "tasks, 300 for the others"
)
MAKE_KWARGS_DOC = (
    "keyword arguments for gymnasium.make, per gym task id: {task_id: {name: value}} "
    "(JSON values; a task left out gets none)"
)
RENDER_DOC = "render preset; unset: 'full' for LIBERO tasks (LIBERO's own pixels), 'lean' for the others"


# 0 (the default) asks the pod to choose (vecsim.engine.resolve_envs_per_worker); YAML and JSON may say "auto".
AUTO_ENVS_PER_WORKER = 0
ENVS_PER_WORKER_DOC = (
    "envs hosted by one worker process, consecutive env indices of one task or several; 0 or "
    "'auto': the pod picks the fewest that keep its workers within its cores"
)


def _auto_to_zero(value: object) -> object:
    return AUTO_ENVS_PER_WORKER if value == "auto" else value


class TaskBlock(_Model):
    """A contiguous block of a pod's envs that all run one task for one stage.

    ``stage_id`` is the stage the block's envs serve; ``None``: the stage of the pod's
    assignment (a pod of the ``pods`` layout holds one stage, so its blocks leave it unset).
    """

    task_id: str
    env_start: int = Field(ge=0)
    num_envs: int = Field(ge=0)
    stage_id: int | None = Field(None, ge=0)


class EnvSettings(_Model):
    """How envs are built and served, set once in the job and carried to every pod in its
    assignment: the fields :class:`JobSpec` and :class:`Assignment` share."""

    engine: EngineName = Field("cpu", description=ENGINE_DOC)
    camera: CameraConfig = CameraConfig()
    render: RenderPreset | None = Field(None, description=RENDER_DOC)
    seed: int = 0
    envs_per_worker: int = Field(AUTO_ENVS_PER_WORKER, ge=0, le=256, description=ENVS_PER_WORKER_DOC)
    max_episode_steps: int | None = Field(None, ge=1, description=MAX_EPISODE_STEPS_DOC)
    libero: LiberoProtocol = LiberoProtocol()
    make_kwargs: dict[str, dict[str, Any]] = Field(default_factory=dict, description=MAKE_KWARGS_DOC)

    _auto_envs_per_worker = field_validator("envs_per_worker", mode="before")(_auto_to_zero)


class Assignment(EnvSettings):
    """What the controller tells one pod to run (``PUT /v1/assignment``).

    ``stage_id`` is the pod's one stage (``pods`` layout), or ``None`` when the pod holds envs of
    several stages (``slices`` layout): then every block names its own ``stage_id``.
    """

    generation: int = Field(ge=0)
    job_id: str = "default"
    pod: str
    stage_id: int | None = Field(ge=0)
    tasks: tuple[TaskBlock, ...] = ()

    @model_validator(mode="after")
    def _blocks_have_stages(self) -> "Assignment":
        if self.stage_id is None:
            unstaged = [b.task_id for b in self.tasks if b.stage_id is None]
            if unstaged:
                raise ValueError(
                    f"tasks: block for {unstaged[0]!r} has no stage_id; an assignment without a stage_id "
                    "(the 'slices' layout) names the stage of every block"
                )
        return self

    def stage_of_block(self, block: TaskBlock) -> int | None:
        """The stage ``block``'s envs serve: its own ``stage_id``, else the assignment's."""
        return block.stage_id if block.stage_id is not None else self.stage_id

    @model_validator(mode="after")
    def _blocks_are_contiguous(self) -> "Assignment":
        expected = 0
        for block in self.tasks:
            if block.env_start != expected:
                raise ValueError(
                    f"tasks: block for {block.task_id!r} starts at env {block.env_start}, "
                    f"expected {expected} (blocks must be contiguous, in order)"
                )
            expected += block.num_envs
        return self

    @property
    def num_envs(self) -> int:
        return sum(b.num_envs for b in self.tasks)

    def same_envs(self, other: "Assignment | None") -> bool:
        """True when ``other`` would build exactly the same envs (only the generation differs)."""
        if other is None:
            return False
        return self.model_dump(exclude={"generation"}) == other.model_dump(exclude={"generation"})


class JobSpec(EnvSettings):
    """The desired job (``PUT /v1/job``): what to simulate, over how many stages and pods."""

    job_id: str = "default"
    suite: str | None = None
    tasks: tuple[str, ...] = ()
    group_size: int = Field(4, ge=0, description="envs per task per stage")
    num_stages: int = Field(2, ge=1)
    pods_per_stage: int = Field(
        1,
        ge=1,
        description=(
            "'pods' layout: the pods of each stage (num_stages x pods_per_stage pods in all); "
            "'slices' layout: the job's pods, each holding every stage's share of its tasks"
        ),
    )
    stage_layout: StageLayout = Field("pods", description=STAGE_LAYOUT_DOC)

    @model_validator(mode="after")
    def _suite_or_tasks(self) -> "JobSpec":
        if self.suite is None and not self.tasks:
            raise ValueError("give either 'suite' or a non-empty 'tasks' list")
        if len(set(self.tasks)) != len(self.tasks):
            raise ValueError(f"tasks: duplicate task ids in {list(self.tasks)}")
        return self

    @property
    def pods_needed(self) -> int:
        """The pods that hold the job's envs (its slots): ``pods_per_stage`` in the ``slices``
        layout, ``num_stages x pods_per_stage`` in the ``pods`` layout."""
        if self.stage_layout == "slices":
            return self.pods_per_stage
        return self.num_stages * self.pods_per_stage


class PodCapacity(_Model):
    max_envs: int = Field(64, ge=0)
    gpu: bool = False


class PodRegistration(_Model):
    """``POST /v1/pods``: a pod says who it is and where it is reached."""

    # ``name``, the old spelling, is accepted for this release only (a pod from an older checkout
    # registering); both together are refused. docs/api.md says so.
    pod: str = Field(
        min_length=1, max_length=63, pattern=POD_NAME_PATTERN, validation_alias=AliasChoices("pod", "name")
    )
    url: str
    capacity: PodCapacity = PodCapacity()


class PodRecord(_Model):
    """A registered pod as the controller's ``GET /v1/pods`` lists it."""

    pod: str
    url: str
    capacity: PodCapacity = PodCapacity()
    stage_id: int | None = None
    ready: bool = False
    generation: int | None = None
    last_seen: float = 0.0


class RoutedPod(_Model):
    pod: str
    url: str
    num_envs: int
    tasks: tuple[TaskBlock, ...]


class RoutedStage(_Model):
    stage_id: int
    pods: tuple[RoutedPod, ...]

    @property
    def num_envs(self) -> int:
        return sum(p.num_envs for p in self.pods)


class RoutingTable(_Model):
    generation: int
    job_id: str
    ready: bool
    stages: tuple[RoutedStage, ...]

    @property
    def num_envs(self) -> int:
        return sum(s.num_envs for s in self.stages)


# One CPU list in ``taskset -c`` syntax: "3", "0-3", "0,2,4-7".
_CPU_LIST = re.compile(r"^\d+(-\d+)?(,\d+(-\d+)?)*$")


def parse_cpu_list(text: str) -> set[int]:
    """Return the CPUs a ``taskset -c`` list names ("0-3,8" -> {0, 1, 2, 3, 8}).

    Raises:
        ValueError: not such a list, or a range that runs backwards.
    """
    if not _CPU_LIST.match(text):
        raise ValueError(f"{text!r} is not a CPU list like '3', '0-3' or '0,2,4-7'")
    cpus: set[int] = set()
    for part in text.split(","):
        first, _, last = part.partition("-")
        low, high = int(first), int(last or first)
        if high < low:
            raise ValueError(f"{text!r}: the range {part!r} runs backwards")
        cpus.update(range(low, high + 1))
    return cpus


class PodsConfig(_Model):
    replicas: int = Field(2, ge=0)
    host: str = "127.0.0.1"
    base_port: int = Field(8100, ge=1024, le=65000)
    max_envs: int = Field(64, ge=0)
    cpu_affinity: Literal["auto", "off"] | tuple[str, ...] = Field(
        "auto",
        description=(
            "how pods share the machine's CPUs, as CPU limits share a Kubernetes node: 'auto' gives "
            "each pod (its env workers too) an equal share of the machine's CPUs (its cpuset; more pods "
            "than CPUs: one CPU each, in turn); CPU lists (taskset -c syntax) pin pod i to "
            "cpu_affinity[i % len]; 'off' or an empty list leaves pods unpinned"
        ),
    )

    render_gpus: tuple[Annotated[int, Field(ge=0)], ...] = Field(
        (),
        description=(
            "GPUs (EGL device indices) pods render on: pod i renders on render_gpus[i % len] "
            "(MUJOCO_EGL_DEVICE_ID), so cameras can stay off the GPU a local trainer's policy uses; "
            "an mjwarp pod runs on the CUDA device of that number (VECSIM_MJWARP_GPU); "
            "empty: the default device. Kubernetes gives each pod its own GPU instead"
        ),
    )

    @field_validator("cpu_affinity")
    @classmethod
    def _cpu_lists(cls, lists: str | tuple[str, ...]) -> str | tuple[str, ...]:
        for text in () if isinstance(lists, str) else lists:
            parse_cpu_list(text)
        return lists

    def cpus_of(self, ordinal: int, usable: Collection[int]) -> list[int] | None:
        """Return the CPUs pod ``ordinal`` runs on, or None when pods are not pinned.

        ``usable``: the CPUs the pods may share (the machine's cpuset), which ``auto``
        splits into ``replicas`` contiguous shares of equal size (the first ones one CPU larger
        when they do not divide); with more pods than CPUs, pod ``i`` gets CPU ``i % len``.
        """
        if self.cpu_affinity == "off" or not self.cpu_affinity:
            return None
        if self.cpu_affinity != "auto":
            return sorted(parse_cpu_list(self.cpu_affinity[ordinal % len(self.cpu_affinity)]))
        cpus = sorted(usable)
        if self.replicas >= len(cpus):
            return [cpus[ordinal % len(cpus)]]
        size, larger = divmod(len(cpus), self.replicas)
        start = ordinal * size + min(ordinal, larger)
        return cpus[start : start + size + (ordinal < larger)]

    def render_gpu_of(self, ordinal: int) -> int | None:
        """Return the EGL device pod ``ordinal`` renders on, or None for the default device."""
        return self.render_gpus[ordinal % len(self.render_gpus)] if self.render_gpus else None


class HeartbeatConfig(_Model):
    """The heartbeat interval, which a pod and its controller must agree on: the one setting every
    server's settings share with the job file's ``controller`` section."""

    heartbeat_interval_s: float = Field(
        1.0, gt=0, description="seconds between a pod's heartbeats: the pod sends them so, the controller expects so"
    )


class ControllerConfig(HeartbeatConfig):
    """The job file's ``controller`` section: where the controller listens and how it keeps time.
    ``service.controller.settings.ControllerSettings`` extends it, so each field is declared here
    only; a port below 1024 is the operating system's to allow or refuse."""

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=1, le=65535)
    heartbeat_ttl_s: float = Field(5.0, gt=0, description="a pod not heard from for this long is dropped")
    reconcile_interval_s: float = Field(0.5, gt=0, description="seconds between two reconcile passes")


class JobConfig(_Model):
    """A whole local job: the YAML that ``vecsim up -c`` and ``configs/*.yaml`` hold."""

    job: JobSpec
    pods: PodsConfig = PodsConfig()
    controller: ControllerConfig = ControllerConfig()


class ConfigError(ValueError):
    """A config file that cannot be used; the message names the file and the field."""


def load_job_config(path: str | Path) -> JobConfig:
    """Read a job config YAML into a :class:`JobConfig`.

    Raises:
        ConfigError: the file is missing, is not YAML, or a field is wrong (named in the message).
    """
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc}") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping with a 'job' key, got {type(raw).__name__}")
    try:
        return JobConfig.model_validate(raw)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in err['loc']) or '<root>'}: {err['msg']}" for err in exc.errors()
        )
        raise ConfigError(f"{path}: {problems}") from exc
