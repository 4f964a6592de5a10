"""Job config files wrong in each field: every entry point says which field, and starts nothing.

The same broken file goes to `vecsim.config.load_job_config`, `vecsim up -c`, `vecsim pod
--config` and `vecsim controller -c` (their `main` functions, in this process: a broken config
is refused before anything starts); one file per command also goes through the real command.
"""

from __future__ import annotations

import copy
import re
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml
from support.service_procs import clean_env, free_port, free_port_block

from service.controller.main import main as controller_main
from service.pod.main import main as pod_main
from service.runner.main import main as up_main
from vecsim.config import ConfigError, load_job_config

VALID: dict[str, Any] = {
    "job": {
        "job_id": "config-errors",
        "tasks": ["gym/Pendulum-v1"],
        "group_size": 1,
        "num_stages": 1,
        "pods_per_stage": 1,
        "camera": {"names": [], "height": 16, "width": 16},
        "render": "lean",
        "seed": 0,
        "envs_per_worker": 1,
        "max_episode_steps": 20,
        "libero": {
            "image_orientation": "rotate180",
            "settle_steps": 10,
            "fixture_seed": 0,
            "fixture_rule": "published",
        },
    },
    "pods": {"replicas": 1, "host": "127.0.0.1", "base_port": 8100, "max_envs": 4},
    "controller": {
        "host": "127.0.0.1",
        "port": 8000,
        "heartbeat_interval_s": 1.0,
        "heartbeat_ttl_s": 5.0,
        "reconcile_interval_s": 0.5,
    },
}


def wrong(field: str, value: Any, says: str, named: str | None = None) -> Any:
    """A case: set ``field`` to ``value``; the message names ``named`` (default: the field's
    dotted path) and then says ``says``."""
    return pytest.param(field, value, named or field, says, id=f"{field}={value!r}")


WRONG_FIELDS = [
    wrong("job.job_id", ["a", "list"], "valid string"),
    wrong("job.suite", 7, "valid string"),
    wrong("job.tasks", "gym/Pendulum-v1", "valid tuple"),
    # A check across the fields of `job` names `job`, then the field in its own words.
    wrong("job.tasks", ["gym/Pendulum-v1", "gym/Pendulum-v1"], "tasks: duplicate task ids", named="job"),
    wrong("job.group_size", -1, "greater than or equal to 0"),
    wrong("job.group_size", "four", "valid integer"),
    wrong("job.num_stages", 0, "greater than or equal to 1"),
    wrong("job.pods_per_stage", 0, "greater than or equal to 1"),
    wrong("job.camera", "agentview", "valid dictionary"),
    wrong("job.camera.names", ["agentview", "agentview"], "unique"),
    wrong("job.camera.height", 4, "greater than or equal to 8"),
    wrong("job.camera.width", 4096, "less than or equal to 1024"),
    wrong("job.render", "ultra", "'full', 'fast', 'lean' or 'lowpoly'"),
    wrong("job.seed", 1.5, "valid integer"),
    wrong("job.envs_per_worker", -1, "greater than or equal to 0"),
    wrong("job.envs_per_worker", 1000, "less than or equal to 256"),
    wrong("job.max_episode_steps", 0, "greater than or equal to 1"),
    wrong("job.libero.image_orientation", "flipped", "'upright', 'rotate180' or 'raw'"),
    wrong("job.libero.settle_steps", -1, "greater than or equal to 0"),
    wrong("job.libero.fixture_seed", -7, "greater than or equal to 0"),
    wrong("job.libero.fixture_rule", "lerobot", "'published' or 'first_reset'"),
    wrong("job.libero.fixture_stride", 2, "Extra inputs are not permitted"),
    wrong("pods.replicas", -1, "greater than or equal to 0"),
    wrong("pods.host", None, "valid string"),
    wrong("pods.base_port", 80, "greater than or equal to 1024"),
    wrong("pods.max_envs", -4, "greater than or equal to 0"),
    wrong("controller.host", 12, "valid string"),
    wrong("controller.port", 70000, "less than or equal to 65535"),
    wrong("controller.heartbeat_interval_s", 0, "greater than 0"),
    wrong("controller.heartbeat_ttl_s", -5, "greater than 0"),
    wrong("controller.reconcile_interval_s", "often", "valid number"),
]
# A misspelt field is an error naming it, never a silently ignored key.
MISSPELT = [
    ("job.group_sise", 2),
    ("job.libero.settle_step", 2),
    ("pods.replica", 2),
    ("controller.prot", 8000),
    ("jobs", {}),
]


def changed(config: dict[str, Any], dotted: str, value: Any) -> dict[str, Any]:
    """A copy of ``config`` with field ``dotted`` (``"job.camera.height"``) set to ``value``."""
    config = copy.deepcopy(config)
    *parents, leaf = dotted.split(".")
    node = config
    for key in parents:
        node = node[key]
    node[leaf] = value
    return config


def with_value(dotted: str, value: Any) -> dict[str, Any]:
    return changed(VALID, dotted, value)


def write(tmp_path: Path, config: Any, name: str = "job.yaml") -> Path:
    path = tmp_path / name
    path.write_text(config if isinstance(config, str) else yaml.safe_dump(config))
    return path


