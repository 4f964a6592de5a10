# syntax=docker/dockerfile:1
# One image for sim pods and the controller: `vecsim pod` (the default command) or
# `vecsim controller --config ...`. Build from the repository root:
#   docker build -t vecsim:0.1.0 .
# The tag is the version in pyproject.toml; the Kubernetes manifests pin it.
FROM nvidia/cuda:12.4.1-runtime-ubuntu22.04

ARG DEBIAN_FRONTEND=noninteractive

# Python 3.11 from deadsnakes (Ubuntu 22.04 itself ships only a 3.11 release candidate).
# EGL goes through libglvnd: on GPU nodes the container runtime mounts NVIDIA's EGL library
# (NVIDIA_DRIVER_CAPABILITIES includes graphics) and the vendor file below points at it; on CPU
# nodes Mesa's software EGL answers instead. tini reaps the sim worker processes.
RUN apt-get update \
 && apt-get install -y --no-install-recommends ca-certificates gnupg software-properties-common \
 && add-apt-repository -y ppa:deadsnakes/ppa \
 && apt-get update \
 && apt-get install -y --no-install-recommends \
      python3.11 python3.11-venv \
      libglvnd0 libegl1 libgl1 libgles2 libopengl0 libegl-mesa0 libgl1-mesa-dri \
      tini \
 && apt-get purge -y --auto-remove software-properties-common gnupg \
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

COPY --chown=10001:10001 pyproject.toml README.md ./
COPY --chown=10001:10001 scripts/ scripts/
COPY --chown=10001:10001 vecsim/ vecsim/
COPY --chown=10001:10001 service/ service/
COPY --chown=10001:10001 configs/ configs/

# The README's install, step for step: a venv at $VECSIM_VENV with the pod's pinned dependencies
# (the `pod` extra: no plotting, video or test packages), LIBERO --no-deps and its assets. The pip
# cache survives between builds.
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
