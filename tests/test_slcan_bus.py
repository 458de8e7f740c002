"""busgate's reads of an SLCAN adapter (``gateway/bus/slcan.py``) against python-can's own: the
same lines on a pty, in chunks split anywhere, make the same frames; a garbled line is one
``ValueError`` and the next line reads."""

from __future__ import annotations

import os
import select
import threading
import time
import tty

import can
import pytest
from can.interfaces.slcan import slcanBus

from busgate.gateway.bus.slcan import MAX_LINE, SlcanBus

#: An adapter's lines of every kind python-can reads: acknowledgements (CR), a refusal (BEL),
#: standard and extended frames, remote frames, frames with no data, CAN FD with and without
#: the bit-rate switch.
LINES = (
    b"\r",
    b"t0018000000e10005fff6\r",
    b"\a",
    b"T1ABCDEF03112233\r",
    b"t7FF0\r",
    b"r0012\r",
    b"R000000054\r",
    b"d1239" + b"AB" * 12 + b"\r",
    b"B0000012FA" + b"5A" * 16 + b"\r",
    b"t0038000100200000000F\r",
)


def drain(master: int) -> None:
    """Read what the bus told the adapter (its open commands), so the pty never fills."""
    while select.select([master], [], [], 0)[0]:
        os.read(master, 4096)


def frames(bus: can.BusABC, count: int) -> list[tuple]:
    got = []
    while len(got) < count:
        message = bus.recv(timeout=5)
        assert message is not None, f"{len(got)} of {count} frames came"
        got.append(
            (message.arbitration_id, message.is_extended_id, message.is_remote_frame,
             message.is_fd, message.bitrate_switch, message.dlc, bytes(message.data))
        )
    return got


@pytest.fixture
def adapter():
    """The adapter's side of a pty (the test writes its lines there) and the tty a bus opens."""
    opened = []

    def make() -> tuple[int, str]:
        master, slave = os.openpty()
        opened.extend((master, slave))
        return master, os.ttyname(slave)

    yield make
    for fd in opened:
        os.close(fd)


def read_through(kind: type[slcanBus], stream: bytes, chunk: int, adapter) -> list[tuple]:
    master, path = adapter()
    bus = kind(channel=path, bitrate=500_000, sleep_after_open=0)
    try:
        drain(master)
        for start in range(0, len(stream), chunk):
            os.write(master, stream[start : start + chunk])
        return frames(bus, 8)
    finally:
        bus.shutdown()


@pytest.mark.parametrize("chunk", [1, 7, 4096], ids=["byte-by-byte", "split-anywhere", "at-once"])
def test_the_lines_make_the_frames_python_cans_own_reads_make(chunk, adapter) -> None:
    stream = b"".join(LINES)
    ours = read_through(SlcanBus, stream, chunk, adapter)
    assert ours == read_through(slcanBus, stream, chunk, adapter)
    assert ours[0] == (1, False, False, False, False, 8, bytes.fromhex("000000e10005fff6"))


@pytest.fixture
def bus_and_adapter(adapter):
    master, path = adapter()
    bus = SlcanBus(channel=path, bitrate=500_000, sleep_after_open=0, timeout=5.0)
    drain(master)
    yield bus, master
    bus.shutdown()


@pytest.mark.parametrize("garbled", [
    b"t0018\xff\xfe000000000000\r",  # no ASCII
    b"t1\r", b"T1234567\r", b"r12\r", b"d1239\r",  # too short for what they say they are
    b"d123f" + b"00" * 4 + b"\r",  # a CAN FD length code past the table's
])
def test_a_garbled_line_is_one_frame_lost(bus_and_adapter, garbled) -> None:
    bus, master = bus_and_adapter
    os.write(master, garbled + LINES[1])
    with pytest.raises(ValueError):
        bus.recv(timeout=5)
    assert frames(bus, 1)[0][0] == 1


def test_a_line_past_any_frame_without_its_end_is_dropped(bus_and_adapter) -> None:
    bus, master = bus_and_adapter
    os.write(master, b"t" * (MAX_LINE + 1))
    with pytest.raises(ValueError):
        bus.recv(timeout=5)
    os.write(master, LINES[1] + LINES[1])
    assert frames(bus, 1)[0][0] == 1
    assert bus.has_line  # the second, read in with the first
    assert frames(bus, 1)[0][0] == 1
    assert not bus.has_line


def test_a_look_at_a_quiet_adapter_does_not_wait(bus_and_adapter) -> None:
    """python-can's own waits out its serial timeout (here 5 s) for a byte that does not come."""
    bus, _ = bus_and_adapter
    started = time.monotonic()
    assert bus.recv(timeout=0) is None
    assert time.monotonic() - started < 2.5  # not the port's 5 s: half of it, for a busy host


def test_an_adapter_one_bus_holds_is_refused_to_another_naming_the_holder(adapter) -> None:
    master, path = adapter()
    bus = SlcanBus(channel=path, bitrate=500_000, sleep_after_open=0)
    try:
        drain(master)
        with pytest.raises(can.CanInitializationError) as refused:
            SlcanBus(channel=f"{path}@115200", bitrate=500_000, sleep_after_open=0)
        assert str(refused.value).startswith(f"{path} is locked by another process (pid "
                                             f"{os.getpid()}: ")
        assert not select.select([master], [], [], 0.05)[0]  # nothing written to the adapter
    finally:
        bus.shutdown()
    again = SlcanBus(channel=path, bitrate=500_000, sleep_after_open=0)  # let go at shutdown
    again.shutdown()


def test_an_adapter_that_takes_no_bytes_fails_the_open_waiting_not_spinning(adapter) -> None:
    """Its tty full (the adapter stopped reading): python-can's open spun a core in its first
    write for ever. The write waits for room up to its timeout, then the open fails."""
    master, path = adapter()
    filler = os.open(path, os.O_RDWR | os.O_NONBLOCK | os.O_NOCTTY)
    tty.setraw(filler)  # as pyserial leaves it
    try:
        refused = 0
        while refused < 10:  # until the kernel takes no byte more, for a while
            try:
                os.write(filler, b"\0")
                refused = 0
            except BlockingIOError:
                refused += 1
                time.sleep(0.01)
        outcome: list = []

        def open_it() -> None:  # in a thread of its own: a spin for ever fails, not hangs
            cpu, started = time.thread_time(), time.monotonic()
            try:
                SlcanBus(channel=path, bitrate=500_000, sleep_after_open=0)
            except can.CanError as exc:
                outcome.extend((exc, time.thread_time() - cpu, time.monotonic() - started))

        opening = threading.Thread(target=open_it, daemon=True)
        opening.start()
        opening.join(10)
        assert not opening.is_alive(), "the open still writing after 10 s"
        refusal, cpu_s, waited_s = outcome
        assert "the adapter took no bytes for 0.5 s" in str(refusal)
        assert cpu_s < waited_s / 4, "it waited for room, it did not spin"
    finally:
        os.close(filler)
    drain(master)
    SlcanBus(channel=path, bitrate=500_000, sleep_after_open=0).shutdown()  # let go: no lock
