"""Nested observation trees: dicts and tuples whose leaves are arrays with one row per env.

A gymnasium ``Dict`` space's batched value is a dict of such trees, a ``Tuple`` space's a tuple;
on the wire a tuple travels as a dict keyed ``"0"``, ``"1"``, ... (:func:`vecsim.spaces.tuples_as_dicts`).
Every helper here walks dicts and tuples alike and leaves other values as leaves. Pure: no I/O.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

__all__ = ["TreeMismatchError", "fill_rows", "leaves", "map_leaves", "put_rows", "row", "stack", "take_rows"]


class TreeMismatchError(ValueError):
    """A value does not have the tree's structure or a leaf's shape; the message names the key path."""


def leaves(tree: Any) -> list[Any]:
    """The leaves of ``tree``, depth first, in key order."""
    if isinstance(tree, dict):
        return [leaf for item in tree.values() for leaf in leaves(item)]
    if isinstance(tree, tuple):
        return [leaf for item in tree for leaf in leaves(item)]
    return [tree]


def map_leaves(fn: Callable[[Any], Any], tree: Any) -> Any:
    """A tree of ``tree``'s structure holding ``fn(leaf)`` for each leaf."""
    if isinstance(tree, dict):
        return {key: map_leaves(fn, item) for key, item in tree.items()}
    if isinstance(tree, tuple):
        return tuple(map_leaves(fn, item) for item in tree)
    return fn(tree)


def take_rows(tree: Any, index: np.ndarray) -> Any:
    """Rows ``index`` of every leaf (numpy indexing: an index array copies)."""
    return map_leaves(lambda leaf: leaf[index], tree)


def row(tree: Any, i: int) -> Any:
    """Row ``i`` of every leaf, each a copy (one env's value out of a batched one)."""
    return map_leaves(lambda leaf: np.array(leaf[i]), tree)


def stack(items: Sequence[Any]) -> Any:
    """One tree whose leaves stack the items' leaves along a new first axis (items share a structure)."""
    first = items[0]
    if isinstance(first, dict):
        return {key: stack([item[key] for item in items]) for key in first}
    if isinstance(first, tuple):
        return tuple(stack([item[i] for item in items]) for i in range(len(first)))
    return np.stack(items)


def put_rows(dst: Any, src: Any, rows: np.ndarray, take: np.ndarray | None = None) -> None:
    """Write ``src`` (its rows ``take``, or all) into rows ``rows`` of ``dst``, trees of one structure."""
    if isinstance(dst, dict):
        for key in dst:
            put_rows(dst[key], src[key], rows, take)
    elif isinstance(dst, tuple):
        for sub, part in zip(dst, src):
            put_rows(sub, part, rows, take)
    else:
        dst[rows] = src if take is None else src[take]


def fill_rows(dst: Any, src: Any, rows: np.ndarray, where: str) -> None:
    """Copy ``src``, a value as the wire carries it (tuples as dicts keyed "0", "1", ...), into rows
    ``rows`` of ``dst``, checking structure and shapes first at each level.

    Raises:
        TreeMismatchError: ``src`` has other keys or a leaf another shape than ``len(rows)`` rows
            of ``dst``'s; the message names the key path, starting at ``where``.
    """
    if isinstance(dst, tuple):
        keys = [str(i) for i in range(len(dst))]
        if not isinstance(src, dict) or sorted(src) != sorted(keys):
            got = sorted(src) if isinstance(src, dict) else type(src).__name__
            raise TreeMismatchError(f"answer {where} has keys {got}, expected {keys}")
        for key, sub in zip(keys, dst):
            fill_rows(sub, src[key], rows, f"{where}.{key}")
        return
    if isinstance(dst, dict):
        if not isinstance(src, dict) or set(src) != set(dst):
            got = sorted(src) if isinstance(src, dict) else type(src).__name__
            raise TreeMismatchError(f"answer {where} has keys {got}, expected {sorted(dst)}")
        for key in dst:
            fill_rows(dst[key], src[key], rows, f"{where}.{key}")
        return
    src = np.asarray(src)
    if src.shape != (len(rows), *dst.shape[1:]):
        raise TreeMismatchError(f"answer {where} has shape {list(src.shape)}, expected {[len(rows), *dst.shape[1:]]}")
    dst[rows] = src
