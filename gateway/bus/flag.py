"""A flag that any thread raises and one thread waits on: ``threading.Event``'s ``set``,
``clear``, ``is_set`` and ``wait``, on one lock.

``threading.Event`` is a condition variable written in Python: each wait makes a lock of its
own and queues it, a ``set`` takes the condition's lock to wake the waiters, and each woken
waiter takes that lock again before it returns. The bus threads wait on such flags at every
idle pause and every wait's last stretch, and are woken through them by every hand-over (an
e-stop, a command, a worker's next batch). On this project's host a set while another thread
waited cost 14.6 µs on an ``Event`` against 5.3 µs on a lock, and the waiter was back 25.9 µs
after it against 15.5 (docs/performance.md, "Flags on one lock").

Rules of this file:

1. Raised is the lock free, lowered is the lock held (a ``threading.Lock`` belongs to no
   thread: any thread may free it). Raising a raised flag changes nothing.
2. A wait that ends raised takes the lock and frees it again before it returns, so the flag
   stays raised, as an ``Event`` does, until it is lowered; a second waiter is woken in turn.
3. One thread lowers a flag: the one that waits on it. (Lowered by another while its waiter
   was waking, it could be raised again by that waiter's rule 2.)
"""

from __future__ import annotations

import threading


class Flag:
    """``threading.Event`` for one waiting thread, at a lock's cost (rules 1-3)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._lock.acquire()  # lowered

    def set(self) -> None:
        lock = self._lock
        if not lock.locked():  # raised already: the usual case of a busy bus, and no raise
            return
        try:  # noqa: SIM105 (contextlib.suppress would cost a context manager a raise)
            lock.release()
        except RuntimeError:  # raised by another thread meanwhile
            pass

    def clear(self) -> None:
        self._lock.acquire(False)

    def is_set(self) -> bool:
        return not self._lock.locked()

    def wait(self, timeout: float | None = None) -> bool:
        """Until the flag is raised, ``timeout`` seconds at most (``None``: for ever; none
        left: a look); whether it is."""
        if not self._lock.acquire(True, -1 if timeout is None else max(timeout, 0.0)):
            return False
        self.set()  # it stays raised (rule 2)
        return True
