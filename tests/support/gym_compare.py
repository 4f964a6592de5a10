"""Comparing a served vector env's results with gymnasium's own, whole or for some envs."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def assert_same(served, local, path: str = "") -> None:
    """Equal structure, dtypes, shapes and values (object arrays element by element)."""
    if isinstance(local, dict):
        assert isinstance(served, dict) and set(served) == set(local), (
            f"{path}: keys {sorted(served)} != {sorted(local)}"
        )
        for key in local:
            assert_same(served[key], local[key], f"{path}.{key}")
    elif isinstance(local, tuple):
        assert isinstance(served, tuple) and len(served) == len(local), path
        for i, (a, b) in enumerate(zip(served, local)):
            assert_same(a, b, f"{path}.{i}")
    elif isinstance(local, np.ndarray) and local.dtype == object:
        assert served.dtype == object and served.shape == local.shape, path
        for a, b in zip(served, local):
            assert_same(a, b, path)
    elif local is None:
        assert served is None, path
    else:
        a, b = np.asarray(served), np.asarray(local)
        assert (a.dtype, a.shape) == (b.dtype, b.shape), f"{path}: {a.dtype}{a.shape} != {b.dtype}{b.shape}"
        assert np.array_equal(a, b), f"{path}: {a} != {b}"


def env_rows(tree: Any, rows: Sequence[int]) -> Any:
    """The rows ``rows`` (envs) of a vector env's batched value: every array of a dict or tuple,
    each dict's keys that none of those envs gave (``_key`` mask all false) left out."""
    if isinstance(tree, tuple):
        return tuple(env_rows(item, rows) for item in tree)
    if isinstance(tree, dict):
        out = {key: env_rows(value, rows) for key, value in tree.items()}
        for key in [k for k in out if f"_{k}" in out and not out[f"_{k}"].any()]:
            del out[key], out[f"_{key}"]
        return {key: value for key, value in out.items() if not (isinstance(value, dict) and not value)}
    return np.asarray(tree)[list(rows)]
