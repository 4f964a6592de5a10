"""``service.runner.ports``: new ports come from below the kernel's ephemeral range, at random,
and never one that a listener or ``avoid`` holds."""

from __future__ import annotations

import socket

import pytest

from service.runner import ports


def test_a_block_lies_below_the_ephemeral_range_and_every_port_of_it_binds():
    first = ports.ephemeral_ports_from()
    for n in (1, 4, 17):
        base = ports.free_port_block(n)
        assert ports.PICK_FROM <= base and base + n <= first
        assert all(ports.port_free("127.0.0.1", port) for port in range(base, base + n))
    assert ports.PICK_FROM <= ports.free_port() < first


def test_a_block_a_listener_holds_a_port_of_or_that_avoid_names_is_passed_over(monkeypatch):
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        held = listener.getsockname()[1]
        free = ports.free_port_block(3)
        picks = iter([held - 1, free + 1, free])  # a block over the listener, one over `avoid`, a free one
        monkeypatch.setattr(ports._RANDOM, "randrange", lambda low, high: next(picks))
        monkeypatch.setattr(ports, "ephemeral_ports_from", lambda: 65000)
        assert ports.free_port_block(3, avoid={free + 3}) == free


def test_no_free_block_in_the_attempts_given_is_an_error_naming_the_block(monkeypatch):
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        held = listener.getsockname()[1]
        monkeypatch.setattr(ports._RANDOM, "randrange", lambda low, high: held)
        monkeypatch.setattr(ports, "ephemeral_ports_from", lambda: 65000)
        with pytest.raises(RuntimeError, match="no 2 consecutive free ports on 127.0.0.1"):
            ports.free_port_block(2, attempts=5)
    with pytest.raises(ValueError, match="n >= 1"):
        ports.free_port_block(0)


def test_where_too_few_ports_lie_below_the_ephemeral_range_the_kernel_picks(monkeypatch):
    monkeypatch.setattr(ports, "ephemeral_ports_from", lambda: ports.PICK_FROM + 500)
    monkeypatch.setattr(ports._RANDOM, "randrange", lambda low, high: pytest.fail("picked at random"))
    assert ports.port_free("127.0.0.1", ports.free_port_block(2))


@pytest.mark.parametrize("text, first", [("20000\t60999\n", 20000), ("", 32768), ("ports", 32768), ("80 90", 32768)])
def test_the_ephemeral_range_is_read_from_the_kernel_or_taken_as_linuxs_default(tmp_path, text, first):
    path = tmp_path / "ip_local_port_range"
    path.write_text(text)
    assert ports.ephemeral_ports_from(path) == first
    assert ports.ephemeral_ports_from(tmp_path / "missing") == 32768
