"""The `mjwarp` engine's host side: where the images land, and whose turn the GPU is.

:class:`HostImages` holds the pod's last images of every env, per camera, in page-locked host
memory where the engine runs on a CUDA GPU, so that the copy of a batch's frames lands in them
straight from the GPU: no staging buffer, no second copy on the host, no fresh pages to fault in
each render. An answer may hold views of those arrays while the pod sends it (or keeps it for a
replayed request); the next render then writes into a set that nothing holds any more, taken
from the spares, or a new one.

:class:`GpuTurn` lets the pods that share one GPU take turns at it, one engine call at a time,
through a lock file per GPU (``fcntl.flock``: the kernel frees it when a pod dies). Without turns
two pods on one GPU are time-sliced: their calls stretch to the same end, then both answer over
HTTP while the GPU idles. With turns, one pod's GPU work runs while the other answers.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import sys
import time
import weakref
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from vecsim.engine.mjwarp.settings import DEFAULT_TURN_WAIT_S, MjwarpSettings, turns_directory

log = logging.getLogger(__name__)

# Spare sets of image arrays kept per camera beyond the current one.
SPARES = 2
# At most this many arrays a camera from the (page-locked) allocator alive at once; past it, while
# answers still hold the older ones, plain arrays: page-locked memory is not for an unbounded pile.
LOCKED_SETS = SPARES + 2


class HostImages:
    """Each camera's images of every env, ``uint8 [num_envs, H, W, 3]``, in arrays made by
    ``allocate(shape)`` (page-locked ones on a CUDA GPU), at most :data:`LOCKED_SETS` of them a
    camera alive at once (then plain numpy arrays)."""

    def __init__(
        self, names: tuple[str, ...], shape: tuple[int, ...], allocate: Callable[[tuple[int, ...]], np.ndarray]
    ):
        self._shape = tuple(shape)
        self._allocate = allocate
        self._allocated: list[weakref.ref] = []  # the allocator's arrays, alive or not
        self._limit = LOCKED_SETS * len(names)
        self.current: dict[str, np.ndarray] = {name: self._new() for name in names}
        self._spare: dict[str, list[np.ndarray]] = {name: [] for name in names}
        # Whether an answer may hold views of the current arrays (see :meth:`lend`).
        self._lent = False

    def lend(self, name: str, rows: slice) -> np.ndarray:
        """A view of camera ``name``'s images of envs ``rows``, for an answer to keep: the next
        :meth:`renew` leaves these arrays to it."""
        self._lent = True
        return self.current[name][rows]

    def renew(self, every: bool) -> None:
        """Before a render: if the current arrays were lent, write into another set, one that
        nothing holds any more. ``every``: the render writes every env, so the set's old pixels
        do not matter; otherwise they are made the current ones first."""
        if not self._lent:
            return
        self._lent = False
        for name, pixels in self.current.items():
            fresh = self._take(name)
            if not every:
                np.copyto(fresh, pixels)
            spare = self._spare[name]
            spare.append(pixels)
            if len(spare) > SPARES:
                spare.pop(0)  # the oldest: freed once its last answer lets go
            self.current[name] = fresh

    def _take(self, name: str) -> np.ndarray:
        spare = self._spare[name]
        for index in range(len(spare)):
            # The list's reference and the call's argument: no answer holds a view of it.
            if sys.getrefcount(spare[index]) == 2:
                return spare.pop(index)
        return self._new()

    def _new(self) -> np.ndarray:
        self._allocated = [ref for ref in self._allocated if ref() is not None]
        if len(self._allocated) >= self._limit:
            return np.empty(self._shape, dtype=np.uint8)
        array = self._allocate(self._shape)
        self._allocated.append(weakref.ref(array))
        if array.shape != self._shape or array.dtype != np.uint8 or not array.flags.c_contiguous:
            raise ValueError(f"allocate: got {array.dtype} {array.shape}, want a C-contiguous uint8 {self._shape}")
        return array


def pinned_allocator(device: object) -> Callable[[tuple[int, ...]], np.ndarray]:
    """``allocate(shape)`` for :class:`HostImages`: page-locked host arrays made by warp when
    ``device`` is a CUDA device, else plain ones."""
    import warp as wp

    if not getattr(device, "is_cuda", False):
        return lambda shape: np.zeros(shape, dtype=np.uint8)
    # The numpy array keeps the warp array (its base), and so the page-locked memory, alive.
    return lambda shape: wp.zeros(shape, dtype=wp.uint8, device="cpu", pinned=True).numpy()


def for_engine(camera: Any, num_envs: int, settings: MjwarpSettings) -> tuple[GpuTurn, HostImages]:
    """The turn (as ``settings`` say) and the image arrays of an engine on warp's default device,
    for ``camera`` (a :class:`vecsim.config.CameraConfig`) and ``num_envs`` envs."""
    import warp as wp

    device = wp.get_device()
    shape = (num_envs, camera.height, camera.width, 3)
    return GpuTurn.for_device(device, settings), HostImages(tuple(camera.names), shape, pinned_allocator(device))


class GpuTurn:
    """``with turn:`` holds this GPU's turn for one engine call (a no-op without a lock
    directory: ``None``, ``""`` or ``"off"``); the engine's own lock keeps its calls one at a
    time. Two pods of 2,048 worlds on one H200 ran 1.38x faster with turns than time-sliced
    (docs/mjwarp.md)."""

    def __init__(self, directory: str | None, gpu: str, wait_s: float = DEFAULT_TURN_WAIT_S):
        self.path: Path | None = None
        self.wait_s = wait_s
        # Seconds the last __enter__ waited for the turn.
        self.waited_s = 0.0
        self._fd: int | None = None
        directory = turns_directory(directory)
        if directory is not None:
            name = "".join(c if c.isalnum() or c in "-_." else "_" for c in gpu) or "gpu"
            self.path = Path(directory) / f"vecsim-gpu-{name}.lock"

    @classmethod
    def for_device(cls, device: object, settings: MjwarpSettings) -> GpuTurn:
        """The turn of a warp device in ``settings.turns`` (``VECSIM_MJWARP_TURNS``), waited for
        at most ``settings.turn_wait_s``; none on warp's CPU device."""
        if not getattr(device, "is_cuda", False):
            return cls(None, "cpu")
        return cls(settings.turns_dir, getattr(device, "uuid", None) or str(device), settings.turn_wait_s)

    def __enter__(self) -> GpuTurn:
        started = time.monotonic()
        if self.path is not None and self._fd is None:
            self._fd = self._open()
        if self._fd is not None:
            self._acquire(self._fd)
        self.waited_s = time.monotonic() - started
        return self

    def __exit__(self, *exc_info: object) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def _open(self) -> int | None:
        assert self.path is not None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            return os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            log.warning("mjwarp: no GPU turns (%s: %s); pods on this GPU are time-sliced", self.path, exc)
            self.path = None
            return None

    def _acquire(self, fd: int) -> None:
        """Wait for the lock, polling: a blocking flock could not give up after ``wait_s``."""
        deadline = time.monotonic() + self.wait_s
        pause = 0.0002
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EACCES):
                    raise
            if time.monotonic() >= deadline:
                log.warning(
                    "mjwarp: waited %.0f s for the GPU's turn (%s); going on without it", self.wait_s, self.path
                )
                return  # __exit__'s unlock is then a no-op
            time.sleep(pause)
            pause = min(pause * 2, 0.002)
