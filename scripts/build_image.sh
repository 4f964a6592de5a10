#!/usr/bin/env bash
# Builds a pod image from the repository's Dockerfile, unchanged, on a machine without a
# registry or a Docker daemon (run as root):
#   1. makes the Dockerfile's base (`FROM debian:bookworm-slim`) with debootstrap from Debian's
#      own mirror and tags it under that name in buildah's store;
#   2. `buildah bud`s the Dockerfile's target for the engine with torch's CPU wheel taken from a
#      local directory.
# Users with a registry run `docker build [--target mjwarp] -t <tag> .` instead (docs/kubernetes.md).
#
#   scripts/build_image.sh [--engine cpu|mjwarp] [TAG]
#
#   --engine   cpu (default): the CPU image, TAG defaults to vecsim:<version in pyproject.toml>;
#              mjwarp: the mjwarp engine's image (the CPU image's layers plus its own venv and
#              scenes), TAG defaults to vecsim-mjwarp:<version>
#
# Environment:
#   VECSIM_IMAGE_CACHE   where the base's root tarball, buildah's store and the pip cache live
#                        (default ~/.cache/vecsim/image); reruns reuse them, a fresh one still works
#   VECSIM_TORCH_WHEELS  a directory holding torch's CPU wheel (torch-2.13.0+cpu-...whl); default:
#                        pip's find-links on this machine (PIP_FIND_LINKS or /opt/wheels). Empty:
#                        take torch from the Dockerfile's default, PyTorch's CPU index, online
#   DEBIAN_MIRROR        the Debian mirror debootstrap and the build's apt use (default deb.debian.org)
#   VECSIM_MJWARP_TASKS  the LIBERO tasks whose scenes the mjwarp image holds, space-separated
#                        (default: the Dockerfile's MJWARP_TASKS, libero_10/0)
# Prints the tag it built. The store is not Docker's: export the image with, for example,
#   CONTAINERS_STORAGE_CONF=~/.cache/vecsim/image/storage.conf buildah push vecsim:0.1.0 docker-archive:vecsim.tar
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cache="${VECSIM_IMAGE_CACHE:-$HOME/.cache/vecsim/image}"
mirror="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
version="$(sed -n 's/^version *= *"\(.*\)"/\1/p' "$here/pyproject.toml" | head -1)"
engine=cpu
if [ "${1:-}" = --engine ]; then
  engine="${2:-}"
  shift 2 || { echo "build_image: --engine needs a value: cpu or mjwarp" >&2; exit 2; }
fi
case "$engine" in
  cpu) tag="${1:-vecsim:$version}" ;;
  mjwarp) tag="${1:-vecsim-mjwarp:$version}" ;;
  *) echo "build_image: --engine $engine: the images are cpu and mjwarp" >&2; exit 2 ;;
esac
wheels="${VECSIM_TORCH_WHEELS-${PIP_FIND_LINKS:-/opt/wheels}}"

if [ "$(id -u)" != 0 ]; then
  echo "build_image: run as root (debootstrap and buildah's chroot isolation need it)" >&2
  exit 2
fi
for tool in buildah debootstrap; do
  command -v "$tool" >/dev/null || { echo "build_image: $tool is missing: apt-get install buildah debootstrap" >&2; exit 2; }
done

mkdir -p "$cache/tmp"
# One build at a time per cache (two would write the same base tarball and store).
exec 9>"$cache/build.lock"
flock 9
# buildah keeps RUN --mount=type=cache directories under TMPDIR: keep them (the pip cache) with
# the rest of the cache instead of in /var/tmp.
export TMPDIR="$cache/tmp"
# The image store, in the cache: overlay where the kernel mounts overlayfs (each layer costs what
# it changes), else vfs (each build step copies the whole root: slow, but works anywhere). The
# choice is made once and kept in storage.conf; `CONTAINERS_STORAGE_CONF=<it> buildah ...` (and
# podman) use the same store, as tests/deploy/test_image.py does.
export CONTAINERS_STORAGE_CONF="$cache/storage.conf"
if [ ! -f "$CONTAINERS_STORAGE_CONF" ]; then
  driver=vfs
  probe="$(mktemp -d "$cache/tmp/overlay-probe.XXXXXX")"
  mkdir "$probe/lower" "$probe/upper" "$probe/work" "$probe/merged"
  if mount -t overlay overlay -o "lowerdir=$probe/lower,upperdir=$probe/upper,workdir=$probe/work" "$probe/merged" 2>/dev/null; then
    umount "$probe/merged"
    driver=overlay
  fi
  rm -rf "$probe"
  printf '[storage]\ndriver = "%s"\ngraphroot = "%s"\nrunroot = "%s"\n' "$driver" "$cache/storage" "$cache/run" \
    >"$CONTAINERS_STORAGE_CONF"
fi
bah=(buildah)

