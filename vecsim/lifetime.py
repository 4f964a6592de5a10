"""A child process that never outlives its parent: on Linux the kernel SIGKILLs it when its
parent goes, even when the parent itself was SIGKILLed and could stop nothing.

``prctl(PR_SET_PDEATHSIG)`` fires when the *thread* that forked the child exits, not only the
process: fork from a thread that lives as long as the process that owns the child (a watcher
thread, the pod's single sim thread, multiprocessing's forkserver). The setting survives
``execve``, so it works as a ``subprocess.Popen`` ``preexec_fn``:

    Popen(argv, preexec_fn=functools.partial(exit_with_parent, os.getpid()), start_new_session=True)

Elsewhere than Linux it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import signal
import sys

PR_SET_PDEATHSIG = 1  # <linux/prctl.h>

# Resolved once in the parent: a preexec_fn runs between fork and exec, where loading a library
# could block on a lock another thread of the parent held at fork time.
_prctl = (
    ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True).prctl if sys.platform == "linux" else None
)


def exit_with_parent(parent_pid: int, sig: int = signal.SIGKILL) -> None:
    """Have the kernel send this process ``sig`` when its parent (thread) exits; and exit now if
    ``parent_pid``, the process expected to be alive, is already gone (it may have died before
    the request took effect). Does nothing on a platform without ``prctl``.

    Raises:
        OSError: the kernel refused the request.
    """
    if _prctl is None:
        return
    if _prctl(PR_SET_PDEATHSIG, int(sig), 0, 0, 0) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"prctl(PR_SET_PDEATHSIG): {os.strerror(errno)}")
    try:
        os.kill(parent_pid, 0)
    except ProcessLookupError:
        os._exit(1)
    except PermissionError:
        pass
