"""``busgate record``: the fleet's telemetry to an MCAP file
(``busgate.gateway.recording.mcap_log``), through a ``busgate.client`` session opened with the
client commands' options; ``--info`` tells what a file holds and ``--timeline`` draws an
incident file's frames (``busgate replay``, the way back, is ``replay``'s).

Rules of this file:

1. Recording never blocks zenoh's threads: a sample is put in a bounded queue and written by
   one writer thread. When the queue is full (``QUEUE_MAX`` samples or ``QUEUE_MAX_BYTES``:
   a disk slower than the fleet, or a peer's large messages) the sample is dropped and
   counted; the progress line and the last line say how many. A sample larger
   than any a gateway publishes on its key (``payload.largest_published``) is left out and
   counted: a queue of them would be memory without end.
2. SIGINT, SIGTERM or ``--seconds`` end a recording the same way: the subscriptions end, the
   queue is written out, and the file gets its summary and index (a complete MCAP file); a
   second signal meanwhile (a Ctrl-C pressed twice) changes nothing of that. A
   write the disk refuses (full) ends it the same way, the file ended as far as the disk
   lets it, and the command fails in one line naming the file and why.
3. An existing file is never overwritten: a recording is evidence.
4. A recording that cannot start (no session, or SIGTERM or Ctrl-C while the session opens)
   leaves no file behind: the operator fixes the endpoint and runs the same command again
   (rule 3 would refuse an empty file left there).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import queue
import signal
import stat
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from busgate.client.keys import check_key, intersects
from busgate.errors import CommandError
from busgate.gateway.cli.arguments import named_path
from busgate.gateway.cli.client_session import add_session_options, open_client
from busgate.gateway.cli.stopping import stopped_by_signals
from busgate.gateway.recording import mcap_log, timeline
from busgate.schemas.payload import largest_published
from busgate.schemas.validation import printable, shown

QUEUE_MAX = 100_000
#: The most the queue holds in bytes (rule 1): 100,000 of the fleet's states are some 40 MB,
#: where a peer's 30 MiB ``joints`` messages held gigabytes (an audit).
QUEUE_MAX_BYTES = 64 * 1024 * 1024
PROGRESS_EVERY_S = 1.0
#: The most of a file's key (a topic, a bus's name) ``--info`` and ``--timeline`` print: a
#: file is a peer's word, and a key may be 64 KiB of terminal escapes.
SHOWN_TOPIC_CHARS = 300
#: Why a recorded or replayed message is left out past ``largest_published`` of its key.
TOO_LARGE = "larger than any a gateway sends on its key"
#: ``--timeline``'s span (ms): by default, and the least and most it draws.
TIMELINE_SPAN_MS, TIMELINE_SPAN_MS_MIN, TIMELINE_SPAN_MS_MAX = 100.0, 1.0, 60_000.0


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    record = subparsers.add_parser(
        "record",
        description="Record every message under the prefix (states, events, bus statistics, "
        "trajectory feedback, e-stops), or the KEYEXPRs given, to an MCAP file: a channel "
        "per key, JSON messages with their JSON Schemas. Ends on Ctrl-C, SIGTERM or "
        "--seconds with a complete file. --info FILE prints what a file holds.",
    )
    add_session_options(record)
    record.add_argument("keys", nargs="*", metavar="KEYEXPR", help="what to record")
    record.add_argument(
        "-o", "--output", type=named_path, metavar="FILE.mcap", help="the file to write"
    )
    record.add_argument("--seconds", type=float, default=None, help="stop after this long")
    record.add_argument(
        "--info", type=named_path, metavar="FILE.mcap", help="print a file's channels and span"
    )
    record.add_argument(
        "--timeline",
        type=named_path,
        metavar="FILE.mcap",
        help="draw an incident file's frames, bus by bus, as SVG (to -o FILE.svg, else stdout)",
    )
    record.add_argument(
        "--span-ms",
        type=float,
        help=f"--timeline: how much to draw (default {TIMELINE_SPAN_MS:g} ms)",
    )
    record.add_argument(
        "--end",
        type=float,
        metavar="UNIX_S",
        help="--timeline: where the drawing ends (default: a fifth of the span after the "
        "first e-stop, else the last frame)",
    )
    record.set_defaults(handler=run_record)


# -- record -----------------------------------------------------------------------------------


def run_record(args: argparse.Namespace) -> int:
    _refuse_strays(args)
    if args.info is not None:
        return _print_info(Path(args.info))
    if args.timeline is not None:
        return _draw_timeline(Path(args.timeline), args)
    if args.output is None:
        raise CommandError("name the file to write: -o FILE.mcap (or --info FILE.mcap)")
    if args.seconds is not None and not (math.isfinite(args.seconds) and args.seconds > 0):
        raise CommandError(f"--seconds is a positive number, not {args.seconds}")
    keys = [check_key(key) for key in args.keys] or [f"{check_key(args.prefix)}/**"]
    _refuse_overlaps(keys)
    output = Path(args.output)
    try:
        stream = output.open("xb")  # rule 3; closed by Recording.close (or below, at once)
    except FileExistsError:
        raise CommandError(f"{args.output} exists: a recording is never overwritten") from None
    except OSError as exc:
        raise CommandError(f"cannot write {args.output}: {exc.strerror}") from None
    stop = threading.Event()
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)  # as Ctrl-C, here
    try:
        try:
            client = open_client(args, "record")
        except BaseException as exc:  # no session: the empty file made above goes (rule 4)
            stream.close()
            output.unlink(missing_ok=True)
            if isinstance(exc, KeyboardInterrupt):
                raise CommandError("stopped before a session opened: nothing recorded") from None
            raise
        # From the session on, a signal ends the recording, whole to its last byte (rule 2):
        # one before its header was written left an empty file (an audit).
        with client, stopped_by_signals(stop):
            _record(client, stream, keys, stop, args)
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0


def _refuse_strays(args: argparse.Namespace) -> None:
    """An option the chosen mode (--info, --timeline, or recording) would ignore is refused:
    a tired operator's ``--span-ms`` without ``--timeline`` drew nothing and said nothing."""
    given = {
        "--info": args.info is not None,
        "--timeline": args.timeline is not None,
        "-o": args.output is not None,
        "--seconds": args.seconds is not None,
        "a KEYEXPR": bool(args.keys),
        "--span-ms": args.span_ms is not None,
        "--end": args.end is not None,
    }
    if given["--info"]:
        mode, takes = "--info", {"--info"}
    elif given["--timeline"]:
        mode, takes = "--timeline", {"--timeline", "-o", "--span-ms", "--end"}
    else:
        mode, takes = "a recording (no --info, no --timeline)", {"-o", "--seconds", "a KEYEXPR"}
    strays = [option for option, present in given.items() if present and option not in takes]
    if strays:
        raise CommandError(f"{' and '.join(strays)} cannot go with {mode}")


