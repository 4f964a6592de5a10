"""The Dockerfile's text: a Debian base the offline build can make, torch's CPU build, a non-root
user, the README's install script, the ``vecsim`` console script as entrypoint, a health check,
EGL, and a build context that holds everything it copies. tests/deploy/test_image.py builds the image
from this same file and runs it."""

from __future__ import annotations

import fnmatch
import importlib
import json
import re
import shlex
import tomllib
from dataclasses import dataclass

import yaml
from support import ROOT


@dataclass(frozen=True)
class Instruction:
    keyword: str
    value: str

    def exec_form(self) -> list[str]:
        """The arguments of an exec-form instruction (``CMD ["a", "b"]``); shell form is split."""
        text = re.sub(r"^(--\S+\s+)*", "", self.value)
        return json.loads(text) if text.startswith("[") else shlex.split(text)


def parse_dockerfile(text: str) -> list[Instruction]:
    """Instructions in order, continuation lines joined and comment lines dropped, as Docker does."""
    instructions: list[Instruction] = []
    pending = ""
    for line in text.splitlines():
        if line.lstrip().startswith("#") or not line.strip():
            continue
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        keyword, _, value = (pending + line).strip().partition(" ")
        instructions.append(Instruction(keyword.upper(), " ".join(value.split())))
        pending = ""
    assert not pending, "Dockerfile ends in a continuation line"
    return instructions


INSTRUCTIONS = parse_dockerfile((ROOT / "Dockerfile").read_text())


def only(keyword: str) -> list[Instruction]:
    return [i for i in INSTRUCTIONS if i.keyword == keyword]


def env() -> dict[str, str]:
    """Variables ENV sets (``KEY=value`` form), later ones winning."""
    values: dict[str, str] = {}
    for instruction in only("ENV"):
        values.update(part.split("=", 1) for part in shlex.split(instruction.value))
    return values


def test_base_image_is_a_debian_slim_release_the_offline_build_can_make() -> None:
    (base,) = only("FROM")
    image = base.value.split()[0]
    name, _, tag = image.rpartition(":")
    assert name == "debian" and tag.endswith("-slim") and tag != "latest", image
    # scripts/build_image.sh makes exactly this base with debootstrap (the suite is the tag's
    # release name) and refuses any other.
    assert "debian:*-slim)" in (ROOT / "scripts" / "build_image.sh").read_text()


def test_torch_comes_from_the_cpu_source_before_setup_pins_it() -> None:
    args = dict(i.value.split("=", 1) for i in only("ARG") if "=" in i.value)
    assert args["TORCH_INDEX_URL"] == "https://download.pytorch.org/whl/cpu"
    runs = [i.value for i in only("RUN")]
    torch_run = next(n for n, run in enumerate(runs) if "TORCH_INDEX_URL" in run)
    setup_run = next(n for n, run in enumerate(runs) if "scripts/setup.sh" in run)
    assert torch_run < setup_run
    assert '"torch==2.13.0"' in runs[torch_run] and "torch is a CUDA build" in runs[torch_run]
    assert 'install -q "torch==2.13.0"' in (ROOT / "scripts" / "setup.sh").read_text()


def test_image_runs_as_a_non_root_numeric_user() -> None:
    user = only("USER")[-1].value.split(":")[0]
    assert user.isdigit() and int(user) != 0


def test_image_user_is_the_one_the_manifests_run_as() -> None:
    uid = int(only("USER")[-1].value.split(":")[0])
    for path in (ROOT / "k8s" / "base").glob("*.yaml"):
        doc = yaml.safe_load(path.read_text())
        if doc.get("kind") in ("StatefulSet", "Deployment"):
            assert doc["spec"]["template"]["spec"]["securityContext"]["runAsUser"] == uid, path.name


