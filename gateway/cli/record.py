"""``busgate record`` and ``busgate replay``: the fleet's telemetry to an MCAP file and back
(``busgate.gateway.recording.mcap_log``), through a ``busgate.client`` session opened with
the client commands' options.

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
4. Replay publishes only telemetry (``mcap_log.REPLAYED_LEAVES``): never a command, a follow
   target or an e-stop, whatever the file holds.
5. Replay publishes only under ``--prefix`` (default ``replay``, no live gateway's), a key
   under it in place of the recorded prefix: a key outside the recorded prefix is left out,
   as is a key with a wildcard (one put reaches every subscriber it covers), and a file
   naming none is refused. A ``--prefix`` a gateway is live under (its liveliness
   token, asked for with a bounded get), or one under a live gateway's keys (``busgate/demo``
   while gateway ``demo`` is live under ``busgate``), is refused before anything is
   published, unless ``--onto-live``: recorded states would go out on that gateway's own keys.
6. A recording that cannot start (no session, or SIGTERM or Ctrl-C while the session opens)
   leaves no file behind: the operator fixes the endpoint and runs the same command again
   (rule 3 would refuse an empty file left there).
7. A file is a peer's word, replayed within bounds whatever it holds: a message larger than
   a gateway publishes on its key (``largest_published``) or on a key zenoh refuses is left
   out and counted, a
   gap between messages longer than ``MAX_GAP_S`` of recorded time is cut to it, and a file
   is read holding at most ``mcap_log.MAX_CHUNK`` of it at once (a file claiming more is
   refused before any session). SIGINT or SIGTERM stops a replay between two messages.
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
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import busgate.client as bc
from busgate.client.keys import Keys, check_key, intersects
from busgate.errors import BusgateError, CommandError
from busgate.gateway.cli.arguments import named_path
from busgate.gateway.cli.client_session import add_session_options, open_client
from busgate.gateway.cli.stopping import stopped_by_signals
from busgate.gateway.recording import mcap_log, timeline
from busgate.schemas.payload import largest_published
from busgate.schemas.validation import printable, shown
from busgate.schemas.zenoh_session import LIVE_WAIT_S

QUEUE_MAX = 100_000
#: The most the queue holds in bytes (rule 1): 100,000 of the fleet's states are some 40 MB,
#: where a peer's 30 MiB ``joints`` messages held gigabytes (an audit).
QUEUE_MAX_BYTES = 64 * 1024 * 1024
PROGRESS_EVERY_S = 1.0
MIN_SPEED = 0.01
MAX_SPEED = 1000.0
#: The most of a file's key (a topic, a bus's name) ``--info`` and ``--timeline`` print: a
#: file is a peer's word, and a key may be 64 KiB of terminal escapes.
SHOWN_TOPIC_CHARS = 300
#: The longest wait between two replayed messages, in recorded time (rule 7): a recording of
#: the fleet holds none longer, a crafted one may name years.
MAX_GAP_S = 60.0
#: Why a recorded or replayed message is left out past ``largest_published`` of its key.
TOO_LARGE = "larger than any a gateway sends on its key"
#: Where a replay publishes unless told otherwise: a prefix no live gateway uses (rule 5).
REPLAY_PREFIX = "replay"
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
    replay = subparsers.add_parser(
        "replay",
        description="Publish a recording's telemetry again at its pace (or --speed times "
        f"it), under --prefix (default {REPLAY_PREFIX}) in place of the recorded prefix, so "
        "busgate watch can be pointed at it (not the dashboard: a replay has no gateway's "
        "liveliness token nor info). Never publishes a command, "
        "follow target or e-stop, nor outside --prefix; refuses a --prefix a gateway is live "
        "under, unless --onto-live.",
        conflict_handler="resolve",  # its own --prefix replaces the session options' one
    )
    add_session_options(replay)
    replay.add_argument(
        "--prefix",
        default=REPLAY_PREFIX,
        help="publish under this prefix in place of the recorded one (default "
        f"{REPLAY_PREFIX}: no live gateway's)",
    )
    replay.add_argument(
        "--onto-live",
        action="store_true",
        help="replay even where a gateway is live under --prefix: onto its own keys",
    )
    replay.add_argument("file", type=named_path, metavar="FILE.mcap")
    replay.add_argument("--speed", type=float, default=1.0, help="how much faster (default 1)")
    replay.set_defaults(handler=run_replay)


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
        except BaseException as exc:  # no session: the empty file made above goes (rule 6)
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
def _recording(path: Path) -> Iterator[tuple[IO[bytes], dict[str, Any]]]:
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
    """The file's summary alone (``_recording``)."""
    with _recording(path) as (_, found):
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
    with _recording(path) as (stream, _):
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


