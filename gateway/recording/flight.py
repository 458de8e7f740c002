"""The daemon's flight recorder: the last seconds of everything, written out when something
goes wrong.

It keeps, in rings (``ring.Ring``) of ``[recorder].seconds``: every message the gateway
publishes (states, events, bus statistics, trajectory feedback: key and bytes as sent), every
command it was sent (key, payload, and the code it answered), and every frame on every bus
(bytes and the host's time, handed over by each bus owner's ``tap`` on its own thread). An
e-stop, a fault raised, a bus going down, or SIGUSR1 triggers an incident: ``AFTER_S`` later
(so that the stop itself is in it) the rings are written as one MCAP file in ``[recorder].dir``
(the channels ``busgate record`` writes, plus ``<base>/commands`` and
``<base>/bus/<bus>/frames``), and the oldest files are pruned to ``max_total_mb``.

Rules of this file:

1. Nothing here delays a frame: a bus thread only appends a tuple of plain values to its
   ring (``tap``); the file is built and written by a process of its own at a lower priority
   (``incident_file``: its work would hold the GIL, and its garbage set off collections
   that stop every thread), fed the rings' chunks down a pipe by the recorder's thread.
2. A file is complete or absent: it is written as ``*.mcap.part`` and renamed once finished.
3. Triggers that come while an incident is gathered or written, or within ``HOLDOFF_S`` of
   the last one, go into the next file, whose metadata names each (the first
   ``TRIGGERS_NAMED`` different ones): a device whose faults flap is written every
   ``HOLDOFF_S``, not on each flap.
4. Shutdown writes a pending incident after the buses have stopped (their last frames in it),
   never before: the devices' safe state comes first.
5. The newest incident matters most (the e-stop's own, say): one whose write fails on a
   disk with no room left (less than the largest incident file there) makes room by
   taking the oldest files away, and is written again, once. On a full disk the newest
   was lost and the oldest kept, for good (an audit).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import pickle
import re
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

from busgate.errors import BusgateError
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.owner import Tap
from busgate.gateway.recording.ring import Ring
from busgate.schemas.config import RecorderSection
from busgate.schemas.events import BUS_DOWN_REASON, WORKER_ENDED_REASON
from busgate.schemas.files import FileRefused, make_folder

log = logging.getLogger(__name__)

#: How long after a trigger the incident is written: the stop and its answers are in it.
AFTER_S = 1.0
#: The least time between two incident files (rule 3).
HOLDOFF_S = 10.0
#: The most entries, and bytes, a ring holds per second of ``seconds``, so that its memory is
#: bounded whatever comes (a peer's commands too); past these rates a ring holds fewer
#: seconds. A UART bus at 921600 baud carries under 2000 frames, 92 KB, a second; 20 devices
#: at full rate publish some 2000 states, 0.7 MB, a second.
FRAMES_PER_S = 5_000
FRAME_BYTES_PER_S = 256 * 1024
MESSAGES_PER_S = 5_000
MESSAGE_BYTES_PER_S = 2 * 1024 * 1024
#: The module that writes the file, in a process of its own (rule 1).
WRITER = "busgate.gateway.recording.incident_file"
PICKLE_PROTOCOL = 5
#: The most triggers one file names (each once): a peer's flood of e-stops is one line.
TRIGGERS_NAMED = 32
INCIDENT_GLOB = "incident-*.mcap"
METADATA = "incident"


@dataclass(frozen=True, slots=True)
class Trigger:
    """Why an incident is written: ``slug`` for the file name, ``text`` for people."""

    slug: str
    text: str


def trigger_of(event: dict[str, Any], bus_of: dict[str, str]) -> Trigger | None:
    """The trigger an event is (an e-stop, a fault raised, a device offline because its bus
    went down or its bus's worker ended), or ``None``."""
    kind, device = event.get("type"), str(event.get("device"))
    if kind == "estop":
        sender = event.get("client")
        return Trigger("estop", f"e-stop{f' from {sender}' if sender else ''}")
    if kind == "fault" and event.get("raised"):
        return Trigger(f"fault-{device}", f"fault on {device}: {', '.join(event['raised'])}")
    if kind == "offline" and event.get("reason") == BUS_DOWN_REASON:
        bus = bus_of.get(device, device)
        return Trigger(f"bus-down-{bus}", f"bus {bus} down")
    if kind == "offline" and str(event.get("reason")).startswith(WORKER_ENDED_REASON):
        bus = bus_of.get(device, device)
        return Trigger(f"worker-ended-{bus}", f"the worker of bus {bus} ended")
    return None


class FlightRecorder:
    """The rings of one gateway, and the incidents written from them."""

    def __init__(
        self,
        settings: RecorderSection,
        *,
        prefix: str,
        gateway: str,
        buses: dict[str, Iterable[str]],
        version: str,
    ) -> None:
        self.settings = settings
        self.folder = Path(settings.dir)
        self.prefix, self.gateway, self.version = prefix, gateway, version
        self.base = f"{prefix}/{gateway}"
        seconds = settings.seconds
        self.frames = {bus: _ring(seconds, FRAMES_PER_S, FRAME_BYTES_PER_S) for bus in buses}
        self.bus_of = {device: bus for bus, devices in buses.items() for device in devices}
        self.published = _ring(seconds, MESSAGES_PER_S, MESSAGE_BYTES_PER_S)
        self.commands = _ring(seconds, MESSAGES_PER_S, MESSAGE_BYTES_PER_S)
        self._events_key = f"{self.base}/events"
        self._pending: list[Trigger] = []
        self._pending_lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake: asyncio.Event | None = None
        self._writer = ThreadPoolExecutor(1, thread_name_prefix="incident")

    # -- start -------------------------------------------------------------------------------

    def prepare(self) -> None:
        """Make the folder (refusing, in one line, one that cannot be written) and remove
        what a crash left half written."""
        where = "(the [recorder] dir of the config)"
        try:
            make_folder(self.folder)
            probe = self.folder / f".busgate-write-test-{os.getpid()}"
            probe.write_bytes(b"")
            probe.unlink()
        except FileRefused as exc:
            raise BusgateError(f"recorder: {exc} {where}") from exc
        except OSError as exc:
            raise BusgateError(
                f"recorder: cannot write incident files in {self.folder}: "
                f"{exc.strerror or exc} {where}"
            ) from exc
        for part in self.folder.glob(INCIDENT_GLOB + ".part"):
            with contextlib.suppress(OSError):
                part.unlink()

    # -- what comes in (any thread) ------------------------------------------------------------

    def tap(self, bus: str) -> Tap:
        """What the bus owner of ``bus`` calls with each frame (rule 1)."""
        return self.frames[bus].append

    def on_published(self, key: str, body: dict[str, Any], data: bytes) -> None:
        """A message the gateway published (``body`` as ``data`` encodes it)."""
        self.published.append((now(), sys.intern(key), data))
        if key == self._events_key:
            trigger = trigger_of(body, self.bus_of)
            if trigger is not None:
                self.trigger(trigger)

    def on_command(
        self, key: str, payload: bytes, reply: dict[str, Any] | None, came: float | None = None
    ) -> None:
        """A command and its reply (``None``: taken, with nothing to answer), dated when it
        came (``None``: now; an e-stop is told after its frames may have gone)."""
        self.commands.append(
            (now() if came is None else came, sys.intern(key), payload, _code(reply))
        )

    def trigger(self, trigger: Trigger) -> None:
        """Ask for an incident file (any thread)."""
        with self._pending_lock:
            if trigger not in self._pending and len(self._pending) < TRIGGERS_NAMED:
                self._pending.append(trigger)
        loop, wake = self._loop, self._wake
        if loop is not None and wake is not None and not loop.is_closed():
            loop.call_soon_threadsafe(wake.set)

    # -- incidents (the loop, then the writer's thread) ---------------------------------------

    async def run(self, stop: asyncio.Event) -> None:
        """Write an incident after each trigger (rule 3) until ``stop``; what is pending then
        is for ``flush`` (rule 4)."""
        self._loop, self._wake = asyncio.get_running_loop(), asyncio.Event()
        if self._pending:
            self._wake.set()
        while not stop.is_set():
            await _unless(stop, self._wake.wait())
            await _unless(stop, asyncio.sleep(AFTER_S))
            if stop.is_set():
                return
            self._wake.clear()
            writing = self._loop.run_in_executor(self._writer, self.write_pending)
            await _unless(stop, asyncio.shield(writing))
            await _unless(stop, asyncio.sleep(HOLDOFF_S))

    def flush(self) -> None:
        """Write what is pending and wait for the writer (at shutdown, rule 4)."""
        self._writer.submit(self.write_pending).result()
        self._writer.shutdown(wait=True)

    def write_pending(self) -> Path | None:
        """The pending triggers' incident file, written now (``None`` when none is pending
        or it could not be written: that is logged)."""
        with self._pending_lock:
            triggers, self._pending = self._pending, []
        if not triggers:
            return None
        for again in (False, True):
            try:
                path = self.write_incident(triggers, now())
                break
            except Exception:  # a full disk, a folder gone: said, and the gateway goes on
                if again or not self._room_made():  # rule 5
                    log.exception("incident (%s) not written", "; ".join(t.text for t in triggers))
                    return None
        self._prune(path)
        return path

    def _room_made(self) -> bool:
        """Whether the oldest incident files went to leave the disk room for one as large as
        the largest there (rule 5); none go while it has that room."""
        files = self._incident_files()
        room = max((size for _, _, size, _ in files), default=0)
        made = False
        for _, _, _, path in sorted(files):
            with contextlib.suppress(OSError):
                if shutil.disk_usage(self.folder).free > room:
                    break
                path.unlink()
                made = True
                log.warning("incident pruned: %s (the disk had no room for a new one)", path)
        return made

    def write_incident(self, triggers: list[Trigger], at: float) -> Path:
        """The rings' last ``seconds`` before ``at`` (a ``now()`` time) as one MCAP file,
        written by a process of its own (``incident_file``: rule 1)."""
        wall_offset = time.time() - now()
        stamp = time.strftime("%Y%m%dT%H%M%S", time.gmtime(at + wall_offset))
        millis = int((at + wall_offset) % 1 * 1000)
        name = f"incident-{self.gateway}-{stamp}.{millis:03d}Z-{_slug(triggers[0].slug)}.mcap"
        path = self.folder / name
        part = path.with_name(name + ".part")
        header = {
            "prefix": self.prefix,
            "base": self.base,
            "start": at - self.settings.seconds,
            "wall_offset": wall_offset,
            "metadata_name": METADATA,
            "metadata": {
                "gateway": self.gateway,
                "triggers": "; ".join(trigger.text for trigger in triggers),
                "triggered_at": f"{at + wall_offset:.6f}",
                "seconds": f"{self.settings.seconds:g}",
                "version": self.version,
            },
        }
        with subprocess.Popen(
            [sys.executable, "-m", WRITER, str(part)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
        ) as writer:
            assert writer.stdin is not None
            with contextlib.suppress(BrokenPipeError):  # it ended: its stderr says why
                self._send(writer.stdin, header)
            out, err = writer.communicate()
        if writer.returncode != 0:
            with contextlib.suppress(OSError):
                part.unlink()
            complaint = err.decode(errors="replace").strip().splitlines()
            raise OSError(complaint[-1] if complaint else f"its writer exited {writer.returncode}")
        os.replace(part, path)
        log.warning(
            "incident written: %s (%s; %s messages, %.0f KiB)",
            path,
            "; ".join(trigger.text for trigger in triggers),
            out.decode().strip(),
            path.stat().st_size / 1024,
        )
        return path

    def _send(self, pipe: IO[bytes], header: dict[str, Any]) -> None:
        """The snapshot down the writer's pipe, chunk by chunk (``incident_file`` rule 1):
        each pickle holds the GIL for microseconds, the pipe's writes none."""
        start = header["start"]
        pickle.dump(header, pipe, PICKLE_PROTOCOL)
        for chunk in self.published.chunks(start):
            pickle.dump(("published", chunk), pipe, PICKLE_PROTOCOL)
        for chunk in self.commands.chunks(start):
            pickle.dump(("commands", chunk), pipe, PICKLE_PROTOCOL)
        for bus, ring in self.frames.items():
            for chunk in ring.chunks(start):
                pickle.dump(("frames", bus, chunk), pipe, PICKLE_PROTOCOL)
        pickle.dump(None, pipe, PICKLE_PROTOCOL)

    def _incident_files(self) -> list[tuple[float, str, int, Path]]:
        """Each incident file of the folder: when it was written, its name, size and path."""
        files = []
        for path in self.folder.glob(INCIDENT_GLOB):
            with contextlib.suppress(OSError):
                found = path.stat()
                files.append((found.st_mtime, path.name, found.st_size, path))
        return files

    def _prune(self, keep: Path) -> None:
        """The oldest incident files go until all take at most ``max_total_mb`` (the one
        just written stays, however large)."""
        budget = self.settings.max_total_mb * 1024 * 1024
        files = self._incident_files()
        total = sum(size for _, _, size, _ in files)
        for _, _, size, path in sorted(files):
            if total <= budget:
                break
            if path == keep:
                continue
            with contextlib.suppress(OSError):
                path.unlink()
                total -= size
                log.info("incident pruned: %s (over max_total_mb)", path)


def folder_problem(folder: Path) -> str | None:
    """Why this user could not write incident files in ``folder`` here (``busgate run`` would
    refuse to start), or ``None``: for ``busgate check-config``."""
    existing = folder
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is not a directory"
    if os.access(existing, os.W_OK | os.X_OK):
        return None
    if existing == folder:
        return f"{folder} is not writable by this user"
    return f"{folder} does not exist and this user may not make it in {existing}"


def _code(reply: dict[str, Any] | None) -> str:
    if reply is None or reply.get("ok"):
        return "ok"
    return str(reply.get("error", {}).get("code", "internal"))


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "-", text)[:64] or "incident"


async def _unless(stop: asyncio.Event, awaitable: Any) -> None:
    """Await ``awaitable`` unless ``stop`` is set first (then it is cancelled)."""
    waiting = asyncio.ensure_future(awaitable)
    stopping = asyncio.ensure_future(stop.wait())
    await asyncio.wait({waiting, stopping}, return_when=asyncio.FIRST_COMPLETED)
    for task in (waiting, stopping):
        task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await waiting


def _ring(seconds: float, entries_per_s: float, bytes_per_s: float) -> Ring:
    """A ring of the last ``seconds``, bounded by what that many seconds hold at these rates."""
    return Ring(seconds, int(seconds * entries_per_s), int(seconds * bytes_per_s))
