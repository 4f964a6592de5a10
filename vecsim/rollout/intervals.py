"""Time intervals ``(begin, end)`` in seconds: the rollout's timing and the benches' use them."""

from __future__ import annotations

from collections.abc import Iterable, Sequence

Interval = tuple[float, float]


def merge(intervals: Iterable[Interval]) -> list[Interval]:
    """``intervals`` as sorted, disjoint intervals covering the same time."""
    merged: list[Interval] = []
    for begin, end in sorted(intervals):
        if merged and begin <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], end))
        else:
            merged.append((begin, end))
    return merged


def covered(intervals: Iterable[Interval]) -> float:
    """The time ``intervals`` cover together, each moment counted once."""
    return sum(end - begin for begin, end in merge(intervals))


def intersection(a: Sequence[Interval], b: Sequence[Interval]) -> float:
    """The time two lists of sorted, disjoint intervals (as :func:`merge` returns) share."""
    total, i, j = 0.0, 0, 0
    while i < len(a) and j < len(b):
        total += max(0.0, min(a[i][1], b[j][1]) - max(a[i][0], b[j][0]))
        if a[i][1] < b[j][1]:
            i += 1
        else:
            j += 1
    return total