def test_install_runs_the_readmes_setup_script() -> None:
    runs = [i.value for i in only("RUN")]
    assert any(re.search(r"(^|\s)scripts/setup\.sh(\s|$)", run) for run in runs)
    # The README's test command is scripts/test.sh, which installs through the same script, so
    # CI exercises the image's install steps.
    assert "scripts/test.sh" in (ROOT / "README.md").read_text()
    assert "scripts/setup.sh" in (ROOT / "scripts" / "test.sh").read_text()


def test_setup_script_installs_into_the_venv_on_the_path() -> None:
    variables = env()
    assert variables["PATH"].split(":")[0] == f"{variables['VECSIM_VENV']}/bin"
    assert "VECSIM_VENV" in (ROOT / "scripts" / "setup.sh").read_text()


def test_setup_runs_python_3_11() -> None:
    assert env()["PYTHON"] == "python3.11"
    assert re.search(r"python3\.11-venv\b", " ".join(i.value for i in only("RUN")))


def test_entrypoint_is_the_vecsim_console_script() -> None:
    entrypoint = only("ENTRYPOINT")[-1].exec_form()
    assert entrypoint[-1] == "vecsim"
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    module_name, _, func_name = scripts["vecsim"].partition(":")
    assert callable(getattr(importlib.import_module(module_name), func_name))


def test_default_command_is_a_sim_pod() -> None:
    from service.cli import COMMANDS

    command = only("CMD")[-1].exec_form()
    assert command == ["pod"]
    assert command[0] in COMMANDS


def test_healthcheck_asks_the_liveness_endpoint() -> None:
    (healthcheck,) = only("HEALTHCHECK")
    assert "/healthz" in healthcheck.value
    assert re.search(r"--timeout=\d+s", healthcheck.value)


def test_mujoco_renders_through_egl() -> None:
    variables = env()
    assert variables["MUJOCO_GL"] == "egl"
    assert set(variables["NVIDIA_DRIVER_CAPABILITIES"].split(",")) >= {"compute", "utility", "graphics"}
    assert "libegl1" in " ".join(i.value for i in only("RUN"))


def _ignored(path: str, patterns: list[str]) -> bool:
    """Whether .dockerignore excludes ``path`` (the last matching pattern wins; ``!`` re-includes)."""
    ignored = False
    parts = path.split("/")
    for pattern in patterns:
        negate = pattern.startswith("!")
        pattern = pattern.lstrip("!").rstrip("/")
        prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
        if any(fnmatch.fnmatch(prefix, pattern) for prefix in prefixes):
            ignored = not negate
    return ignored


def test_build_context_holds_everything_the_dockerfile_copies() -> None:
    patterns = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    sources = [s for i in only("COPY") for s in i.exec_form()[:-1]]
    assert sources
    for source in sources:
        assert (ROOT / source).exists(), f"COPY {source}: not in the repository"
        assert not _ignored(source.rstrip("/"), patterns), f"COPY {source}: excluded by .dockerignore"


def test_build_context_leaves_out_git_and_tests() -> None:
    patterns = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    for path in (".git", "tests", "k8s", ".venv"):
        assert _ignored(path, patterns), path


def test_the_image_installs_the_pod_extra_and_no_plotting_or_video_packages() -> None:
    import tomllib

    runs = [i.value for i in only("RUN") if "scripts/setup.sh" in i.value]
    assert runs and all("VECSIM_EXTRAS=pod " in run for run in runs)
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    pod = project["optional-dependencies"]["pod"] + project["dependencies"]
    names = {re.split(r"[\[<>=!~ ]", requirement, maxsplit=1)[0].lower() for requirement in pod}
    assert not names & {"matplotlib", "imageio", "imageio-ffmpeg", "pytest", "vecsim"}
    # The trainer's install (the base) has no simulator and no torch.
    base = {re.split(r"[\[<>=!~ ]", r, maxsplit=1)[0].lower() for r in project["dependencies"]}
    assert not base & {"mujoco", "robosuite", "torch", "fastapi", "uvicorn", "libero"}
