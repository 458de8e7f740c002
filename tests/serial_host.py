"""A test playing the host on a simulator's pty with pyserial: one exchange, and silence."""

from __future__ import annotations

import serial


def exchange(host: serial.Serial, frame: str, reply_bytes: int) -> bytes:
    """Write ``frame`` (hex) and read up to ``reply_bytes`` within the port's timeout."""
    host.write(bytes.fromhex(frame))
    return host.read(reply_bytes)


def assert_silent(host: serial.Serial, wait_s: float = 0.15) -> None:
    """Nothing comes back within ``wait_s``."""
    host.timeout, before = wait_s, host.timeout
    assert host.read(1) == b""
    host.timeout = before