# -- replay -----------------------------------------------------------------------------------


def run_replay(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.speed) and MIN_SPEED <= args.speed <= MAX_SPEED):
        raise CommandError(f"--speed is from {MIN_SPEED:g} to {MAX_SPEED:g}, not {args.speed}")
    Keys(args.prefix)  # a gateway's prefix, no wildcard: refused before any file or session
    path = Path(args.file)
    with _recording(path) as (stream, found):
        return _replay(args, path, stream, found["largest_chunk"])


def _replay(args: argparse.Namespace, path: Path, stream: IO[bytes], largest: int) -> int:
    """``run_replay`` of the recording ``stream``, whose largest chunk is ``largest`` bytes.
    A file that is no complete recording was refused before any session; so is one too large
    (rule 7)."""
    if largest > mcap_log.MAX_CHUNK:
        raise CommandError(
            f"{path} holds a chunk of {largest / 2**20:.0f} MiB: replay reads at most "
            f"{mcap_log.MAX_CHUNK // 2**20} MiB at once"
        )
    recorded_prefix = _recorded_prefix(stream, path)
    stop = threading.Event()
    try:
        client = open_client(args, "replay")
    except KeyboardInterrupt:  # while the session opens: nothing was published (rule 7)
        raise CommandError("stopped before anything was published") from None
    # From here a signal stops the replay between two messages, its session closed in order.
    with stopped_by_signals(stop), client:
        _refuse_live_prefix(client, args)
        print(f"busgate replay: replaying {path} under {args.prefix}/**", file=sys.stderr)
        started = time.monotonic()
        try:
            sent, left_out, cuts = _publish(client, stream, recorded_prefix, args, started, stop)
        except BusgateError:
            raise  # the session's own refusal, as it is
        except Exception as exc:  # a chunk the reader cannot read, past the summary
            raise CommandError(f"{path} could not be read to its end: {exc}") from None
    said = [f"{sent} messages in {time.monotonic() - started:.1f} s"]
    if left_out:
        said.append(", ".join(f"{count} {why}" for why, count in left_out.items()) + " left out")
    if cuts:
        said.append(f"{cuts} gaps over {MAX_GAP_S:g} s cut to {MAX_GAP_S:g} s")
    if stop.is_set():
        said.append("stopped before the file's end")
    print(f"busgate replay: {'; '.join(said)}", file=sys.stderr)
    return 0


def _recorded_prefix(stream: IO[bytes], path: Path) -> str:
    """The prefix the file ``path`` (``stream``) recorded its keys under; ``CommandError``
    when it names none (rule 5: its keys could not be put under ``--prefix``), or its
    metadata cannot be read (a damaged file: the ``mcap`` reader's errors are of many kinds)."""
    try:
        found = mcap_log.recorded_prefix(stream)
    except Exception as exc:
        raise CommandError(f"{path}: its metadata cannot be read ({exc})") from None
    if found is None:
        raise CommandError(f"{path} names no prefix its keys were recorded under")
    return found


def _refuse_live_prefix(client: bc.Client, args: argparse.Namespace) -> None:
    """``CommandError`` when a gateway is live under ``--prefix``, or ``--prefix`` is under a
    live gateway's keys, and ``--onto-live`` is not given (rule 5): asked before anything is
    published."""
    if args.onto_live:
        return
    live = _live_gateways(client, args.prefix)
    if live:
        raise CommandError(
            f"--prefix {args.prefix} is live (gateway {', '.join(live)}): a replay there "
            f"writes into its telemetry; use another --prefix (default {REPLAY_PREFIX}) or "
            "add --onto-live"
        )