def _record(
    client: Any, stream: IO[bytes], keys: list[str], stop: threading.Event, args: argparse.Namespace
) -> None:
    """``keys`` recorded to ``stream`` until ``stop``, ``--seconds`` or a failed write."""
    try:
        recording = Recording(stream, args.prefix, stop)  # writes the file's header
    except OSError as exc:
        stream.close()
        raise CommandError(f"cannot write {args.output}: {exc.strerror}") from None
    ends: list = []
    try:
        for key in keys:
            ends.append(client.subscribe_raw(key, recording.take))
        until = "Ctrl-C" if args.seconds is None else f"{args.seconds:g} s or Ctrl-C"
        print(
            f"busgate record: recording {', '.join(keys)} to {args.output} until {until}",
            file=sys.stderr,
            flush=True,
        )
        recording.run_until_stopped(args.seconds)
    finally:
        for end in ends:
            end()
        recording.close()
    if recording.failure is not None:
        why = getattr(recording.failure, "strerror", None) or recording.failure
        raise CommandError(f"cannot write {args.output}: {why}")


def _refuse_overlaps(keys: list[str]) -> None:
    """``CommandError`` for two key expressions that a key can match both of: each is a
    subscription of its own, and a sample on such a key would be recorded twice (and
    replayed twice; an audit)."""
    for n, first in enumerate(keys):
        for second in keys[n + 1 :]:
            if intersects(first, second):
                raise CommandError(
                    f"key expressions {shown(first)} and {shown(second)} overlap: a message on "
                    "a key both match would be recorded twice; give one that covers both"
                )


