"""The systemd notify protocol (``sd_notify(3)``), in the few lines it takes.

Rules of this file:

1. Under systemd (``Type=notify``) the service manager puts the path of a datagram socket in
   ``NOTIFY_SOCKET``: an absolute path, or an abstract name written with a leading ``@``. Each
   notification is one datagram of ``KEY=value`` lines (``READY=1``, ``STATUS=…``,
   ``WATCHDOG=1``, ``STOPPING=1``). Without the variable every call is a no-op, so the daemon
   calls them unconditionally.
2. Notifying never raises: systemd acts on what it does not receive (a start-up timeout, a
   watchdog timeout), so a failed send is logged and the daemon goes on.
3. ``WatchdogSec=`` reaches the service as ``WATCHDOG_USEC`` (and ``WATCHDOG_PID``: only that
   process is meant to ping; any other sees no watchdog). ``Watchdog`` pings at half that
   interval, and only while the daemon's health predicate holds, so a stuck bus thread gets
   the service restarted instead of being kept alive by a healthy event loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import time
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)


class Notifier:
    """Sends notifications to the service manager named by ``NOTIFY_SOCKET``, if any."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        environ = os.environ if environ is None else environ
        self.address = _socket_address(environ.get("NOTIFY_SOCKET", ""))
        self.watchdog_interval_s = _watchdog_interval(environ)

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def notify(self, *fields: str) -> bool:
        """Send ``fields`` (``KEY=value`` each) as one datagram; ``True`` when it was sent."""
        if self.address is None:
            return False
        try:
            with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
                sock.sendto("\n".join(fields).encode(), self.address)
        except OSError as exc:
            log.warning("systemd notification %s not sent: %s", fields, exc)
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        return self.notify("READY=1", *_status(status))

    def status(self, text: str) -> bool:
        return self.notify(*_status(text))

    def watchdog(self) -> bool:
        return self.notify("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> bool:
        return self.notify("STOPPING=1", *_status(status))


class Watchdog:
    """Pings ``notifier``'s watchdog at half its interval while ``healthy()`` holds.

    ``check()`` may be called as often as convenient; ``run(stop)`` calls it every quarter
    interval until ``stop`` is set, so one missed check still leaves time for the next ping.
    Without a watchdog (no ``WATCHDOG_USEC``) both do nothing.
    """

    def __init__(
        self,
        notifier: Notifier,
        healthy: Callable[[], bool],
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.notifier = notifier
        self.healthy = healthy
        self.clock = clock
        self.interval_s = notifier.watchdog_interval_s
        self.last_ping: float | None = None

    def check(self) -> bool:
        """Ping if half the interval has passed since the last ping and the daemon is healthy;
        ``True`` when a ping went out."""
        if self.interval_s is None:
            return False
        moment = self.clock()
        if self.last_ping is not None and moment - self.last_ping < self.interval_s / 2:
            return False
        if not self.healthy():
            return False
        self.last_ping = moment
        return self.notifier.watchdog()

    async def run(self, stop: asyncio.Event) -> None:
        if self.interval_s is None:
            return
        while not stop.is_set():
            self.check()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), self.interval_s / 4)


def _socket_address(value: str) -> str | bytes | None:
    """The ``sendto`` address of ``NOTIFY_SOCKET``: a path, or an abstract name as bytes."""
    if value.startswith("/"):
        return value
    if value.startswith("@") and len(value) > 1:
        return b"\0" + value[1:].encode()
    if value:
        log.warning("NOTIFY_SOCKET=%r is neither a path nor an abstract name; not notifying", value)
    return None


def _watchdog_interval(environ: Mapping[str, str]) -> float | None:
    """``WATCHDOG_USEC`` in seconds, when it is meant for this process (``WATCHDOG_PID``)."""
    pid = environ.get("WATCHDOG_PID")
    if pid and pid != str(os.getpid()):
        return None
    try:
        usec = int(environ.get("WATCHDOG_USEC", ""))
    except ValueError:
        return None
    return usec / 1e6 if usec > 0 else None


def _status(text: str | None) -> tuple[str, ...]:
    """A ``STATUS=`` field: one line, as systemctl status shows it."""
    return () if text is None else ("STATUS=" + " ".join(text.split()),)
