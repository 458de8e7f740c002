"""busgate's messages in an MCAP file: one channel per key, message encoding ``json``, each
channel's schema the JSON Schema its key's messages follow (``busgate.schemas.exported``,
schema encoding ``jsonschema``), so that Foxglove, PlotJuggler or Rerun plot the fields as
they are.

Rules of this file:

1. A key's schema comes from the key's shape alone (and, for a state, the device's kind in
   the message): ``.../dev/<d>/state`` a kind's telemetry, ``.../dev/<d>/event`` and
   ``.../events`` the event, ``.../bus/<b>/stats`` the bus statistics; in an incident file
   (``flight``) ``.../bus/<b>/frames`` a frame and ``.../commands`` a command. The shape is
   the key's end, so that gateways recorded under a parent of their prefix (``--prefix
   fleet`` over ``fleet/site1/gw1/…``) have their schemas too. A key of no known shape (an
   e-stop, a trajectory's feedback) gets a channel without a schema.
2. Times are nanoseconds: the log time when the sample was taken (zenoh's timestamp where it
   has one), the publish time the message's own ``ts`` (else the log time).
3. Replay publishes only what is telemetry: never on a key that commands or stops
   (``REPLAYED_LEAVES`` names what may be published again).
4. A file names the prefix its keys were recorded under (the metadata record
   ``PREFIX_METADATA``, written as the file opens), so that replay can put them under
   another (``recorded_prefix``).
5. Reading a file back holds one record of it at a time, of at most ``MAX_CHUNK`` bytes
   whatever it claims: a chunk (with its records, decompressed no further than it claims,
   and split: some three times ``MAX_CHUNK`` at worst), or a record outside chunks, in the
   order the file holds them (the order they were written); a larger one ends the reading,
   as do channels whose keys take more than ``MAX_TOPIC_BYTES`` together (each is held while
   the file is read). A file is a peer's word: 32 KiB of zstd may claim, and hold, a
   gigabyte.
6. A file holds at most ``MAX_CHANNELS`` keys (a channel's id is 16 bits): a message on a
   key past them is left out and counted (``past_channels``), so that the file stays one a
   reader can read, whatever keys the network sends.
7. Messages go to the stream a chunk (``CHUNK_BYTES``) at a time, and the stream is flushed
   with each chunk; ``unwritten`` counts those added since the stream last took one, which
   a refused write loses. Unflushed, a buffered file took a compressed chunk (some 6 KB)
   into its 8 KiB buffer, and the disk's refusal came a chunk later: the chunk it lost went
   uncounted (an audit).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO, Any

import lz4.frame  # type: ignore[import-untyped]
import zstandard
from mcap.reader import make_reader
from mcap.records import Channel, Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import MCAP0_MAGIC, Writer

from busgate.schemas.exported import SCHEMAS, generated

LIBRARY = "busgate"
#: The metadata record naming the prefix the file's keys were recorded under (rule 4).
PREFIX_METADATA = "busgate"
#: The last chunk of a key that replay may publish again (rule 3): telemetry, events, stats.
REPLAYED_LEAVES = frozenset({"state", "event", "events", "stats", "feedback", "joints", "odom"})
#: The schema of a key ``<gateway>/<what>/<name>/<leaf>`` by ``(what, leaf)``, a device's
#: state excepted (its kind's), and of a key ``<gateway>/<leaf>`` by its leaf; the gateway
#: directly under the recording's prefix, or deeper (rule 1).
NAMED_KEY_SCHEMAS = {
    ("dev", "event"): "event.json",
    ("bus", "stats"): "bus_stats.json",
    ("bus", "frames"): "frame.json",
    ("base", "odom"): "odometry.json",
}
GATEWAY_KEY_SCHEMAS = {
    "events": "event.json",
    "commands": "recorded_command.json",
    "joints": "joints.json",
}
#: The most keys a file holds: an MCAP channel's id is 16 bits (past it, a message on a new
#: key is left out and counted; the file would be unreadable).
MAX_CHANNELS = 65_535
#: The most a reader holds of a file at once (rule 5): the writer's chunks are far smaller.
MAX_CHUNK = 64 * 1024 * 1024
#: The most its channels' keys may take together, read back (rule 5): a reader holds every
#: channel's key while it reads, and a small compressed file may name thousands of keys of
#: a megabyte each; busgate's own files name a few hundred short ones.
MAX_TOPIC_BYTES = 16 * 1024 * 1024
#: The writer's chunks (rule 7): what a refused write loses at most, and what a recording
#: holds before the disk is asked to take any (at 1 MiB, some 15 s of the demo's telemetry).
CHUNK_BYTES = 64 * 1024


def schema_name(key: str, prefix: str, body: Any) -> str | None:
    """The file name of the JSON Schema the messages on ``key`` follow (rule 1).

    >>> schema_name("fleet/site1/gw1/bus/can0/stats", "fleet", {})
    'bus_stats.json'
    """
    chunks = key[len(prefix) + 1 :].split("/") if key.startswith(prefix + "/") else []
    if len(chunks) >= 4 and (chunks[-3], chunks[-1]) == ("dev", "state"):
        kind = body.get("kind") if isinstance(body, dict) else None
        name = f"telemetry.{kind}.json"
        return name if name in SCHEMAS else None
    if len(chunks) >= 4 and (named := NAMED_KEY_SCHEMAS.get((chunks[-3], chunks[-1]))):
        return named
    if len(chunks) >= 2:
        return GATEWAY_KEY_SCHEMAS.get(chunks[-1])
    return None


def publish_time_ns(body: Any, log_time_ns: int) -> int:
    """The message's own ``ts`` in ns (rule 2), else its log time."""
    ts = body.get("ts") if isinstance(body, dict) else None
    if isinstance(ts, int | float) and not isinstance(ts, bool) and math.isfinite(ts) and ts > 0:
        return int(ts * 1e9)
    return log_time_ns


