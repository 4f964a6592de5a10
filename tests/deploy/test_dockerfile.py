"""The Dockerfile's text: a Debian base the offline build can make, torch's CPU build, a non-root
user, the README's install script, the ``vecsim`` console script as entrypoint, a health check,
EGL, and a build context that holds everything it copies; and the mjwarp engine's image, a later
target built on the CPU image. tests/deploy/test_image.py and tests/deploy/test_image_mjwarp.py
build the images from this same file and run them."""

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


def stages() -> dict[str | None, list[Instruction]]:
    """Each build stage's instructions, its FROM first, by the stage's name (``FROM x AS name``;
    None for an unnamed one). Insertion order is the file's."""
    found: dict[str | None, list[Instruction]] = {}
    for instruction in INSTRUCTIONS:
        if instruction.keyword == "FROM":
            words = instruction.value.split()
            current: list[Instruction] = []
            found[words[2] if len(words) == 3 and words[1].upper() == "AS" else None] = current
        current.append(instruction)
    return found


def image(target: str | None) -> list[Instruction]:
    """The instructions that make the image of ``target`` (None: the default, the last stage):
    the stages it builds on, from the base image's, then its own."""
    by_name = stages()
    own = by_name[target] if target is not None else list(by_name.values())[-1]
    base = own[0].value.split()[0]
    return (image(base) if base in by_name else []) + own


def only(keyword: str, target: str | None = "cpu") -> list[Instruction]:
    return [i for i in image(target) if i.keyword == keyword]


def env(target: str | None = "cpu") -> dict[str, str]:
    """Variables ENV sets in ``target``'s image (``KEY=value`` form), later ones winning, with
    ``$NAME`` expanded as Docker does: from what earlier instructions set."""
    values: dict[str, str] = {}
    for instruction in only("ENV", target):
        before = dict(values)
        for part in shlex.split(instruction.value):
            key, _, value = part.partition("=")
            values[key] = re.sub(r"\$(\w+)", lambda m: before.get(m.group(1), m.group(0)), value)
    return values


def test_base_image_is_a_debian_slim_release_the_offline_build_can_make() -> None:
    (base,) = only("FROM")
    # Every stage that starts from an image (not from another stage) starts from this one.
    assert {i[0].value.split()[0] for i in stages().values()} - set(stages()) == {base.value.split()[0]}
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
    copies = [i for i in INSTRUCTIONS if i.keyword == "COPY" and "--from=" not in i.value]
    sources = [s for i in copies for s in i.exec_form()[:-1]]
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


def test_the_image_installs_the_pod_extra_and_no_video_or_test_packages() -> None:
    import tomllib

    runs = [i.value for i in only("RUN") if "scripts/setup.sh" in i.value]
    assert runs and all("VECSIM_EXTRAS=pod " in run for run in runs)
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    pod = project["optional-dependencies"]["pod"] + project["dependencies"]
    names = {re.split(r"[\[<>=!~ ]", requirement, maxsplit=1)[0].lower() for requirement in pod}
    # matplotlib is there: LIBERO's env module imports it (test_image.py builds a LIBERO env).
    assert not names & {"imageio", "imageio-ffmpeg", "pytest", "vecsim"}
    # The trainer's install (the base) has no simulator and no torch.
    base = {re.split(r"[\[<>=!~ ]", r, maxsplit=1)[0].lower() for r in project["dependencies"]}
    assert not base & {"mujoco", "robosuite", "torch", "fastapi", "uvicorn", "libero"}


# -- the mjwarp engine's image -------------------------------------------------------------------


def test_the_default_target_is_the_cpu_image() -> None:
    # `docker build .` without --target builds the last stage: nothing but the CPU image.
    last = list(stages().values())[-1]
    assert [i.keyword for i in last] == ["FROM"] and last[0].value == "cpu"


def test_the_mjwarp_image_is_built_on_the_cpu_image() -> None:
    assert stages()["mjwarp"][0].value.split()[0] == "cpu"
    # ... so the pod's user, entrypoint, command and health check are the CPU image's.
    for keyword in ("USER", "ENTRYPOINT", "CMD", "HEALTHCHECK"):
        assert only(keyword, "mjwarp") == only(keyword, "cpu"), keyword


def test_the_mjwarp_packages_are_installed_from_pyproject_alone() -> None:
    # A stage of their own, copying nothing but what decides the dependencies: a change to the
    # source does not install them again.
    packages = stages()["mjwarp-packages"]
    copied = [s for i in packages if i.keyword == "COPY" for s in i.exec_form()[:-1]]
    assert sorted(copied) == ["README.md", "pyproject.toml"]
    (install,) = [i.value for i in packages if i.keyword == "RUN" and "pip install" in i.value]
    assert '"/app[mjwarp]"' in install and "torch" not in install
    copies = [i.value for i in stages()["mjwarp"] if i.keyword == "COPY"]
    venv = env("mjwarp")["VECSIM_MJWARP_VENV"]
    assert copies == [f"--from=mjwarp-packages --chown=10001:10001 {venv} {venv}"]


def test_the_mjwarp_image_runs_the_pod_from_the_mjwarp_venv() -> None:
    variables = env("mjwarp")
    assert variables["PATH"].split(":")[:2] == [
        f"{variables['VECSIM_MJWARP_VENV']}/bin",
        f"{variables['VECSIM_VENV']}/bin",
    ]


def test_the_mjwarp_image_exports_its_scenes_with_the_cpu_venv_where_the_engine_reads_them() -> None:
    from vecsim.engine.mjwarp.scene import ROOT_ENV

    (export,) = [i.value for i in only("RUN", "mjwarp") if "vecsim.engine.mjwarp.scene" in i.value]
    assert '"$VECSIM_VENV/bin/python" -m vecsim.engine.mjwarp.scene $MJWARP_TASKS' in export
    assert f'--root "${ROOT_ENV}"' in export and ROOT_ENV in env("mjwarp")
    args = dict(i.value.split("=", 1) for i in only("ARG", "mjwarp") if "=" in i.value)
    assert "libero_10/0" in args["MJWARP_TASKS"].strip('"').split()


def test_warps_kernel_cache_is_under_the_cache_the_manifests_mount_writable() -> None:
    variables = env("mjwarp")
    assert variables["WARP_CACHE_PATH"].startswith(variables["XDG_CACHE_HOME"] + "/")


def test_the_offline_build_builds_either_target_under_an_engine_named_tag() -> None:
    script = (ROOT / "scripts" / "build_image.sh").read_text()
    assert '--target "$engine"' in script
    for target, tag in (("cpu", "vecsim:$version"), ("mjwarp", "vecsim-mjwarp:$version")):
        assert target in stages() and f'{target}) tag="${{1:-{tag}}}"' in script
