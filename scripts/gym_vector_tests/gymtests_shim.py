"""The env factories the harness (``conftest.py``) wrote for a pod, as callables of this module:
``gym/gymtests_shim:F<n>x<i>`` is file ``F<n>x<i>.pkl`` of ``$GYMTESTS_FACTORIES``, the factory
that ``AsyncVectorEnv`` would have sent to its worker, which the pod calls for env ``i``. Only
files the harness itself wrote on this machine are loaded.
"""

import os
import re
from pathlib import Path

import cloudpickle


def __getattr__(name: str):
    path = Path(os.environ["GYMTESTS_FACTORIES"]) / f"{name}.pkl"
    if not re.fullmatch(r"F\d+x\d+", name) or not path.is_file():
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return cloudpickle.loads(path.read_bytes())