class McapLog:
    """Writes messages to an MCAP stream, a channel per key (opened on its first message), the
    keys under ``prefix`` (rule 4)."""

    def __init__(self, stream: IO[bytes], prefix: str) -> None:
        self._stream = stream
        self._writer = Writer(stream, chunk_size=CHUNK_BYTES)
        self._writer.start(profile="", library=LIBRARY)
        self._writer.add_metadata(PREFIX_METADATA, {"prefix": prefix})
        self._prefix = prefix
        self._texts = generated()
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self.messages = 0
        self.bytes = 0
        #: Messages added since the stream last took a chunk (rule 7).
        self.unwritten = 0
        #: Messages left out: on a key past the file's ``MAX_CHANNELS`` keys.
        self.past_channels = 0

    def add(self, key: str, payload: bytes, log_time_ns: int, *, body: Any = None) -> None:
        """One message; ``body`` is ``payload`` parsed, when the caller has it already."""
        if body is None:
            try:
                body = json.loads(payload)
            except (ValueError, RecursionError):
                body = None
        channel = self._channels.get(key)
        if channel is None:
            if len(self._channels) >= MAX_CHANNELS:  # a peer on ever new keys: the file holds
                self.past_channels += 1  # what its ids can name, and stays readable
                return
            channel = self._channels[key] = self._writer.register_channel(
                topic=key, message_encoding="json", schema_id=self._schema(key, body)
            )
        position = self._stream.tell()
        self._writer.add_message(
            channel,
            log_time=log_time_ns,
            data=payload,
            publish_time=publish_time_ns(body, log_time_ns),
            sequence=self.messages,
        )
        self.messages += 1
        self.bytes += len(payload)
        if self._stream.tell() == position:
            self.unwritten += 1
            return
        self._stream.flush()  # the chunk on the disk, or refused now (rule 7)
        self.unwritten = 0

    def _schema(self, key: str, body: Any) -> int:
        name = schema_name(key, self._prefix, body)
        if name is None:
            return 0  # MCAP's "no schema"
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_schema(
                name=name.removesuffix(".json"),
                encoding="jsonschema",
                data=self._texts[name].encode(),
            )
        return self._schemas[name]

    def metadata(self, name: str, values: dict[str, str]) -> None:
        """A metadata record of the caller's (an incident's triggers)."""
        self._writer.add_metadata(name, values)

    def finish(self) -> None:
        """Write the summary and the index: the file is complete and readable."""
        self._writer.finish()


