"""What the benchmarks under ``bench/`` share; each ``bench/*.py`` script is one benchmark and imports
from here, never from another script.

- :mod:`lib.records`: where records and plots go, spreads, the ``RESULT`` line.
- :mod:`lib.pods`: interleaved rounds, paired ratios, pods and jobs on loopback ports.
- :mod:`lib.machine`: GL/EGL probes, the GPU, CPU topology and pinning, memory.
- :mod:`lib.jobs`: what a GPU bench builds (``Plan``), its job config, start-up, regrouping stages.
- :mod:`lib.policies`: vision policies, their CUDA graphs, a ViT calibrated to a forward time,
  scripted and chunked policies.
- :mod:`lib.measure`: timed stage calls, pod counters, rollouts, interleaved contenders.
- :mod:`lib.stats`: figures from measured rollouts.
- :mod:`lib.scripted`: a scripted pick-and-place policy for LIBERO, Wilson intervals, the
  agreement of two engines per init state.
- :mod:`lib.plots`: the GPU benches' plots.
- :mod:`lib.ceiling`: the node's simulation alone in pinned processes (physics-only, the
  ceiling with cameras), the baselines of ``bench_chunks.py``.

A script runs with ``bench/`` on ``sys.path`` (Python puts a script's folder there), so it
imports ``from lib.jobs import Plan``.
"""
