"""Ties multiprocessing's forkserver to the pod that starts it: the pod's worker pool names this
module in the forkserver's preload, so the forkserver imports it first thing. It lives outside
``vecsim.engine`` so that the forkserver loads no simulator or GL library by importing it.

The forkserver would otherwise outlive a SIGKILLed pod as long as any env worker lives (each
worker holds the pipe whose closing tells the forkserver to exit), and a worker busy or stuck
in a step never reads that its own pipe closed. Tied, the forkserver dies with the pod and the
workers (tied to the forkserver, :class:`vecsim.engine.pool.WorkerPool`) with it.
"""

import os

from vecsim.lifetime import exit_with_parent

exit_with_parent(os.getppid())
