"""Registers, in a pod, the env factories the harness (``conftest.py``) wrote for it: file
``F<n>x<i>.pkl`` of ``$GYMTESTS_FACTORIES`` becomes the id ``F<n>x<i>-v0`` (the pod makes
``gym/gymtests_shim:F<n>x<i>-v0``). The id adds nothing around the factory's env: no order
enforcing, no time limit, no env checker, so the pod serves the env the factory returns, as
``AsyncVectorEnv``'s worker does. Only files the harness itself wrote on this machine are loaded.
"""

import os
from pathlib import Path

import cloudpickle
import gymnasium


def _factory(path: Path):
    def make(**kwargs):
        return cloudpickle.loads(path.read_bytes())(**kwargs)

    return make


for _path in sorted(Path(os.environ["GYMTESTS_FACTORIES"]).glob("F*.pkl")):
    gymnasium.register(
        f"{_path.stem}-v0", entry_point=_factory(_path), order_enforce=False, disable_env_checker=True
    )