def _live_gateways(client: bc.Client, prefix: str) -> list[str]:
    """The gateways up under ``prefix`` (the client's session was opened with it), judged as
    the SDK judges whether a named gateway is up (``Shared.to_gateway``): the liveliness tokens
    its subscriber has seen, and whatever answers ``info`` within ``LIVE_WAIT_S`` (right after
    a session opens, zenoh may not have told it every token yet); those under a longer prefix
    that ``prefix`` begins (``gw under fleet/site1`` for ``fleet``: the file's keys put under
    ``fleet`` may be theirs); and those whose keys hold ``prefix``, ``demo under busgate`` for
    ``busgate/demo/x``: whatever answers their ``info``."""
    keys = Keys(prefix)
    live: set[str] = set()
    stop = client.on_gateways(lambda gateway, alive: live.add(gateway) if alive else None)
    try:
        answers = client.query(keys.info("*"), timeout=LIVE_WAIT_S)
    finally:
        stop()
    live.update(keys.gateway_of(answer.key) for answer in answers)
    for answer in client.query(f"{prefix}/*/*/**/info", timeout=LIVE_WAIT_S):  # two or more
        below, _, gateway = answer.key.removesuffix("/info").rpartition("/")
        live.add(f"{gateway} under {below}")
    names = prefix.split("/")
    for above, gateway in ((Keys("/".join(names[:n])), names[n]) for n in range(1, len(names))):
        if client.query(above.info(gateway), timeout=LIVE_WAIT_S):
            live.add(f"{gateway} under {above.prefix}")
    return sorted(live)


def _publish(
    client: bc.Client,
    stream: IO[bytes],
    recorded_prefix: str,
    args: argparse.Namespace,
    started: float,
    stop: threading.Event,
) -> tuple[int, Counter[str], int]:
    """Publish the file's telemetry at its pace under ``--prefix``, until its end or ``stop``:
    (messages sent, messages left out by why, gaps cut) (rules 4, 5, 7)."""
    sent = cuts = 0
    left_out: Counter[str] = Counter()
    routes: dict[str, tuple[str, str | None]] = {}  # each topic's, found once
    first = last = cut_ns = 0
    for message in mcap_log.messages(stream):
        if message.topic not in routes:
            routes[message.topic] = _route(message.topic, recorded_prefix, args.prefix)
        key, why = routes[message.topic]
        if why is None and len(message.data) > largest_published(key):
            why = TOO_LARGE
        if why is not None:
            left_out[why] += 1
            continue
        if not sent:
            first = last = message.log_time_ns
        if message.log_time_ns - last > MAX_GAP_S * 1e9:
            cut_ns += message.log_time_ns - last - int(MAX_GAP_S * 1e9)
            cuts += 1
        last = max(last, message.log_time_ns)
        due = started + (message.log_time_ns - first - cut_ns) / 1e9 / args.speed
        if stop.wait(max(0.0, due - time.monotonic())):
            break
        client.put(key, message.data)
        sent += 1
    return sent, left_out, cuts


def _route(topic: str, recorded_prefix: str, prefix: str) -> tuple[str, str | None]:
    """The key a recorded ``topic`` is published on under ``prefix``, or why it is left out
    (rules 4, 5, 7): a topic zenoh refuses is named, once."""
    if topic.rsplit("/", 1)[-1] not in mcap_log.REPLAYED_LEAVES:  # rule 4
        return "", "on keys not telemetry (commands, e-stops, frames)"
    if not topic.startswith(recorded_prefix + "/"):  # rule 5
        return "", f"outside {recorded_prefix}/**"
    if "*" in topic:  # one put there reaches every subscriber the wildcard covers (rule 5)
        return "", "on wildcard keys"
    try:
        return check_key(prefix + topic[len(recorded_prefix) :]), None
    except CommandError as exc:
        print(f"busgate replay: left out: {exc}", file=sys.stderr)
        return "", "on keys zenoh refuses"
