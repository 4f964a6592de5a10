"""Helpers the tests share: processes on loopback, scripted pods, test envs, manifests, bench scripts.

``tests/`` is on ``sys.path`` (pyproject's pytest ``pythonpath``), so a test anywhere under it
imports these as ``support.<module>``; a subprocess gets ``tests/`` on its ``PYTHONPATH`` from
``service_procs.clean_env``.
"""

from pathlib import Path

# The repository's root, for tests that read its files (docs, configs, bench/): independent of
# how deep a test file sits under tests/.
ROOT = Path(__file__).resolve().parents[2]