class Recording:
    """Samples in (``take``, zenoh's threads), the file written on one thread (rule 1) and
    closed by ``close``; ``failure``: the write the disk refused (rule 2)."""

    def __init__(self, stream: IO[bytes], prefix: str, stop: threading.Event | None = None) -> None:
        self._stream = stream
        self._log = mcap_log.McapLog(stream, prefix)
        self._queue: queue.Queue[tuple[str, bytes, int] | None] = queue.Queue(QUEUE_MAX)
        self._queued_bytes = 0  # of the payloads in the queue (rule 1)
        self._queued_lock = threading.Lock()
        #: Set by a signal (``stopped_by_signals``) or a failed write: the recording ends.
        self._stop = stop or threading.Event()
        self.dropped = 0
        #: Messages taken but never written: those of the chunk the disk refused, and those
        #: queued behind it.
        self.unwritten = 0
        self.too_large = 0  # messages larger than a gateway publishes on their key, left out
        self.elapsed_s = 0.0
        self.failure: Exception | None = None
        self._writer = threading.Thread(target=self._write, name="busgate-record", daemon=True)
        self._writer.start()

    def take(self, key: str, payload: bytes, ns: int) -> None:
        size = len(payload)
        if size > largest_published(key):  # no gateway's: a queue of them is memory
            self.too_large += 1  # without end
            return
        with self._queued_lock:
            if self._queued_bytes + size <= QUEUE_MAX_BYTES:
                with contextlib.suppress(queue.Full):
                    self._queue.put_nowait((key, payload, ns))
                    self._queued_bytes += size
                    return
        self.dropped += 1

    def _write(self) -> None:
        # Past a failure the queue is still emptied, up to close's None: a put never waits.
        while (item := self._queue.get()) is not None:
            with self._queued_lock:
                self._queued_bytes -= len(item[1])
            if self.failure is not None:
                self.unwritten += 1
                continue
            try:
                self._log.add(*item)
            except Exception as exc:  # the disk's refusal, or a bug: the thread lives on
                self.failure = exc
                self.unwritten += self._log.unwritten + 1  # its chunk, and this one
                self._stop.set()

    def run_until_stopped(self, seconds: float | None) -> None:
        """Show progress until its ``stop`` (a signal), ``seconds`` or a failed
        write (rule 2)."""
        started = time.monotonic()
        deadline = math.inf if seconds is None else started + seconds
        while not self._stop.is_set() and time.monotonic() < deadline:
            self._stop.wait(min(PROGRESS_EVERY_S, max(0.0, deadline - time.monotonic())))
            if sys.stderr.isatty():  # a line redrawn in place: a log would get them run together
                self._progress(time.monotonic() - started, end="\r")
        self.elapsed_s = time.monotonic() - started

    def _progress(self, elapsed: float, end: str) -> None:
        log = self._log
        rate = log.messages / elapsed if elapsed > 0 else 0.0
        print(
            f"busgate record: {log.messages} messages, {log.bytes / 1024:.0f} KiB, "
            f"{rate:.0f}/s, {self.dropped} dropped",
            end=end,
            file=sys.stderr,
            flush=True,
        )

    def close(self) -> None:
        """Write what is queued, then the summary and index, and close the file."""
        self._queue.put(None)
        self._writer.join()
        try:
            with self._stream:  # its close writes what it buffers: a full disk refuses that too
                if self.failure is None:
                    self._log.finish()
        except OSError as exc:
            if self.failure is None:  # the file's last chunk went with its summary
                self.unwritten += self._log.unwritten
            self.failure = self.failure or exc
        self._progress(self.elapsed_s, end="\n")
        for count, why in (
            (self._log.past_channels, f"on keys past the {mcap_log.MAX_CHANNELS} a file names"),
            (self.too_large, TOO_LARGE),
        ):
            if count:
                print(f"busgate record: {count} messages left out: {why}", file=sys.stderr)
        if self.dropped:
            print(
                f"busgate record: {self.dropped} messages were dropped: the disk could not keep up",
                file=sys.stderr,
            )
        if self.unwritten:
            print(
                f"busgate record: {self.unwritten} messages were not written: the disk refused "
                "them",
                file=sys.stderr,
            )


