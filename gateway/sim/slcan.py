"""A simulated SLCAN (Lawicel ASCII) USB-CAN adapter, as CANable and USBtin firmwares speak it.

The host side is a pty that python-can's ``slcan`` interface opens; the CAN side is a
python-can ``virtual`` channel on which a ``CanSimulator`` serves the devices. Commands are
``\\r``-terminated ASCII: ``S0``–``S8`` bitrate, ``O`` open, ``L`` open listen-only, ``C`` close,
``V`` version, ``N`` serial number, ``F`` status, ``tIIIL<data>`` send a standard frame. ``\\r``
acknowledges, BEL (``\\a``) refuses, and frames from the bus reach the host as ``tIIIL<data>\\r``
only while the channel is open. Extended (``T``) and remote frames are not part of our
devices' protocols and are refused.
"""

from __future__ import annotations

import select
import threading

import can

from busgate.gateway.sim.pty_link import PtyLink

OK, ERROR = b"\r", b"\a"
BITRATES = {
    "S0": 10_000,
    "S1": 20_000,
    "S2": 50_000,
    "S3": 100_000,
    "S4": 125_000,
    "S5": 250_000,
    "S6": 500_000,
    "S7": 800_000,
    "S8": 1_000_000,
}
MAX_LINE = 64


class SlcanAdapter:
    """Bridges a pty speaking SLCAN to a python-can virtual channel."""

    def __init__(self, channel: str, *, link: PtyLink | None = None) -> None:
        self.link = link or PtyLink()
        self.bitrate: int | None = None
        self.is_open = False
        self._bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
        self._line = bytearray()
        self._write_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._host_to_bus, name="slcan-rx", daemon=True),
            threading.Thread(target=self._bus_to_host, name="slcan-tx", daemon=True),
        ]

    @property
    def port(self) -> str:
        return self.link.link or self.link.path

    def start(self) -> SlcanAdapter:
        for thread in self._threads:
            thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            if thread.is_alive():
                thread.join(timeout=2)
        self._bus.shutdown()
        self.link.close()

    def unplug(self) -> None:
        """Pull the adapter: the pty goes away and the channel closes."""
        self.link.want(False)

    def replug(self) -> None:
        """Plug it back in: a new pty, closed until the host opens the channel again."""
        self.link.want(True)

    def _host_to_bus(self) -> None:
        while not self._stop.is_set():
            with self._write_lock:
                plugged = self.link.sync()
                if not plugged:
                    self.is_open = False
                    self._line.clear()
            if not plugged:
                self._stop.wait(0.02)
                continue
            readable, _, _ = select.select([self.link], [], [], 0.05)
            if readable:
                for line in self._lines(self.link.read()):
                    self._write(self._execute(line))

    def _lines(self, data: bytes) -> list[str]:
        self._line += data
        *complete, rest = self._line.split(b"\r")
        self._line = bytearray(rest[-MAX_LINE:])
        return [line.decode("ascii", "replace") for line in complete]

    def _execute(self, line: str) -> bytes:
        if not line:  # a bare CR: hosts send it to flush, firmwares acknowledge it
            return OK
        if line in BITRATES and not self.is_open:
            self.bitrate = BITRATES[line]
            return OK
        if line in ("O", "L") and not self.is_open and self.bitrate is not None:
            self.is_open = True
            return OK
        if line == "C":
            self.is_open = False
            return OK
        if line in ("V", "v", "N", "F"):
            return {"V": b"V1013\r", "v": b"v1013\r", "N": b"NBG01\r", "F": b"F00\r"}[line]
        if line.startswith("t") and self.is_open:
            return self._transmit(line)
        return ERROR

    def _transmit(self, line: str) -> bytes:
        try:
            ident, length = int(line[1:4], 16), int(line[4], 16)
            data = bytes.fromhex(line[5 : 5 + 2 * length])
        except (ValueError, IndexError):
            return ERROR
        if len(data) != length or length > 8 or len(line) != 5 + 2 * length:
            return ERROR
        self._bus.send(can.Message(arbitration_id=ident, data=data, is_extended_id=False))
        return b"z\r"

    def _bus_to_host(self) -> None:
        while not self._stop.is_set():
            message = self._bus.recv(timeout=0.05)
            if message is None or message.is_extended_id or not self.is_open:
                continue
            data = bytes(message.data)
            self._write(f"t{message.arbitration_id:03X}{len(data)}{data.hex().upper()}\r".encode())

    def _write(self, data: bytes) -> None:
        with self._write_lock:
            if self.link.plugged:
                self.link.write(data)