# 1. The base. `debian:bookworm-slim` is itself a debootstrap minbase root; ours comes from the
#    same mirror the build's apt uses, with the same sources (bookworm, -updates, -security).
base="$(awk 'toupper($1) == "FROM" { print $2; exit }' "$here/Dockerfile")"
case "$base" in
  debian:*-slim) suite="${base#debian:}"; suite="${suite%-slim}" ;;
  *) echo "build_image: the Dockerfile's base $base is not a debian:<suite>-slim image debootstrap can make" >&2; exit 2 ;;
esac
if ! "${bah[@]}" inspect --type image "$base" >/dev/null 2>&1; then
  rootfs_tar="$cache/debian-$suite-minbase.tar"
  if [ ! -f "$rootfs_tar" ]; then
    echo "[build_image] debootstrap $suite from $mirror" >&2
    rootfs="$(mktemp -d "$cache/tmp/rootfs.XXXXXX")"
    debootstrap --variant=minbase "$suite" "$rootfs" "$mirror" >"$cache/debootstrap.log" 2>&1 \
      || { tail -20 "$cache/debootstrap.log" >&2; rm -rf "$rootfs"; exit 1; }
    rm -f "$rootfs/etc/apt/sources.list"
    cat >"$rootfs/etc/apt/sources.list.d/debian.sources" <<EOF
Types: deb
URIs: $mirror
Suites: $suite $suite-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: ${mirror%/debian}/debian-security
Suites: $suite-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
    rm -rf "$rootfs"/var/lib/apt/lists/* "$rootfs"/var/cache/apt/*.bin "$rootfs"/var/cache/apt/archives/*.deb
    tar -C "$rootfs" --exclude='./dev/*' --exclude='./proc/*' --exclude='./sys/*' -cf "$rootfs.tar" .
    mv "$rootfs.tar" "$rootfs_tar"
    rm -rf "$rootfs"
  fi
  echo "[build_image] tagging $rootfs_tar as $base" >&2
  ctr="$("${bah[@]}" from scratch)"
  "${bah[@]}" add "$ctr" "$rootfs_tar" / >/dev/null
  "${bah[@]}" config --env PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin --cmd bash "$ctr"
  "${bah[@]}" commit --quiet "$ctr" "$base" >/dev/null
  "${bah[@]}" rm "$ctr" >/dev/null
fi

# 2. The Dockerfile as it is. Build-time mounts only: their contents stay out of the image, but
#    buildah leaves their empty mount points in it (an empty /etc/pip.conf, /mnt/torch-wheels/,
#    /run/vecsim-build/), which change nothing:
#    - torch's CPU wheel directory, when given;
#    - this machine's CA bundle for pip, through a pip config: where HTTPS goes through a proxy
#      with its own CA, pip inside the build must trust what the host trusts.
# Docker's image format: OCI's has no HEALTHCHECK, and buildah would drop the Dockerfile's.
args=(--format docker --isolation chroot --layers --pull-never --target "$engine" -t "$tag" -f "$here/Dockerfile")
if [ "$engine" = mjwarp ] && [ -n "${VECSIM_MJWARP_TASKS:-}" ]; then
  args+=(--build-arg "MJWARP_TASKS=$VECSIM_MJWARP_TASKS")
fi
if [ -n "$wheels" ]; then
  args+=(-v "$wheels:/mnt/torch-wheels:ro" --build-arg TORCH_FIND_LINKS=/mnt/torch-wheels)
fi
host_ca=/etc/ssl/certs/ca-certificates.crt
if [ -f "$host_ca" ]; then
  printf '[global]\ncert = /run/vecsim-build/ca-certificates.crt\n' >"$cache/pip.conf"
  args+=(-v "$host_ca:/run/vecsim-build/ca-certificates.crt:ro" -v "$cache/pip.conf:/etc/pip.conf:ro")
fi
echo "[build_image] building $tag" >&2
# buildah 1.28 (Debian 12's) has been seen to hang after "Successfully tagged" at the end of a
# build that ran RUN steps, holding its store's locks, idle. Its last act is to print the image
# id: once it has, allow it a while to exit, then end it with SIGQUIT (Go prints where each of its
# goroutines waited) and go on if the tag names that image.
out="$(mktemp "$cache/tmp/bud-out.XXXXXX")"
"${bah[@]}" bud "${args[@]}" "$here" > >(tee "$out" >&2) &
bud=$!
while kill -0 "$bud" 2>/dev/null; do
  if grep -qE '^[0-9a-f]{64}$' "$out"; then
    for _ in $(seq 60); do kill -0 "$bud" 2>/dev/null && sleep 1; done
    if kill -0 "$bud" 2>/dev/null; then
      echo "[build_image] buildah bud still running 60 s after its image id: ending it (SIGQUIT)" >&2
      kill -QUIT "$bud"
    fi
    break
  fi
  sleep 2
done
rc=0
wait "$bud" || rc=$?
id="$(grep -E '^[0-9a-f]{64}$' "$out" | tail -1 || true)"
if [ -z "$id" ] || [ "$("${bah[@]}" inspect --type image --format '{{.FromImageID}}' "$tag" 2>/dev/null)" != "$id" ]; then
  echo "[build_image] buildah bud failed (exit $rc)" >&2
  rm -f "$out"
  exit 1
fi
rm -f "$out"
echo "$tag"
