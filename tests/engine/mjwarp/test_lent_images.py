"""The mjwarp engine's camera images, answered without a copy: a call over a contiguous run of
envs gets views of the engine's latest images (``contiguous_run``), and the next render writes
new arrays (``unlend``), so an answer's pixels never change after the call returned. numpy
only: the parts of ``_gather`` and ``_render`` that need no GPU."""

from __future__ import annotations

import numpy as np
import pytest

from vecsim.engine.mjwarp.engine import contiguous_run, unlend


@pytest.mark.parametrize(
    ("ids", "run"),
    [
        ([0, 1, 2, 3], slice(0, 4)),
        ([5], slice(5, 6)),
        ([2, 3, 4], slice(2, 5)),
        ([], None),
        ([0, 2, 3], None),
        ([1, 0], None),
        ([0, 1, 1, 3], None),  # first and last span 4 envs, but not as a run
    ],
)
def test_a_contiguous_run_of_envs_is_a_slice_and_nothing_else_is(ids: list[int], run: slice | None) -> None:
    assert contiguous_run(np.asarray(ids, dtype=np.int64)) == run


def images_of(envs: int, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {name: rng.integers(0, 256, (envs, 4, 6, 3), dtype=np.uint8) for name in ("agentview", "wrist")}


@pytest.mark.parametrize("every", [True, False])
def test_pixels_lent_to_an_answer_do_not_change_when_the_next_render_writes(every: bool) -> None:
    images = images_of(8, seed=0)
    run = contiguous_run(np.arange(8))
    answer = {name: pixels[run] for name, pixels in images.items()}
    sent = {name: pixels.copy() for name, pixels in answer.items()}
    unlend(images, every=every)
    rendered = images_of(8, seed=1)
    for name in images:
        if every:
            images[name][:] = rendered[name]
        else:
            images[name][[2, 5]] = rendered[name][[2, 5]]
    for name in images:
        np.testing.assert_array_equal(answer[name], sent[name])
        assert not np.shares_memory(answer[name], images[name])


def test_a_partial_render_after_lending_keeps_the_other_envs_pixels() -> None:
    images = images_of(8, seed=0)
    before = {name: pixels.copy() for name, pixels in images.items()}
    unlend(images, every=False)
    for name in images:
        np.testing.assert_array_equal(images[name], before[name])
