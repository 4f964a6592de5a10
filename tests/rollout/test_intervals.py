"""Interval arithmetic behind the rollout's timing and the benches' overlap figures."""

from __future__ import annotations

import pytest

from vecsim.rollout.intervals import covered, intersection, merge


def test_merge_sorts_and_joins_overlapping_and_touching_intervals():
    assert merge([(5.0, 6.0), (0.0, 2.0), (1.0, 3.0), (3.0, 4.0)]) == [(0.0, 4.0), (5.0, 6.0)]
    assert merge([(0.0, 10.0), (2.0, 3.0)]) == [(0.0, 10.0)]  # one inside another
    assert merge([]) == [] and merge(iter([(1.0, 2.0)])) == [(1.0, 2.0)]


def test_covered_counts_each_moment_once():
    assert covered([(0.0, 2.0), (1.0, 3.0), (5.0, 6.0)]) == pytest.approx(4.0)
    assert covered([]) == 0.0


def test_intersection_of_disjoint_lists_is_the_time_both_cover():
    a = merge([(0.0, 2.0), (4.0, 6.0)])
    b = merge([(1.0, 5.0), (5.5, 7.0)])
    assert intersection(a, b) == pytest.approx(1.0 + 1.0 + 0.5)
    assert intersection(a, b) == intersection(b, a)
    assert intersection(a, []) == 0.0 and intersection(a, merge([(2.0, 4.0)])) == 0.0  # only touching
