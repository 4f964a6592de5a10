"""The mjwarp engine's host side (``vecsim.engine.mjwarp.host``), the parts that need no GPU.

- Images answered without a copy: a call over a contiguous run of envs gets views of the
  engine's latest images (``contiguous_run``, ``HostImages.lend``), and the next render writes
  into another set (``HostImages.renew``), so an answer's pixels never change after the call
  returned; a set that no answer holds any more is written again instead of a new one.
- Turns at the GPU (``GpuTurn``) between real processes: one waits while another holds the
  turn, a dead holder frees it, a wait that runs out goes on with a warning.
"""

from __future__ import annotations

import logging
import subprocess
import sys
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from vecsim.engine.mjwarp.engine import contiguous_run
from vecsim.engine.mjwarp.host import LOCKED_SETS, SPARES, GpuTurn, HostImages
from vecsim.engine.mjwarp.settings import DEFAULT_TURNS_DIR, TURNS_ENV, MjwarpSettings

NAMES = ("agentview", "wrist")
SHAPE = (8, 4, 6, 3)


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


class Allocator:
    """Counts the arrays it makes."""

    def __init__(self) -> None:
        self.made = 0

    def __call__(self, shape: tuple[int, ...]) -> np.ndarray:
        self.made += 1
        return np.zeros(shape, dtype=np.uint8)


