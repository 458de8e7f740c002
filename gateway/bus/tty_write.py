"""Writing a frame to a tty, waiting for room rather than spinning, and seeing it leave.

Why its own module: the serial owner and the SLCAN adapter both write to a tty opened without
blocking, and pyserial's ``write`` retries a write the kernel refuses (``EAGAIN``) at once, in
a loop with no wait: a wedged USB adapter, whose far end takes no more bytes, took a core for
as long as the write's timeout ran (and for ever with none, as python-can's SLCAN writes had).

A write returns once the kernel has the bytes; a USB adapter's driver hands them on in its
own time, a USB frame or more later. ``left_driver`` says by when it had (``TIOCOUTQ``, the
bytes still queued in the tty's driver), so that the gap after a frame that gets no reply
counts from when it can have left, not from when it was written (a UART or a pty holds
nothing back, and the answer is the first look, a moment after the write). It waits without
``tcdrain``, which has no timeout: a wedged adapter would hold the bus thread, and its
e-stops, for ever.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import select
import struct
import termios
import time
from collections.abc import Callable

from busgate.gateway.bus.clock import now

#: While a tty takes no bytes, a write is tried again this often at the least: a tty is told
#: writable only once fewer than 256 bytes wait in its driver, when a few bytes may fit before.
RETRY_S = 0.005
#: While bytes wait in a tty's driver, it is looked at this often, and for this long at most
#: (a USB adapter hands a frame on within a few of its 1 ms or 125 µs frames).
DRAIN_POLL_S = 0.0002
DRAIN_MAX_S = 0.02


def write_all(fd: int, data: bytes, timeout_s: float) -> bool:
    """Write all of ``data`` to ``fd``, waiting for room up to ``timeout_s`` in all; whether it
    all went. One ``write`` in the usual case."""
    rest = memoryview(data)
    deadline = now() + timeout_s
    while True:
        with contextlib.suppress(BlockingIOError):  # no room: waited for below
            rest = rest[os.write(fd, rest) :]
        if not rest:
            return True
        left = deadline - now()
        if left <= 0:
            return False
        select.select([], [fd], [], min(left, RETRY_S))


def queued_out(fd: int) -> int:
    """How many bytes written to ``fd`` its tty's driver still holds (0 when it cannot say:
    a descriptor that is no tty)."""
    try:
        return struct.unpack("i", fcntl.ioctl(fd, termios.TIOCOUTQ, b"\0\0\0\0"))[0]
    except OSError:
        return 0


def left_driver(fd: int, written: float, queued: Callable[[int], int] = queued_out) -> float:
    """By when the tty's driver had handed on every byte written to ``fd`` at ``written``:
    the first look that found none left (a look taken late, the thread held up after the
    write, gives a later moment than the truth: a longer gap, never a shorter one), looked
    at every ``DRAIN_POLL_S`` for ``DRAIN_MAX_S`` at most (then that moment: a wedged adapter
    is the next write's to find)."""
    give_up = written + DRAIN_MAX_S
    while queued(fd) and now() < give_up:
        time.sleep(DRAIN_POLL_S)
    return now()
