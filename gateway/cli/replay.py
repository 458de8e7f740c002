"""``busgate replay``: a recording's telemetry published again (``busgate record``'s files,
read by ``record.read_recording``), through a ``busgate.client`` session opened with the
client commands' options.

Rules of this file:

1. Replay publishes only telemetry (``mcap_log.REPLAYED_LEAVES``): never a command, a follow
   target or an e-stop, whatever the file holds.
2. Replay publishes only under ``--prefix`` (default ``replay``, no live gateway's), a key
   under it in place of the recorded prefix: a key outside the recorded prefix is left out,
   as is a key with a wildcard (one put reaches every subscriber it covers), and a file
   naming none is refused. A ``--prefix`` a gateway is live under (its liveliness
   token, asked for with a bounded get), or one under a live gateway's keys (``busgate/demo``
   while gateway ``demo`` is live under ``busgate``), is refused before anything is
   published, unless ``--onto-live``: recorded states would go out on that gateway's own keys.
3. A file is a peer's word, replayed within bounds whatever it holds: a message larger than
   a gateway publishes on its key (``largest_published``) or on a key zenoh refuses is left
   out and counted, a gap between messages longer than ``MAX_GAP_S`` of recorded time is cut
   to it, and a file is read holding at most ``mcap_log.MAX_CHUNK`` of it at once (a file
   claiming more is refused before any session). SIGINT or SIGTERM stops a replay between
   two messages.
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import IO

import busgate.client as bc
from busgate.client.keys import Keys, check_key
from busgate.errors import BusgateError, CommandError
from busgate.gateway.cli.arguments import named_path
from busgate.gateway.cli.client_session import add_session_options, open_client
from busgate.gateway.cli.record import TOO_LARGE, read_recording
from busgate.gateway.cli.stopping import stopped_by_signals
from busgate.gateway.recording import mcap_log
from busgate.schemas.payload import largest_published
from busgate.schemas.zenoh_session import LIVE_WAIT_S

MIN_SPEED = 0.01
MAX_SPEED = 1000.0
#: The longest wait between two replayed messages, in recorded time (rule 3): a recording of
#: the fleet holds none longer, a crafted one may name years.
MAX_GAP_S = 60.0
#: Where a replay publishes unless told otherwise: a prefix no live gateway uses (rule 2).
REPLAY_PREFIX = "replay"


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
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


def run_replay(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.speed) and MIN_SPEED <= args.speed <= MAX_SPEED):
        raise CommandError(f"--speed is from {MIN_SPEED:g} to {MAX_SPEED:g}, not {args.speed}")
    Keys(args.prefix)  # a gateway's prefix, no wildcard: refused before any file or session
    path = Path(args.file)
    with read_recording(path) as (stream, found):
        return _replay(args, path, stream, found["largest_chunk"])


def _replay(args: argparse.Namespace, path: Path, stream: IO[bytes], largest: int) -> int:
    """``run_replay`` of the recording ``stream``, whose largest chunk is ``largest`` bytes.
    A file that is no complete recording was refused before any session; so is one too large
    (rule 3)."""
    if largest > mcap_log.MAX_CHUNK:
        raise CommandError(
            f"{path} holds a chunk of {largest / 2**20:.0f} MiB: replay reads at most "
            f"{mcap_log.MAX_CHUNK // 2**20} MiB at once"
        )
    recorded_prefix = _recorded_prefix(stream, path)
    stop = threading.Event()
    try:
        client = open_client(args, "replay")
    except KeyboardInterrupt:  # while the session opens: nothing was published (rule 3)
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
    when it names none (rule 2: its keys could not be put under ``--prefix``), or its
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
    live gateway's keys, and ``--onto-live`` is not given (rule 2): asked before anything is
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
    (messages sent, messages left out by why, gaps cut) (rules 1, 2, 3)."""
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
    (rules 1, 2, 3): a topic zenoh refuses is named, once."""
    if topic.rsplit("/", 1)[-1] not in mcap_log.REPLAYED_LEAVES:  # rule 1
        return "", "on keys not telemetry (commands, e-stops, frames)"
    if not topic.startswith(recorded_prefix + "/"):  # rule 2
        return "", f"outside {recorded_prefix}/**"
    if "*" in topic:  # one put there reaches every subscriber the wildcard covers (rule 2)
        return "", "on wildcard keys"
    try:
        return check_key(prefix + topic[len(recorded_prefix) :]), None
    except CommandError as exc:
        print(f"busgate replay: left out: {exc}", file=sys.stderr)
        return "", "on keys zenoh refuses"
