# syntax=docker/dockerfile:1
# The pod images, one per engine. Build from the repository root:
#   docker build -t vecsim:0.1.0 .                          the CPU image (the default target)
#   docker build --target mjwarp -t vecsim-mjwarp:0.1.0 .   the mjwarp engine's image
# or, on a machine without a registry, scripts/build_image.sh [--engine mjwarp] (makes the base
# with debootstrap, then builds this same file with buildah). The tag is the version in
# pyproject.toml; the Kubernetes manifests pin it.
#
# The CPU image serves sim pods and the controller: `vecsim pod` (the default command) or
# `vecsim controller --config ...`.
FROM debian:bookworm-slim AS cpu

ARG DEBIAN_FRONTEND=noninteractive
# Where the CPU build of torch comes from. PyPI's torch for Linux is the CUDA build (GBs the pod
# never uses: it renders through EGL and runs torch only for LIBERO's init states), so torch is
# installed from here first and setup.sh finds its pin already met. An offline build points
# TORCH_FIND_LINKS at a mounted directory holding the wheel instead (scripts/build_image.sh).
ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu
ARG TORCH_FIND_LINKS=

# Debian's Python 3.11 (the project's Python). EGL goes through libglvnd: on GPU nodes the
# container runtime mounts NVIDIA's EGL library (NVIDIA_DRIVER_CAPABILITIES includes graphics) and
# the vendor file below points at it; on CPU nodes Mesa's software EGL answers instead. OpenCV
# (robosuite's) loads libGL and GLib. tini reaps the sim worker processes.
RUN apt-get update \
 && apt-get install -y --no-install-recommends \
      ca-certificates python3.11 python3.11-venv \
      libglvnd0 libegl1 libgl1 libgles2 libopengl0 libegl-mesa0 libgl1-mesa-dri libglib2.0-0 \
      tini \
 && rm -rf /var/lib/apt/lists/* \
 && mkdir -p /usr/share/glvnd/egl_vendor.d \
 && printf '{"file_format_version": "1.0.0", "ICD": {"library_path": "libEGL_nvidia.so.0"}}\n' \
      > /usr/share/glvnd/egl_vendor.d/10_nvidia.json

# A fixed numeric uid, so that Kubernetes' runAsNonRoot can check it without a passwd lookup.
RUN groupadd --gid 10001 vecsim \
 && useradd --uid 10001 --gid 10001 --create-home --home-dir /home/vecsim --shell /usr/sbin/nologin vecsim \
 && mkdir -p /opt/vecsim /app /home/vecsim/.cache \
 && chown 10001:10001 /opt/vecsim /app /home/vecsim/.cache

ENV HOME=/home/vecsim \
    VECSIM_VENV=/opt/vecsim/venv \
    PYTHON=python3.11 \
    PATH=/opt/vecsim/venv/bin:$PATH \
    XDG_CACHE_HOME=/home/vecsim/.cache \
    MPLCONFIGDIR=/tmp/matplotlib \
    MUJOCO_GL=egl \
    PYOPENGL_PLATFORM=egl \
    NVIDIA_DRIVER_CAPABILITIES=compute,utility,graphics \
    VECSIM_HOST=0.0.0.0 \
    PYTHONUNBUFFERED=1

USER 10001:10001
WORKDIR /app

# torch's CPU build alone (its own dependencies come from PyPI through setup.sh's pin below).
RUN --mount=type=cache,target=/home/vecsim/.cache/pip,uid=10001,gid=10001 \
    python3.11 -m venv "$VECSIM_VENV" \
 && if [ -n "$TORCH_FIND_LINKS" ]; then source="--no-index --find-links $TORCH_FIND_LINKS"; \
    else source="--index-url $TORCH_INDEX_URL"; fi \
 && "$VECSIM_VENV/bin/pip" install --no-deps $source "torch==2.13.0" \
 && "$VECSIM_VENV/bin/python" -c "import importlib.metadata as m, sys; cuda = [r for r in m.requires('torch') or [] if r.startswith('nvidia-')]; sys.exit(f'torch is a CUDA build: it needs {cuda}' if cuda else 0)"

# The README's install, step for step: a venv at $VECSIM_VENV with the pod's pinned dependencies
# (the `pod` extra: no video or test packages), LIBERO --no-deps and its assets, and
# the link to them. It runs twice: first with only what decides the dependencies (so this slow
# layer is rebuilt only when they change), then with the source, when it finds every dependency
# in place and only points the editable install at the packages. The pip cache survives builds.
COPY --chown=10001:10001 pyproject.toml README.md ./
COPY --chown=10001:10001 scripts/setup.sh scripts/
RUN --mount=type=cache,target=/home/vecsim/.cache/pip,uid=10001,gid=10001 VECSIM_EXTRAS=pod scripts/setup.sh
COPY --chown=10001:10001 vecsim/ vecsim/
COPY --chown=10001:10001 service/ service/
COPY --chown=10001:10001 configs/ configs/
RUN --mount=type=cache,target=/home/vecsim/.cache/pip,uid=10001,gid=10001 VECSIM_EXTRAS=pod scripts/setup.sh

# Bytecode for the project's own modules now: the running container's root is read-only.
# (vecsim writes its caches, LIBERO's config among them, under $HOME/.cache, a volume at run time.)
RUN python -m compileall -q vecsim service

EXPOSE 8100 8000

# Liveness of whichever server runs: set VECSIM_PORT to the controller's port when running it.
HEALTHCHECK --interval=30s --timeout=5s --start-period=60s --retries=3 \
  CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:' + os.environ.get('VECSIM_PORT', '8100') + '/healthz', timeout=4)"]

ENTRYPOINT ["tini", "--", "vecsim"]
CMD ["pod"]

# The mjwarp engine's packages (docs/mjwarp.md): MuJoCo Warp needs mujoco 4, which the CPU venv's
# robosuite and LIBERO exclude, so they get a venv of their own. It is installed in a stage of its
# own, from pyproject.toml alone (the editable install finds no source yet, as setup.sh's first
# run does), so that a change to the source does not install them again.
FROM debian:bookworm-slim AS mjwarp-packages
ARG DEBIAN_FRONTEND=noninteractive
RUN apt-get update \
 && apt-get install -y --no-install-recommends ca-certificates python3.11 python3.11-venv \
 && rm -rf /var/lib/apt/lists/*
COPY pyproject.toml README.md /app/
RUN --mount=type=cache,target=/root/.cache/pip \
    python3.11 -m venv /opt/vecsim/mjwarp \
 && /opt/vecsim/mjwarp/bin/pip install -e "/app[mjwarp]"

# The mjwarp image: the CPU image (its layers reused) plus the mjwarp venv, which runs `vecsim pod`,
# and the LIBERO scenes of MJWARP_TASKS, exported at build time by the CPU venv. A job still picks
# its engine (`engine: mjwarp`). On a GPU node warp needs only the driver's libcuda.so.1, which
# the NVIDIA container runtime mounts (`compute` capability); its kernels compile on the first
# build of a pod into WARP_CACHE_PATH, on the cache volume (the root filesystem is read-only).
FROM cpu AS mjwarp
ARG MJWARP_TASKS="libero_10/0"
ENV VECSIM_MJWARP_VENV=/opt/vecsim/mjwarp \
    VECSIM_MJWARP_SCENES=/opt/vecsim/mjwarp-scenes \
    WARP_CACHE_PATH=/home/vecsim/.cache/warp
COPY --from=mjwarp-packages --chown=10001:10001 /opt/vecsim/mjwarp /opt/vecsim/mjwarp
RUN --mount=type=cache,target=/home/vecsim/.cache/pip,uid=10001,gid=10001 \
    "$VECSIM_MJWARP_VENV/bin/pip" install --no-deps -e /app
# The export needs the CPU stack alone (its index tables are read without warp). What else it
# writes (LIBERO's config, init states, Mesa's and matplotlib's caches, robosuite's log) goes.
RUN cache="$(mktemp -d)" \
 && VECSIM_CACHE_DIR="$cache" XDG_CACHE_HOME="$cache" MPLCONFIGDIR="$cache/matplotlib" \
    "$VECSIM_VENV/bin/python" -m vecsim.engine.mjwarp.scene $MJWARP_TASKS --root "$VECSIM_MJWARP_SCENES" \
 && rm -rf "$cache" /tmp/robosuite.log
ENV PATH=$VECSIM_MJWARP_VENV/bin:$PATH

# The default target (`docker build .` without --target): the CPU image.
FROM cpu
