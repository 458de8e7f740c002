"""An incident file written in a process of its own:
``python -m busgate.gateway.recording.incident_file PATH`` reads a snapshot of the flight
recorder's rings on stdin and writes it to PATH as MCAP (``mcap_log.McapLog``).

Why a process: a minute of 20 devices is some 200 000 messages of Python work (JSON, the
mcap writer). In the daemon that work would hold the GIL the bus threads need, and the
garbage it makes would set off collections that stop every thread at once (a follow tick
late by hundreds of milliseconds, measured). Here it has an interpreter of its own, at a
lower priority; the daemon only pickles its rings' chunks down a pipe (some 15 µs per chunk
of 256 entries).

Rules of this file:

1. stdin is the daemon's pipe and nothing else: a stream of pickles, first a ``header``
   dict, then ``(stream, entries)`` pieces (``published``, ``commands``, or ``frames`` with
   the bus as ``("frames", bus, entries)``), then ``None``. Entries are the rings' tuples,
   times in ``perf_counter`` seconds; those before the header's ``start`` are left out.
2. Exit status 0 once the file is finished (summary and index written); otherwise 1, with
   one line on stderr saying why. The daemon renames the file into place, or removes it.
3. It runs at normal priority, niced (``NICENESS``), whatever it inherited: a daemon whose
   buses ask for real-time priority starts it from a ``SCHED_FIFO`` thread, and a real-time
   writer would take a core from the bus threads for as long as it writes.
"""

from __future__ import annotations

import contextlib
import heapq
import json
import os
import pickle
import sys
from collections.abc import Iterator
from typing import IO, Any

from busgate.codecs.can_frame import CanFrame
from busgate.gateway.recording.mcap_log import McapLog
from busgate.schemas.base import client_named
from busgate.schemas.encoding import message_json

#: Of a payload that is no JSON object, this much is kept as text.
TEXT_KEPT = 256
#: The niceness of the writing process: the daemon's bus threads come first.
NICENESS = 10

#: ``(time, key, payload bytes, body)``: a message for the file, ``body`` its JSON as parsed.
Message = tuple[float, str, bytes, Any]


def recorded_command(ts: float, key: str, payload: bytes, code: str) -> dict[str, Any]:
    """A command as an incident file holds it (``schemas.recording.RecordedCommand``): a
    payload that is no JSON object the file can hold as it is (NaN, infinities) is kept as
    text, and a client is named only when its id is valid."""
    command = _json_object(payload)
    if command is None:
        text = payload[: TEXT_KEPT * 4].decode("utf-8", "replace")[:TEXT_KEPT]
        return {"ts": ts, "key": key, "client": None, "command": None, "text": text, "code": code}
    return {
        "ts": ts,
        "key": key,
        "client": client_named(command.get("client")),
        "command": command,
        "text": None,
        "code": code,
    }


def _json_object(payload: bytes) -> dict[str, Any] | None:
    """``payload`` as a JSON object that writes back as JSON, else ``None``."""
    try:
        value = json.loads(payload)
        json.dumps(value, allow_nan=False)  # NaN and infinities are no JSON
    except (ValueError, RecursionError):
        return None
    return value if isinstance(value, dict) else None


def recorded_frame(ts: float, bus: str, direction: str, data: bytes, can_id: int | None):
    """A frame as an incident file holds it (``schemas.recording.RecordedFrame``): a CAN
    frame in the codecs' text form (``CanFrame``)."""
    wire = data.hex() if can_id is None else str(CanFrame(can_id, data))
    return {"ts": ts, "bus": bus, "dir": direction, "wire": wire}


class Snapshot:
    """What came down the pipe, sorted by stream, ready to be merged in time order."""

    def __init__(self, header: dict[str, Any]) -> None:
        self.header = header
        self.start: float = header["start"]
        self.wall_offset: float = header["wall_offset"]
        self.base: str = header["base"]
        self.published: list[tuple] = []
        self.commands: list[tuple] = []
        self.frames: dict[str, list[tuple]] = {}

    def take(self, piece: tuple) -> None:
        kind, *rest = piece
        if kind == "frames":
            bus, entries = rest
            self.frames.setdefault(bus, []).extend(entries)
        else:
            (entries,) = rest
            {"published": self.published, "commands": self.commands}[kind].extend(entries)

    def messages(self) -> Iterator[Message]:
        """Every message from ``start`` on, in time order."""
        return heapq.merge(
            self._published(),
            self._commands(),
            *(self._frames(bus) for bus in self.frames),
            key=lambda message: message[0],
        )

    def _recent(self, entries: list[tuple]) -> list[tuple]:
        # A ring several threads append to (the commands) may hold neighbours out of order.
        return sorted((entry for entry in entries if entry[0] >= self.start), key=_time)

    def _published(self) -> Iterator[Message]:
        for t, key, data in self._recent(self.published):
            yield t, key, data, None

    def _commands(self) -> Iterator[Message]:
        key = f"{self.base}/commands"
        for t, on_key, payload, code in self._recent(self.commands):
            body = recorded_command(t + self.wall_offset, on_key, payload, code)
            yield t, key, message_json(body), body

    def _frames(self, bus: str) -> Iterator[Message]:
        key = f"{self.base}/bus/{bus}/frames"
        for t, direction, data, can_id in self._recent(self.frames[bus]):
            body = recorded_frame(t + self.wall_offset, bus, direction, data, can_id)
            yield t, key, message_json(body), body


def _time(entry: tuple) -> float:
    return entry[0]


def read_snapshot(stream: IO[bytes]) -> Snapshot:
    """The daemon's pickles (rule 1), up to the closing ``None``."""
    snapshot = Snapshot(pickle.load(stream))
    while (piece := pickle.load(stream)) is not None:
        snapshot.take(piece)
    return snapshot


def write(snapshot: Snapshot, out: IO[bytes]) -> int:
    """The snapshot as MCAP into ``out``; how many messages."""
    mcap = McapLog(out, snapshot.header["prefix"])
    for t, key, data, body in snapshot.messages():
        mcap.add(key, data, int((t + snapshot.wall_offset) * 1e9), body=body)
    mcap.metadata(snapshot.header["metadata_name"], snapshot.header["metadata"])
    mcap.finish()
    return mcap.messages


def main(argv: list[str]) -> int:
    with contextlib.suppress(OSError, AttributeError):  # rule 3 (Linux's scheduler calls)
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError):
        os.nice(NICENESS)
    try:
        snapshot = read_snapshot(sys.stdin.buffer)
        with open(argv[0], "wb") as out:
            count = write(snapshot, out)
    except (OSError, EOFError, pickle.UnpicklingError) as exc:
        print(f"incident file {argv[0]}: {exc}", file=sys.stderr)
        return 1
    print(count)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
