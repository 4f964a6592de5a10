"""The ``mjwarp`` engine's settings (``vecsim.engine.mjwarp.settings``), in the CPU stack (no warp).

- Unset, each variable keeps the default the engine always had; every value the engine took
  before keeps its meaning (a ``1``/``0`` flag, an ``int()``/``float()`` number, ``off`` or
  empty for no GPU turns).
- A malformed value of any variable is refused naming the variable and the value; several at
  once are all named.
- An engine reads them when it is built, not when its module is imported: a valid value reaches
  the engine, and a malformed one fails a real pod's build, which ``/readyz`` then says.
"""

from __future__ import annotations

import httpx
import pytest
from support.service_procs import RunningPod, assignment, running, wait_until

from vecsim.config import Assignment
from vecsim.engine.errors import SimBuildError
from vecsim.engine.mjwarp.engine import MjwarpEngine, use_device
from vecsim.engine.mjwarp.settings import DEFAULT_TURNS_DIR, ENV_VARS, TURNS_ENV, MjwarpSettings
from vecsim.envsettings import SettingsError

NCONMAX, NJMAX = "VECSIM_MJWARP_NCONMAX", "VECSIM_MJWARP_NJMAX"
DETERMINISTIC, ALLOW_CPU = "VECSIM_MJWARP_DETERMINISTIC", "VECSIM_MJWARP_ALLOW_CPU"
TURN_WAIT_S = "VECSIM_MJWARP_TURN_WAIT_S"
GPU = "VECSIM_MJWARP_GPU"
MALFORMED = [
    (NCONMAX, "lots"),
    (NCONMAX, "0"),
    (NCONMAX, "9.5"),
    (NJMAX, "-600"),
    (NJMAX, "600 rows"),
    (DETERMINISTIC, "true"),
    (DETERMINISTIC, "2"),
    (ALLOW_CPU, "yes"),
    (ALLOW_CPU, " 1"),
    (TURN_WAIT_S, "2 min"),
    (TURN_WAIT_S, "0"),
    (TURN_WAIT_S, "nan"),
    (GPU, "-1"),
    (GPU, "cuda:1"),
    (GPU, "0,1"),
]


def _spare() -> Assignment:
    """An mjwarp assignment of no envs: an engine of it reads its settings and needs no warp."""
    return assignment("sim-mjwarp", [], engine="mjwarp")


def test_the_variables_are_the_engines_and_each_names_a_field() -> None:
    assert set(ENV_VARS) == {NCONMAX, NJMAX, DETERMINISTIC, ALLOW_CPU, GPU, TURNS_ENV, TURN_WAIT_S}
    assert set(ENV_VARS.values()) == set(MjwarpSettings.model_fields)


def test_unset_or_empty_variables_keep_the_engines_defaults() -> None:
    for environ in ({}, {name: "" for name in ENV_VARS if name != TURNS_ENV}):
        settings = MjwarpSettings.from_env(environ)
        assert (settings.nconmax, settings.njmax) == (96, 600)
        assert settings.deterministic is False and settings.allow_cpu is False
        assert settings.turns_dir == DEFAULT_TURNS_DIR == "/dev/shm/vecsim-turns"
        assert settings.turn_wait_s == 120.0
        assert settings.gpu is None  # warp's default device


@pytest.mark.parametrize(
    ("name", "value", "field", "meaning"),
    [
        (NCONMAX, "128", "nconmax", 128),
        (NJMAX, " 104 ", "njmax", 104),  # as int() read it
        (NJMAX, "1_000", "njmax", 1000),
        (DETERMINISTIC, "1", "deterministic", True),
        (DETERMINISTIC, "0", "deterministic", False),
        (ALLOW_CPU, "1", "allow_cpu", True),
        (ALLOW_CPU, "0", "allow_cpu", False),
        (TURN_WAIT_S, "2.5", "turn_wait_s", 2.5),
        (GPU, "0", "gpu", 0),
        (GPU, "3", "gpu", 3),
        (TURN_WAIT_S, "inf", "turn_wait_s", float("inf")),  # wait for the turn however long it takes
        (TURNS_ENV, "/tmp/turns", "turns_dir", "/tmp/turns"),
        (TURNS_ENV, "off", "turns_dir", None),
        (TURNS_ENV, "", "turns_dir", None),  # empty: no turns, as before (not the default folder)
    ],
)
def test_a_value_the_engine_took_before_keeps_its_meaning(name: str, value: str, field: str, meaning: object) -> None:
    assert getattr(MjwarpSettings.from_env({name: value}), field) == meaning


@pytest.mark.parametrize(("name", "value"), MALFORMED)
def test_a_malformed_value_is_refused_naming_the_variable_and_the_value(name: str, value: str) -> None:
    with pytest.raises(SettingsError) as refused:
        MjwarpSettings.from_env({name: value})
    assert f"environment variable {name} is {value!r}" in str(refused.value)


def test_every_malformed_variable_of_an_environment_is_named_at_once() -> None:
    with pytest.raises(SettingsError) as refused:
        MjwarpSettings.from_env({NJMAX: "0", DETERMINISTIC: "on", TURN_WAIT_S: "-1"})
    message = str(refused.value)
    assert all(name in message for name in (NJMAX, DETERMINISTIC, TURN_WAIT_S)), message
    assert NCONMAX not in message


def test_an_engine_reads_its_settings_when_it_is_built(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(NJMAX, "104")
    monkeypatch.setenv(DETERMINISTIC, "1")
    monkeypatch.setenv(TURNS_ENV, "off")
    with MjwarpEngine(_spare()) as engine:
        assert engine.settings == MjwarpSettings(njmax=104, deterministic=True, turns="off")
    monkeypatch.setenv(NJMAX, "none")
    with pytest.raises(SimBuildError, match=f"mjwarp: environment variable {NJMAX} is 'none'"):
        MjwarpEngine(_spare())


@pytest.mark.parametrize("allow_cpu", [False, True])
def test_a_gpu_warp_does_not_see_fails_the_build_naming_it(allow_cpu: bool) -> None:
    """The device an engine builds on (``use_device``, before any world): a GPU named where warp
    sees none (this machine) fails, saying why, even where the CPU device is allowed; where warp
    sees GPUs, one past the last is named with their count."""
    import warp as wp

    settings = MjwarpSettings.from_env({GPU: "7", ALLOW_CPU: str(int(allow_cpu))})
    if wp.is_cuda_available():
        expected = f"{GPU} is '7': warp sees {wp.get_cuda_device_count()} CUDA GPU"
    else:
        expected = "the engine runs on a CUDA GPU and warp found none"
    with pytest.raises(SimBuildError, match=expected):
        use_device(settings)


@pytest.mark.timeout(120)
def test_a_pod_with_a_malformed_setting_fails_its_build_and_readyz_says_which(tmp_path) -> None:
    def failed() -> str:
        answer = httpx.get(f"{pod.url}/readyz", timeout=5)
        detail = answer.json().get("detail", "") if answer.status_code == 503 else ""
        return detail if "failed" in detail else ""

    pod = RunningPod(_spare(), tmp_path, env={TURN_WAIT_S: "2 min"})
    with running(pod):
        detail = wait_until(failed, "the build to fail", timeout_s=60)
    assert f"environment variable {TURN_WAIT_S} is '2 min'" in detail, detail
