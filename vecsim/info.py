"""An env's own ``info``, batched the way gymnasium's vector envs batch it, and back into a vector env.

A pod answers the own info of the n envs of a call (the keys beyond vecsim's ``success``,
``task_id``, ``state_id``) as one batched dict, built by gymnasium's rule
(``VectorEnv._add_info``): a number becomes an array ``[n]`` of its own type (``int`` int64,
``float`` float64, ``bool`` bool, a numpy number its dtype), an array an array ``[n, *shape]`` of
its dtype, a dict a dict batched the same way, anything else a list of ``n`` JSON values (None
where absent), which the client turns into an object array. Each key ``k`` has its mask ``_k``
(bool ``[n]``: which envs gave it). A value JSON cannot hold is left out (logged once per key).

:func:`take_rows` keeps some rows of such a batch; :func:`merge_rows` puts one into the info of
a vector env of ``num_envs`` envs at the rows of the envs it belongs to, as gymnasium would have
added each env's info itself. Pure.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from typing import Any

import numpy as np

from vecsim import wire

__all__ = ["batch_infos", "merge_rows", "take_rows"]

log = logging.getLogger("vecsim.info")
_warned: set[str] = set()


def _plain(value: Any) -> Any:
    """``value`` as JSON data a list on the wire can hold (no objects inside), else ValueError."""
    data = wire.to_jsonable(value)
    json.dumps(data, allow_nan=False)

    def check(item: Any) -> None:
        if isinstance(item, dict):
            raise ValueError("an object inside a list")
        if isinstance(item, list):
            for sub in item:
                check(sub)

    check(data)
    return data


def _add(out: dict[str, Any], info: dict[str, Any], row: int, n: int, where: str) -> dict[str, Any]:
    for key, value in info.items():
        path = f"{where}{key}"
        if not isinstance(key, str):
            continue
        if isinstance(value, dict):
            array: Any = _add(out.get(key, {}), value, row, n, f"{path}.")
        else:
            array = out.get(key)
            if array is None:
                if type(value) in (int, float, bool) or isinstance(value, np.number):
                    array = np.zeros(n, dtype=type(value))
                elif isinstance(value, np.ndarray) and value.dtype.kind in "biuf":
                    array = np.zeros((n, *value.shape), dtype=value.dtype)
                else:
                    array = [None] * n
            try:
                if isinstance(array, list):
                    array[row] = _plain(value)
                else:
                    array[row] = value
            except (ValueError, TypeError, wire.WireError) as exc:
                if path not in _warned:
                    _warned.add(path)
                    log.warning("info key %r: a %s cannot travel; left out (%s)", path, type(value).__name__, exc)
                continue
        mask = out.get(f"_{key}")
        if mask is None:
            mask = np.zeros(n, dtype=bool)
        mask[row] = True
        out[key], out[f"_{key}"] = array, mask
    return out


def _numbers(infos: Sequence[dict[str, Any]]) -> dict[str, Any] | None:
    """The batch of ``infos`` when every env gave the same keys, each a number of one type in all
    of them (a gym env's own info, say), column by column; None for any other batch.

    The same arrays and masks as :func:`_add` builds row by row, at a fraction of its cost: a pod
    batches the info of every env it steps, on every step."""
    keys = list(infos[0])
    # map() over builtins, not generators: this check runs on every step.
    if set(map(type, keys)) != {str} or set(map(len, infos)) != {len(keys)}:
        return None
    out: dict[str, Any] = {}
    for key in keys:
        try:
            column = [info[key] for info in infos]
        except KeyError:
            return None
        kinds = set(map(type, column))
        kind = kinds.pop()
        if kinds or not (kind in (int, float, bool) or issubclass(kind, np.number)):
            return None
        out[key], out[f"_{key}"] = np.array(column, dtype=kind), np.ones(len(infos), dtype=bool)
    return out


def batch_infos(infos: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Batch one own info per env (``infos[i]`` of the call's row i) as gymnasium does, with masks.

    Returns:
        the batched dict (empty when no env gave anything): arrays, lists and nested dicts.
    """
    if infos and infos[0] and (columns := _numbers(infos)) is not None:
        return columns
    out: dict[str, Any] = {}
    for row, info in enumerate(infos):
        if info:
            _add(out, info, row, len(infos), "")
    return out


def merge_rows(
    info: dict[str, Any], batched: dict[str, Any], envs: np.ndarray, num_envs: int, keep: np.ndarray | None = None
) -> dict[str, Any]:
    """Put ``batched`` (rows ``0..len(envs)-1``) into ``info`` at rows ``envs`` of ``num_envs``
    (only the rows ``keep`` marks, if given); return ``info``. A list becomes an object array, as
    gymnasium keeps values of other types. A key no kept row gave is not added."""
    envs = np.asarray(envs, dtype=np.int64)
    rows = np.arange(len(envs)) if keep is None else np.flatnonzero(keep)
    if rows.size == 0:
        return info
    for key, value in batched.items():
        mask = batched.get(key[1:]) is not None and key.startswith("_")
        given = batched.get(f"_{key}")
        if not mask and given is not None and not np.asarray(given)[rows].any():
            continue
        if mask and not np.asarray(value)[rows].any():
            continue
        if isinstance(value, dict):
            info[key] = merge_rows(info.get(key, {}), value, envs, num_envs, keep)
        elif isinstance(value, np.ndarray):
            if key not in info:
                info[key] = np.zeros((num_envs, *value.shape[1:]), dtype=value.dtype)
            info[key][envs[rows]] = value[rows]
        else:
            if key not in info:
                info[key] = np.full(num_envs, None, dtype=object)
            for row in rows:
                info[key][envs[row]] = value[row]
    return info


def take_rows(batched: dict[str, Any], rows: Sequence[int] | np.ndarray) -> dict[str, Any]:
    """The batch of rows ``rows`` of ``batched`` (in that order): arrays, masks and lists alike,
    nested dicts too. A key none of those rows gave stays, its mask all false."""
    index = np.asarray(rows, dtype=np.int64)
    out: dict[str, Any] = {}
    for key, value in batched.items():
        if isinstance(value, dict):
            out[key] = take_rows(value, index)
        elif isinstance(value, np.ndarray):
            out[key] = value[index]
        else:
            out[key] = [value[int(i)] for i in index]
    return out
