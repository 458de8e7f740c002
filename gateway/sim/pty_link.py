"""A simulated USB serial adapter: a pty pair whose other end a host opens with pyserial.

The simulator keeps both ends open, so the pty lives while no host has it open, and works on
the master end. ``unplug()`` closes both ends (the host's reads fail as on a real unplug) and
removes the ``link`` symlink; ``plug()`` makes a new pty and points the symlink at it, the way
/dev/serial/by-id follows a USB adapter that comes back under a new /dev/ttyUSBn. Only a
simulator's symlink at ``link`` (to a pty, or left dangling by one that ended) is replaced, and
only its own is removed: a file, a directory or any other link there (a udev link to a real
adapter) is refused with ``FileExistsError``, and a link that cannot be made leaves no pty open
and no staging symlink behind.

Only the thread that serves the pty may open or close it (closing a descriptor another thread
is waiting on is a race), so other threads ask with ``want(plugged)`` and the serving thread
carries the wish out in ``sync()``.
"""

from __future__ import annotations

import contextlib
import errno
import os
import threading
import tty


class PtyLink:
    """The master end of a pty, with the slave path a host opens (``path``, or ``link``)."""

    def __init__(self, link: str | None = None) -> None:
        self.link = link
        self.path = ""
        self._master = -1
        self._slave = -1
        self._wanted = threading.Event()
        self._wanted.set()
        self.plug()

    @property
    def plugged(self) -> bool:
        return self._master >= 0

    def plug(self) -> None:
        """Make a new pty (after ``unplug``) and point ``link`` at it."""
        if self.plugged:
            return
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        path = os.ttyname(slave)
        if self.link:
            try:
                _point_symlink(self.link, path)
            except OSError:
                os.close(master)
                os.close(slave)
                raise
        self._master, self._slave, self.path = master, slave, path

    def unplug(self) -> None:
        """Close the pty: the host's port fails, and the symlink goes away."""
        if not self.plugged:
            return
        if self.link and os.path.islink(self.link) and os.readlink(self.link) == self.path:
            with contextlib.suppress(FileNotFoundError):  # ours: a link made since is kept
                os.unlink(self.link)
        for fd in (self._master, self._slave):
            os.close(fd)
        self._master = self._slave = -1

    close = unplug

    def want(self, plugged: bool) -> None:
        """Ask the serving thread to plug or unplug (thread-safe)."""
        if plugged:
            self._wanted.set()
        else:
            self._wanted.clear()

    def sync(self) -> bool:
        """In the serving thread: carry out the last ``want``; return whether plugged."""
        if self._wanted.is_set():
            self.plug()
        else:
            self.unplug()
        return self.plugged

    def fileno(self) -> int:
        return self._master

    def read(self) -> bytes:
        """Whatever the host has written, without blocking (``b""`` when nothing)."""
        try:
            return os.read(self._master, 4096)
        except (BlockingIOError, OSError):
            return b""

    def write(self, data: bytes) -> int:
        """Send ``data`` to the host; bytes the host's buffer cannot take are lost, as on a wire."""
        sent = 0
        with contextlib.suppress(BlockingIOError, OSError):
            while sent < len(data):
                sent += os.write(self._master, data[sent:])
        return sent


def _point_symlink(link: str, target: str) -> None:
    """Make ``link`` a symlink to ``target`` in one rename, so a host never finds it missing;
    a link there is replaced only when it is a simulator's (``_ours``)."""
    if os.path.lexists(link) and not _ours(link):
        raise FileExistsError(
            errno.EEXIST, "exists and is not a simulator's link to a pty, so it is kept", link
        )
    staging = f"{link}.{os.getpid()}.tmp"
    os.symlink(target, staging)
    try:
        os.replace(staging, link)
    except OSError:
        os.unlink(staging)
        raise


def _ours(link: str) -> bool:
    """Whether ``link`` is a symlink a simulator made: to a pty, or to nothing any more (one
    that ended); never a udev link to a real adapter, nor a link to anyone's file."""
    if not os.path.islink(link):
        return False
    target = os.readlink(link)
    return target.startswith("/dev/pts/") or not os.path.exists(link)