def refused_by_every_command(path: Path, capsys: pytest.CaptureFixture[str]) -> dict[str, str]:
    """Give ``path`` to each command's main; each must exit 2. Returns each one's stderr."""
    errors = {}
    for command, main in (("vecsim up", up_main), ("vecsim controller", controller_main)):
        assert main(["-c", str(path)]) == 2, command
        errors[command] = capsys.readouterr().err
    assert pod_main(["--config", str(path), "--port", str(free_port())]) == 2
    errors["vecsim pod"] = capsys.readouterr().err
    return errors


def test_the_valid_config_of_these_tests_loads(tmp_path):
    assert load_job_config(write(tmp_path, VALID)).job.tasks == ("gym/Pendulum-v1",)


@pytest.mark.parametrize(("field", "value", "named", "says"), WRONG_FIELDS)
def test_a_wrong_value_is_refused_naming_the_field(tmp_path, capsys, field, value, named, says):
    path = write(tmp_path, with_value(field, value))
    expected = re.compile(rf"{re.escape(named)}: .*{re.escape(says)}")
    with pytest.raises(ConfigError) as caught:
        load_job_config(path)
    assert str(caught.value).startswith(f"{path}: ") and expected.search(str(caught.value))
    for command, err in refused_by_every_command(path, capsys).items():
        assert expected.search(err), f"{command}: {err}"


@pytest.mark.parametrize(("field", "value"), MISSPELT, ids=[f for f, _ in MISSPELT])
def test_a_misspelt_field_is_refused_naming_it(tmp_path, capsys, field, value):
    path = write(tmp_path, with_value(field, value))
    with pytest.raises(ConfigError, match=rf"{field}: Extra inputs are not permitted"):
        load_job_config(path)
    for command, err in refused_by_every_command(path, capsys).items():
        assert field in err, command


@pytest.mark.parametrize(
    ("config", "says"),
    [
        ({"job": {"group_size": 2}}, "give either 'suite' or a non-empty 'tasks' list"),
        ({"pods": {"replicas": 1}}, "job: Field required"),
        ("job: [unclosed", "not valid YAML"),
        ("- just\n- a list\n", "expected a mapping with a 'job' key, got list"),
        ("", "expected a mapping with a 'job' key, got NoneType"),
    ],
    ids=["neither-suite-nor-tasks", "no-job", "not-yaml", "not-a-mapping", "empty"],
)
def test_a_file_that_is_not_a_job_config_is_refused_saying_why(tmp_path, capsys, config, says):
    path = write(tmp_path, config)
    with pytest.raises(ConfigError, match=rf"{path}: .*{says}"):
        load_job_config(path)
    for command, err in refused_by_every_command(path, capsys).items():
        assert says in err, command


def test_a_missing_file_is_refused_naming_it(tmp_path, capsys):
    path = tmp_path / "nowhere.yaml"
    with pytest.raises(ConfigError, match=rf"{path}: cannot read"):
        load_job_config(path)
    for command, err in refused_by_every_command(path, capsys).items():
        assert f"{path}: cannot read" in err, command


# -- configs valid field by field that cannot run: `vecsim up` says what to change --------------


def runnable(**changes: Any) -> dict[str, Any]:
    """VALID on free ports, with ``changes`` (dotted field -> value) applied."""
    config = changed(with_value("pods.base_port", free_port_block(2)), "controller.port", free_port())
    for field, value in changes.items():
        config = changed(config, field, value)
    return config


@pytest.mark.parametrize(
    ("changes", "says"),
    [
        ({"job.tasks": ["nope/missing"]}, "nope/missing"),
        ({"job.tasks": None, "job.suite": "no_such_suite"}, "suite: unknown suite 'no_such_suite'"),
        ({"job.tasks": ["gym/Pendulum-v1", "gym/MountainCarContinuous-v0"]}, "other observation/action spaces"),
        ({"job.group_size": 8}, "max_envs"),
        ({"job.num_stages": 2}, "pods.replicas: 1 pods cannot fill 2 stages"),
    ],
    ids=["unknown-task", "unknown-suite", "tasks-with-other-spaces", "slot-too-big", "too-few-replicas"],
)
def test_vecsim_up_refuses_a_job_that_cannot_run_saying_what_to_change(tmp_path, capsys, changes, says):
    config = runnable(**changes)
    if config["job"]["tasks"] is None:
        del config["job"]["tasks"]
    assert up_main(["-c", str(write(tmp_path, config)), "--log-dir", str(tmp_path / "logs")]) == 1
    assert says in capsys.readouterr().err
    assert not (tmp_path / "logs").exists()  # nothing was started


def test_vecsim_up_refuses_a_port_in_use_naming_the_field(tmp_path, capsys):
    config = runnable()
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", config["controller"]["port"]))
        assert up_main(["-c", str(write(tmp_path, config))]) == 1
    assert f"controller.port: port {config['controller']['port']} on 127.0.0.1 is in use" in capsys.readouterr().err


@pytest.mark.parametrize("command", [["up", "-c"], ["pod", "--config"], ["controller", "-c"]], ids=lambda c: c[0])
def test_the_real_command_exits_2_naming_the_field(tmp_path, command):
    path = write(tmp_path, with_value("job.camera.height", 4))
    result = subprocess.run(
        [sys.executable, "-m", "service.cli", *command, str(path)],
        env=clean_env(),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert "job.camera.height" in result.stderr and "greater than or equal to 8" in result.stderr
