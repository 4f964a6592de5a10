"""The client's event loop thread stops within bounds: closing it never waits on a loop that
cannot stop, so a trainer's exit (an exception, Ctrl-C) cannot hang on it."""

from __future__ import annotations

import asyncio
import logging
import threading
import time

import pytest

from vecsim.client.pods import EventLoopThread


def test_close_stops_the_loop_and_joins_its_thread() -> None:
    loop = EventLoopThread(name="test-loop")
    assert loop.run(asyncio.sleep(0, result=3)) == 3
    loop.close()
    assert not loop.thread.is_alive() and loop.loop.is_closed()
    loop.close()  # twice: a no-op


def test_close_gives_up_on_a_loop_held_up_in_a_callback_with_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    loop = EventLoopThread(name="test-loop-held")
    release = threading.Event()
    entered = threading.Event()

    def hold() -> None:  # a callback that blocks the loop's thread, as a leaked lock would
        entered.set()
        release.wait(30)

    loop.loop.call_soon_threadsafe(hold)
    assert entered.wait(10)
    started = time.monotonic()
    try:
        with caplog.at_level(logging.WARNING, logger="vecsim.client.pods"):
            loop.close(timeout=0.5)
        waited = time.monotonic() - started
        assert waited < 10, waited  # bounded by the timeout, not by the callback
        assert loop.thread.is_alive() and not loop.loop.is_closed()
        assert any("did not stop within 0.5 s" in r.getMessage() for r in caplog.records)
    finally:
        release.set()
        loop.thread.join(10)
    assert not loop.thread.is_alive()  # the loop stopped once the callback let go
    loop.close()
    assert loop.loop.is_closed()
