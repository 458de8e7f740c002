"""One log format for the gateway's processes (the daemon, its workers, the demo), with the
journal's priority on each line when systemd's journal takes the process's stderr.

journald files a line that does not start ``<N>`` at the unit's default priority (info):
``journalctl -p warning -u busgate`` then showed no warning or error at all. Under the journal
(``JOURNAL_STREAM`` names the stream stderr is: systemd.exec(5)) each line starts with its
level's syslog priority, which journald takes off and keeps; on a terminal nothing changes.
"""

from __future__ import annotations

import logging
import os
import sys

FORMAT = "%(levelname)s %(name)s: %(message)s"
#: syslog's priority of each logging level (sd-daemon(3): ``<3>`` error … ``<7>`` debug).
PRIORITIES = {logging.CRITICAL: 2, logging.ERROR: 3, logging.WARNING: 4, logging.INFO: 6}
DEBUG_PRIORITY = 7


class JournalFormatter(logging.Formatter):
    """``FORMAT``, each line of a record led by its priority (a traceback's lines too: each
    is a journal entry of its own)."""

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{PRIORITIES.get(record.levelno, DEBUG_PRIORITY)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines())


def configure(level: str | int) -> None:
    """Log at ``level`` on stderr, in ``FORMAT``, with priorities for the journal."""
    handler = logging.StreamHandler()
    handler.setFormatter(
        JournalFormatter(FORMAT) if to_the_journal() else logging.Formatter(FORMAT)
    )
    logging.basicConfig(level=level, handlers=[handler])


def to_the_journal() -> bool:
    """Whether stderr is the journal's stream: ``JOURNAL_STREAM`` is its ``device:inode``."""
    stream = os.environ.get("JOURNAL_STREAM", "")
    try:
        device, inode = (int(part) for part in stream.split(":"))
        found = os.fstat(sys.stderr.fileno())
    except (ValueError, OSError):
        return False
    return (found.st_dev, found.st_ino) == (device, inode)