@dataclass(frozen=True)
class Recorded:
    topic: str
    data: bytes
    log_time_ns: int


def messages(stream: IO[bytes]) -> Iterator[Recorded]:
    """Every message of an MCAP file, in the order the file holds them; ``ValueError`` (or the
    ``mcap`` reader's own) at a record or chunk larger than ``MAX_CHUNK`` (rule 5)."""
    stream.seek(0)
    topics: dict[int, str] = {}
    topic_bytes = 0
    records = StreamReader(stream, emit_chunks=True, record_size_limit=MAX_CHUNK).records
    for record in records:
        for inner in (
            breakup_chunk(_decompressed(record)) if isinstance(record, Chunk) else [record]
        ):
            if isinstance(inner, Channel):
                topic_bytes += len(inner.topic) - len(topics.get(inner.id, ""))
                if topic_bytes > MAX_TOPIC_BYTES:
                    raise ValueError(
                        f"channels whose keys take more than {MAX_TOPIC_BYTES // 2**20} MiB"
                    )
                topics[inner.id] = inner.topic
            elif isinstance(inner, Message):
                if inner.channel_id not in topics:
                    raise ValueError(f"a message on channel {inner.channel_id}, named by no record")
                yield Recorded(topics[inner.channel_id], inner.data, inner.log_time)


def _decompressed(chunk: Chunk) -> Chunk:
    """``chunk`` with its records uncompressed, no more of them read than it claims, at most
    ``MAX_CHUNK`` (rule 5): the library would decompress whatever size its zstd frame names."""
    size = chunk.uncompressed_size
    if size > MAX_CHUNK:  # refused on its word, before decompressing
        raise ValueError(f"a chunk of {size} bytes (at most {MAX_CHUNK})")
    if chunk.compression == "zstd":
        data = zstandard.ZstdDecompressor().stream_reader(chunk.data).read(size + 1)
    elif chunk.compression == "lz4":
        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=size + 1)
    elif chunk.compression == "":
        data = chunk.data
    else:
        raise ValueError(f"a chunk compressed with {chunk.compression!r}")
    if len(data) != size:
        raise ValueError(f"a chunk whose records are not the {size} bytes it names")
    return dataclasses.replace(chunk, compression="", data=data)


def recorded_prefix(stream: IO[bytes]) -> str | None:
    """The prefix the file's keys were recorded under (rule 4); ``None`` when it names none
    (a file of another tool, or written before files named it)."""
    stream.seek(0)
    found = None
    for record in make_reader(stream).iter_metadata():
        if record.name == PREFIX_METADATA:
            found = record.metadata.get("prefix") or None
    return found


def ends_short(stream: IO[bytes]) -> bool:
    """Whether ``stream`` begins as an MCAP file does (its magic) but does not end as one:
    a recording killed, or its disk full, before its end (summary, footer, magic)."""
    size = len(MCAP0_MAGIC)
    try:
        stream.seek(0)
        starts = stream.read(size) == MCAP0_MAGIC
        stream.seek(-size, 2)
        return starts and stream.read(size) != MCAP0_MAGIC
    except OSError:  # shorter than the magic, or no seeking
        return False


def summary(stream: IO[bytes]) -> dict[str, Any]:
    """What a file holds: each channel's topic, schema and message count, the time span (ns) of
    its messages, and its largest chunk's size uncompressed, as the file claims it (rule 5)."""
    found = make_reader(stream).get_summary()
    if found is None or found.statistics is None:
        raise ValueError("the file has no summary (it was not finished)")
    statistics = found.statistics
    counts = Counter(statistics.channel_message_counts)
    channels = []
    for channel_id, channel in sorted(found.channels.items(), key=lambda item: item[1].topic):
        schema = found.schemas.get(channel.schema_id)
        channels.append(
            {
                "topic": channel.topic,
                "schema": schema.name if schema is not None else None,
                "messages": counts[channel_id],
            }
        )
    return {
        "messages": statistics.message_count,
        "start_ns": statistics.message_start_time,
        "end_ns": statistics.message_end_time,
        "channels": channels,
        "largest_chunk": max((chunk.uncompressed_size for chunk in found.chunk_indexes), default=0),
    }
