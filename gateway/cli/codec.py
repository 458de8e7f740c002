"""``busgate encode`` and ``busgate decode``: the codecs at the command line.

encode: JSON command → schema model → driver frames → wire, one frame per line (lowercase
hex, CAN frames as ``id#data`` like cansend). decode: wire → one JSON object per frame or
event; exit status 1 when anything failed its checksum, was discarded or was left incomplete.
A frame that carries registers' values (the codec's ``readings``: a read's reply, a ZLAC706
write and its echo) also lists them under ``"registers"``: name, address, raw value, value
in the unit the register table states.
"""

from __future__ import annotations

import argparse
import json
import sys

from busgate.codecs.can_frame import CanFrame
from busgate.codecs.framing import ChecksumMismatch, Discarded
from busgate.errors import CommandError, RefusedError
from busgate.gateway.cli.jsonify import to_jsonable
from busgate.gateway.drivers.families import driver_class
from busgate.schemas.families import PROTOCOLS, WireProtocol
from busgate.schemas.payload import decode_object
from busgate.schemas.validation import command_from_object

DEFAULT_ID = 1  # the factory default of every addressed device family we drive


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    encode = subparsers.add_parser(
        "encode",
        description="Print the frame(s) of a JSON command, one per line: lowercase hex, or "
        "id#data for CAN.",
    )
    encode.add_argument("protocol", choices=sorted(PROTOCOLS))
    encode.add_argument("command", help='the JSON command, e.g. \'{"op":"move","position":1000}\'')
    encode.add_argument(
        "--id", type=int, default=None, help=f"device id (default {DEFAULT_ID}; 255/254 broadcast)"
    )
    encode.set_defaults(handler=run_encode)

    decode = subparsers.add_parser(
        "decode",
        description="Decode wire bytes (hex; CAN frames as id#data) into one JSON object per frame "
        "or event. Exit status 1 when a checksum fails or bytes are discarded.",
    )
    decode.add_argument("protocol", choices=sorted(PROTOCOLS))
    decode.add_argument("wire", nargs="+", help="hex bytes (spaces allowed), or id#data for CAN")
    decode.add_argument(
        "--as",
        dest="direction",
        choices=("auto", "command", "reply"),
        default="auto",
        help="decode as host commands or as device replies (default: whichever fits)",
    )
    decode.set_defaults(handler=run_decode)


def run_encode(args: argparse.Namespace) -> int:
    protocol = PROTOCOLS[args.protocol]
    if args.id is not None and not protocol.addressed:
        raise CommandError(f"{protocol.name} frames carry no device id; drop --id")
    try:  # read as the gateway reads a command: a key given twice, or NaN, is refused
        fields = decode_object(args.command.encode())
    except RefusedError as exc:
        raise CommandError(f"invalid command: {exc}") from None
    command = command_from_object(protocol.schema.COMMAND_ADAPTER, fields, protocol.kind)
    device_id = DEFAULT_ID if args.id is None else args.id
    for frame in driver_class(protocol)("encode", device_id).frames_of(command):
        print(wire_text(protocol.codec.encode(frame)))
    return 0


def wire_text(wire: bytes | CanFrame) -> str:
    return str(wire) if isinstance(wire, CanFrame) else wire.hex()


def run_decode(args: argparse.Namespace) -> int:
    protocol = PROTOCOLS[args.protocol]
    directions = ("command", "reply") if args.direction == "auto" else (args.direction,)
    results = [decode_wire(protocol, direction, args.wire) for direction in directions]
    events, leftover = min(results, key=_badness)
    for event in events:
        decoded = to_jsonable(event)
        readings = protocol.codec.readings(event)
        if readings:  # only where a frame names its registers; every other key is kept
            decoded["registers"] = to_jsonable(readings)
        print(json.dumps(decoded))
    problems = [_describe_problem(e) for e in events if isinstance(e, Discarded | ChecksumMismatch)]
    if leftover:
        problems.append(f"incomplete frame: {leftover} byte(s) left over at the end")
    for problem in problems:
        print(f"busgate decode: {problem}", file=sys.stderr)
    return 1 if problems else 0


def decode_wire(protocol: WireProtocol, direction: str, wire: list[str]) -> tuple[list, int]:
    """Decode ``wire`` as commands or replies; return the events and the bytes left over."""
    codec = protocol.codec
    decoder = codec.CommandDecoder() if direction == "command" else codec.ReplyDecoder()
    if protocol.can:
        for text in wire:
            decoder.feed(CanFrame.parse(text))
    else:
        decoder.feed(_parse_hex(" ".join(wire)))
    events = list(decoder.events())
    return events, 0 if protocol.can else decoder.pending


def _parse_hex(text: str) -> bytes:
    try:
        data = bytes.fromhex(text)
    except ValueError as exc:
        raise CommandError(f"not hex bytes: {text!r}") from exc
    if not data:  # decoded, it printed nothing and said it went well
        raise CommandError("no bytes to decode: give the frame in hex")
    return data


def _badness(result: tuple[list, int]) -> tuple[int, int]:
    """Order decodings: fewest bad bytes first, then most frames."""
    events, leftover = result
    # A checksum mismatch costs one byte: the decoder moves one byte on and rescans the rest
    # of the frame, which is then counted where it lands (counting the whole frame made a
    # bad-checksum command lose to the reply decoder's single "no frame header").
    bad = leftover + sum(
        len(e.data) if isinstance(e, Discarded) else 1
        for e in events
        if isinstance(e, Discarded | ChecksumMismatch)
    )
    return bad, -len(events)


def _describe_problem(event: Discarded | ChecksumMismatch) -> str:
    if isinstance(event, ChecksumMismatch):
        return (
            f"checksum mismatch in frame {event.frame.hex()}: checksum should be "
            f"{event.expected:#04x}, frame has {event.received:#04x}"
        )
    return f"discarded {event.data.hex()}: {event.reason}"