@contextlib.contextmanager
def read_recording(path: Path) -> Iterator[tuple[IO[bytes], dict[str, Any]]]:
    """The file, opened once for every reading of it (each seeks to where it starts), and
    its summary (``mcap_log.summary``); ``CommandError`` when it cannot be read or is not a
    complete MCAP file."""
    try:
        stream = _opened(path)
    except OSError as exc:
        raise CommandError(f"cannot read {path}: {exc.strerror}") from None
    with stream:
        try:
            found = mcap_log.summary(stream)
        except OSError as exc:
            raise CommandError(f"cannot read {path}: {exc.strerror}") from None
        except Exception as exc:  # the mcap reader's errors have no common base
            why = str(exc) or type(exc).__name__  # some say nothing
            if mcap_log.ends_short(stream):  # killed, or its disk full, before its end
                why = (
                    "it ends short of its summary and index (a recording killed, or its disk "
                    "full, before its end): `mcap recover` mends it, keeping every chunk "
                    f"written whole ({why})"
                )
            raise CommandError(f"{path} is not a complete MCAP file: {why}") from None
        yield stream, found


def _opened(path: Path) -> IO[bytes]:
    """``path`` opened to be read; ``CommandError`` when it is no regular file: a FIFO's open
    waits for a writer, and a recording is read by seeking to its end."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # a FIFO's open returns at once
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise CommandError(f"{path} is no regular file: a recording is one")
    os.set_blocking(fd, True)
    return os.fdopen(fd, "rb")


def _summary(path: Path) -> dict[str, Any]:
    """The file's summary alone (``read_recording``)."""
    with read_recording(path) as (_, found):
        return found


def _print_info(path: Path) -> int:
    found = _summary(path)
    span = (found["end_ns"] - found["start_ns"]) / 1e9 if found["messages"] else 0.0
    print(
        f"{path}: {found['messages']} messages in {len(found['channels'])} channels over "
        f"{span:.3f} s"
    )
    for channel in found["channels"]:  # a file's keys are a peer's word: shown, not obeyed
        topic = printable(channel["topic"], SHOWN_TOPIC_CHARS)
        print(f"  {channel['messages']:>8}  {topic}  ({channel['schema'] or 'no schema'})")
    return 0


def _draw_timeline(path: Path, args: argparse.Namespace) -> int:
    span_ms = TIMELINE_SPAN_MS if args.span_ms is None else args.span_ms
    end = args.end
    if not (math.isfinite(span_ms) and TIMELINE_SPAN_MS_MIN <= span_ms <= TIMELINE_SPAN_MS_MAX):
        raise CommandError(
            f"--span-ms is from {TIMELINE_SPAN_MS_MIN:g} to {TIMELINE_SPAN_MS_MAX:g}, not {span_ms}"
        )
    if end is not None and not (math.isfinite(end) and end > 0):
        raise CommandError(f"--end is a Unix time in seconds, not {end}")
    # A file that is no complete recording is refused in its words.
    with read_recording(path) as (stream, _):
        try:
            window = timeline.window_of(stream, span_ms / 1e3, end)
        except OSError as exc:
            raise CommandError(f"cannot read {path}: {exc.strerror}") from None
        except Exception as exc:  # the mcap reader's errors have no common base; ours: too many
            raise CommandError(f"{path}: {exc}") from None
    if not window.frames:
        raise CommandError(
            f"{path} holds no frames in those {span_ms:g} ms (the flight recorder's incident "
            "files hold the wire's frames; a `busgate record` file holds what zenoh carried, "
            "no frames)"
        )
    picture = timeline.svg(window)
    if args.output is None:
        sys.stdout.write(picture)
    else:
        try:
            with open(args.output, "x", encoding="utf-8") as out:  # never over a recording
                out.write(picture)
        except FileExistsError:
            raise CommandError(f"{args.output} exists: give a new file name") from None
        except OSError as exc:
            raise CommandError(f"cannot write {args.output}: {exc.strerror}") from None
    drawn = sum(map(len, window.frames.values()))
    left_out = (
        f"; {window.left_out} frame messages not a recorder's, left out" if window.left_out else ""
    )
    print(
        f"busgate record: {drawn} frames on "
        f"{', '.join(printable(bus, SHOWN_TOPIC_CHARS) for bus in sorted(window.frames))} drawn, "
        f"{span_ms:g} ms{left_out}",
        file=sys.stderr,
    )
    return 0
