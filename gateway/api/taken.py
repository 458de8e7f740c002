"""The count of e-stops a put or query was taken off the network under, kept on the thread
that handles it (``intake`` rule 5), so that what it hands on, or hands to a bus, after
another e-stop is refused ``estopped``: sent before that e-stop, it must never move a device
after a reset that follows at once. Apart from ``intake`` so that what judges by it need not
import zenoh.
"""

from __future__ import annotations

import threading

_taken = threading.local()


def taken_under(estops: int) -> None:
    """This thread handles next what was taken when ``estops`` e-stops had been counted."""
    _taken.estops = estops


def estops_when_taken(now: int) -> int:
    """The e-stop count the put or query this thread handles was taken under; ``now`` on a
    thread that is no intake's."""
    return getattr(_taken, "estops", now)