def rendered(seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {name: rng.integers(0, 256, SHAPE, dtype=np.uint8) for name in NAMES}


def render(images: HostImages, seed: int, envs: list[int] | None = None) -> None:
    """What the engine's render does: renew, then write every env's pixels or ``envs``'."""
    images.renew(every=envs is None)
    for name, pixels in rendered(seed).items():
        if envs is None:
            images.current[name][:] = pixels
        else:
            images.current[name][envs] = pixels[envs]


def lend_all(images: HostImages) -> dict[str, np.ndarray]:
    return {name: images.lend(name, slice(0, SHAPE[0])) for name in NAMES}


@pytest.mark.parametrize("every", [True, False])
def test_pixels_lent_to_an_answer_do_not_change_when_the_next_render_writes(every: bool) -> None:
    images = HostImages(NAMES, SHAPE, Allocator())
    render(images, seed=0)
    answer = lend_all(images)
    sent = {name: pixels.copy() for name, pixels in answer.items()}
    render(images, seed=1, envs=None if every else [2, 5])
    for name in NAMES:
        np.testing.assert_array_equal(answer[name], sent[name])
        assert not np.shares_memory(answer[name], images.current[name])


def test_a_partial_render_after_lending_keeps_the_other_envs_pixels() -> None:
    images = HostImages(NAMES, SHAPE, Allocator())
    render(images, seed=0)
    before = {name: pixels.copy() for name, pixels in images.current.items()}
    lend_all(images)
    render(images, seed=1, envs=[2, 5])
    new = rendered(1)
    for name in NAMES:
        want = before[name].copy()
        want[[2, 5]] = new[name][[2, 5]]
        np.testing.assert_array_equal(images.current[name], want)


def test_a_set_no_answer_holds_is_written_again_and_no_new_one_is_made() -> None:
    allocate = Allocator()
    images = HostImages(NAMES, SHAPE, allocate)
    first = {name: id(pixels) for name, pixels in images.current.items()}  # ids: a reference would hold them
    answer = lend_all(images)
    render(images, seed=1)  # the first set is lent: a second one is made
    assert allocate.made == 2 * len(NAMES)
    del answer  # the answer was sent and let go
    lend_all(images)
    render(images, seed=2)
    assert allocate.made == 2 * len(NAMES)
    for name in NAMES:
        assert id(images.current[name]) == first[name]
        np.testing.assert_array_equal(images.current[name], rendered(2)[name])


def test_sets_still_held_are_never_written_and_spares_are_bounded() -> None:
    images = HostImages(NAMES, SHAPE, Allocator())
    answers = []
    for seed in range(SPARES + 3):
        render(images, seed=seed)
        answers.append((seed, lend_all(images)))
    render(images, seed=99)
    for seed, answer in answers:
        for name in NAMES:
            np.testing.assert_array_equal(answer[name], rendered(seed)[name])
            assert not np.shares_memory(answer[name], images.current[name])
    assert all(len(spare) <= SPARES for spare in images._spare.values())


def test_a_set_not_lent_is_written_in_place() -> None:
    allocate = Allocator()
    images = HostImages(NAMES, SHAPE, allocate)
    first = dict(images.current)
    render(images, seed=0)
    render(images, seed=1)
    assert allocate.made == len(NAMES)
    assert all(images.current[name] is first[name] for name in NAMES)


def test_an_allocator_of_the_wrong_arrays_is_refused_naming_what_it_got() -> None:
    with pytest.raises(ValueError, match=r"allocate: got float32 \(8, 4, 6, 3\)"):
        HostImages(NAMES, SHAPE, lambda shape: np.zeros(shape, dtype=np.float32))


HOLDER = """
import sys, time
from vecsim.engine.mjwarp.host import GpuTurn
turn = GpuTurn(sys.argv[1], "GPU-test")
with turn:
    print("held", flush=True)
    sys.stdin.readline()
print("released", flush=True)
"""


class Holder:
    """Another process holding the GPU's turn until :meth:`release` (or until it is killed)."""

    def __init__(self, directory: Path) -> None:
        self.process = subprocess.Popen(
            [sys.executable, "-c", HOLDER, str(directory)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.process.stdout is not None and self.process.stdout.readline().strip() == "held"

    def release(self) -> None:
        assert self.process.stdin is not None and self.process.stdout is not None
        self.process.stdin.write("\n")
        self.process.stdin.flush()
        assert self.process.stdout.readline().strip() == "released"
        self.process.wait(timeout=30)

    def kill(self) -> None:
        self.process.kill()
        self.process.wait(timeout=30)


def enter_in_thread(turn: GpuTurn) -> tuple[threading.Thread, threading.Event, threading.Event]:
    entered, leave = threading.Event(), threading.Event()

    def hold() -> None:
        with turn:
            entered.set()
            leave.wait(timeout=30)

    thread = threading.Thread(target=hold, daemon=True)
    thread.start()
    return thread, entered, leave


@pytest.mark.parametrize("let_go", ["release", "kill"])
def test_a_pod_waits_for_the_turn_another_process_holds_until_it_lets_go_or_dies(
    let_go: str, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    holder = Holder(tmp_path)
    turn = GpuTurn(str(tmp_path), "GPU-test", wait_s=60)
    try:
        thread, entered, leave = enter_in_thread(turn)
        assert not entered.wait(timeout=0.5)
        getattr(holder, let_go)()  # "kill": the kernel frees a dead holder's lock
        assert entered.wait(timeout=30)
        leave.set()
        thread.join(timeout=30)
    finally:
        holder.kill()
        turn.close()
    assert turn.waited_s >= 0.5  # what the pod's metric vecsim_pod_gpu_turn_wait_seconds adds up
    assert "going on without it" not in caplog.text
    assert [p.name for p in tmp_path.iterdir()] == ["vecsim-gpu-GPU-test.lock"]


def test_a_wait_that_runs_out_goes_on_with_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    holder = Holder(tmp_path)
    turn = GpuTurn(str(tmp_path), "GPU-test", wait_s=0.2)
    try:
        with caplog.at_level(logging.WARNING, logger="vecsim.engine.mjwarp.host"), turn:
            pass
    finally:
        holder.kill()
        turn.close()
    assert "waited 0 s for the GPU's turn" in caplog.text and "going on without it" in caplog.text


@pytest.mark.parametrize("directory", [None, "", "off"])
def test_no_directory_means_no_turns(directory: str | None, tmp_path: Path) -> None:
    turn = GpuTurn(directory, "GPU-test")
    with turn:
        with turn:  # nothing is held, so nothing waits
            pass
    assert turn.path is None


def test_a_directory_that_cannot_hold_the_lock_means_no_turns_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    turn = GpuTurn(str(blocker / "turns"), "GPU-test")
    with caplog.at_level(logging.WARNING, logger="vecsim.engine.mjwarp.host"), turn:
        pass
    assert turn.path is None and "no GPU turns" in caplog.text


def test_the_lock_file_is_named_after_the_gpu_with_nothing_unsafe(tmp_path: Path) -> None:
    turn = GpuTurn(str(tmp_path), "GPU-1/../x y")
    assert turn.path == tmp_path / "vecsim-gpu-GPU-1_.._x_y.lock"


def test_pods_on_a_gpu_take_turns_by_default_and_the_setting_turns_them_off() -> None:
    gpu = SimpleNamespace(is_cuda=True, uuid="GPU-0a1b")  # what the engine reads of a warp device
    default = GpuTurn.for_device(gpu, MjwarpSettings.from_env({}))
    assert default.path == Path(DEFAULT_TURNS_DIR) / "vecsim-gpu-GPU-0a1b.lock" and default.wait_s == 120
    for off in ("off", ""):
        assert GpuTurn.for_device(gpu, MjwarpSettings.from_env({TURNS_ENV: off})).path is None
    # warp's CPU device
    assert GpuTurn.for_device(SimpleNamespace(is_cuda=False, uuid=None), MjwarpSettings()).path is None


def test_the_turn_settings_reach_the_turn(tmp_path: Path) -> None:
    gpu = SimpleNamespace(is_cuda=True, uuid="GPU-0a1b")
    settings = MjwarpSettings.from_env({TURNS_ENV: str(tmp_path), "VECSIM_MJWARP_TURN_WAIT_S": "2.5"})
    turn = GpuTurn.for_device(gpu, settings)
    assert turn.path == tmp_path / "vecsim-gpu-GPU-0a1b.lock" and turn.wait_s == 2.5


def test_past_the_locked_sets_held_by_answers_new_sets_are_plain_arrays() -> None:
    allocate = Allocator()
    images = HostImages(NAMES, SHAPE, allocate)
    answers = []
    for seed in range(LOCKED_SETS + 3):
        render(images, seed=seed)
        answers.append((seed, lend_all(images)))
    assert allocate.made == LOCKED_SETS * len(NAMES)
    for seed, answer in answers:
        for name in NAMES:
            np.testing.assert_array_equal(answer[name], rendered(seed)[name])
    answers.clear()  # every answer let go: the allocator's arrays are written again, no new ones
    for seed in range(LOCKED_SETS + 3):
        render(images, seed=seed)
        lend_all(images)
    assert allocate.made == LOCKED_SETS * len(NAMES)
