"""python-can's ``slcan`` interface, reading what the adapter sent in one call, not a byte a call.

python-can 4.6 reads an SLCAN adapter one byte per call (a ``select`` and a ``read`` each): a
frame is a line of some 22 characters, so 22 round trips into the kernel. Five ZLAC706
heartbeating every 10 ms make 1,000 frames a second on a bus; four such buses took one core of
this machine whole and fell behind (the gateway published a fifth of the heartbeats).
Upstream's fix (hardbyte/python-can#2028) is not in a release yet; this subclass is ours until it
is, and the test that reads a stream of lines through it and through python-can's own keeps the
two telling the same frames.

Rules of this file:

1. Only ``_read`` (one line of the adapter, through its terminator) and ``_write`` (rule 4)
   are replaced: opening, sending, closing and the parsing of a line into a ``can.Message``
   stay python-can's (its frame checked against its line: rule 3).
   Around the opening, the adapter's tty is locked as the serial owner locks its ports
   (``flock``, as pyserial's ``exclusive=True``), before python-can writes a byte to it, and
   held until ``shutdown``: a second gateway given the same adapter is refused, naming the
   process that holds it (python-can opens the tty unlocked, so two gateways would each take
   half of the adapter's lines).
2. A read takes everything the adapter has sent so far; the lines it holds beyond the one it
   returns are handed out by the next reads, before the adapter is asked again. ``has_line``
   tells the owner that one is there (its descriptor no longer does).
3. A line is taken out before it is read: one that is no ASCII, runs past any frame's length
   without a terminator, or is shorter than the frame it names (python-can's parsing indexes
   past its end, or makes a frame of fewer bytes than its length says), raises ``ValueError``
   once (the owner counts one frame lost) and the next line reads as it should. A failing
   port is python-can's ``CanOperationError``, as its own reads raise.
4. A line goes to an adapter's tty by ``tty_write.write_all``, within the send's timeout
   (``WRITE_TIMEOUT_S`` while opening), and is not waited out (``tcdrain``): python-can's
   write spun a core, with no timeout while opening, on an adapter that took no more bytes,
   and its drain could wait for ever. An adapter that takes none is python-can's
   ``CanOperationError``. A channel that is no file (a ``socket://`` URL) is written by
   python-can.
"""

from __future__ import annotations

import fcntl
import os

from can import Message
from can.exceptions import CanInitializationError, CanOperationError, error_check
from can.interfaces.slcan import slcanBus

from busgate.gateway.bus.clock import now
from busgate.gateway.bus.port_access import describe_open_error
from busgate.gateway.bus.tty_write import write_all

#: How long a line written while opening (python-can's commands, no timeout of their own) may
#: wait for the adapter to take it (rule 4).
WRITE_TIMEOUT_S = 0.5
#: The line ends: CR after a frame or an acknowledgement, BEL after a refused command.
_TERMINATORS = (b"\r", b"\a")
#: Longer than any line an adapter sends (a CAN FD frame with an extended identifier: 1 + 8 +
#: 1 + 128 characters and its terminator); what runs past it unterminated is garbage.
MAX_LINE = 160


class SlcanBus(slcanBus):
    """An SLCAN adapter, as python-can's ``slcan`` interface, read a chunk at a time."""

    def __init__(self, channel: str, *args, **kwargs) -> None:
        self._lock = _locked(channel)
        try:
            super().__init__(channel, *args, **kwargs)
        except BaseException:
            self._unlock()
            raise

    def shutdown(self) -> None:
        try:
            super().shutdown()
        finally:
            self._unlock()

    def _unlock(self) -> None:
        lock, self._lock = self._lock, None
        if lock is not None:
            os.close(lock)

    @property
    def has_line(self) -> bool:
        """Whether a whole line of the adapter is already read in, waiting to be taken."""
        return self._line_end() >= 0

    def _write(self, string: str) -> None:
        """One line to the adapter (rule 4)."""
        port = self.serialPortOrig
        if self._lock is None:  # no tty of ours
            super()._write(string)
            return
        timeout = WRITE_TIMEOUT_S if port.write_timeout is None else port.write_timeout
        if not write_all(port.fileno(), string.encode() + self.LINE_TERMINATOR, timeout):
            raise CanOperationError(
                f"Could not write to serial device: the adapter took no bytes for {timeout:g} s"
            )

    def _recv_internal(self, timeout: float | None) -> tuple[Message | None, bool]:
        """python-can's, a line too short for the frame it names refused (rule 3)."""
        try:
            message, filtered = super()._recv_internal(timeout)
        except IndexError as exc:
            raise ValueError("an SLCAN line shorter than the frame it names") from exc
        if message is not None and not message.is_remote_frame and len(message.data) != message.dlc:
            raise ValueError(
                f"an SLCAN line of {len(message.data)} data bytes for a length of {message.dlc}"
            )
        return message, filtered

    def _read(self, timeout: float | None) -> str | None:
        """The adapter's next line (its terminator included), waiting ``timeout`` seconds at
        most for it (``None``: as long as it takes); ``None`` when none came."""
        deadline = None if timeout is None else now() + timeout
        port = self.serialPortOrig
        while (line := self._take_line()) is None:
            with error_check("Could not read from serial device"):
                waiting = port.in_waiting
                if not waiting and deadline is not None and now() >= deadline:
                    return None
                # With nothing there, the port's own timeout (1 ms) bounds the wait for a byte.
                self._buffer += port.read(waiting or 1)
        return line

    def _line_end(self) -> int:
        """Where the first whole line read in ends (its terminator), -1 when none is in."""
        ends = [at for at in (self._buffer.find(end) for end in _TERMINATORS) if at >= 0]
        return min(ends, default=-1)

    def _take_line(self) -> str | None:
        """The first whole line read in, taken out of the buffer (rule 3)."""
        buffer = self._buffer
        end = self._line_end() + 1
        if not end:
            if len(buffer) > MAX_LINE:
                del buffer[:]
                raise ValueError(f"an SLCAN line of more than {MAX_LINE} characters")
            return None
        line = bytes(buffer[:end])
        del buffer[:end]
        return line.decode("ascii")  # a UnicodeDecodeError is a ValueError: one line lost


def _locked(channel: object) -> int | None:
    """A descriptor of ``channel``'s tty holding its lock (rule 1); ``None`` for a channel
    that is no file (python-can's ``socket://`` URLs). ``CanInitializationError`` in
    ``port_access``'s words when it cannot be had (held by another process, missing, not
    ours to open)."""
    path = channel.split("@", 1)[0] if isinstance(channel, str) else ""  # "tty@baud"
    if not path.startswith("/"):
        return None  # python-can says what is wrong with it
    try:
        lock = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise CanInitializationError(describe_open_error(path, exc)) from exc
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as exc:
        os.close(lock)
        raise CanInitializationError(describe_open_error(path, exc)) from exc
    return lock
