"""Every decoder as a Hypothesis state machine: any interleaving of whole frames, frames split
across feeds, noise and frames with a bad checksum, drained at any point.

What noise decodes to cannot be predicted (noise can fake a frame, and a fake header can
swallow what follows until its checksum fails), so the byte-stream model only tracks when the
decoder must be in step with the wire: at the start, and after a drain that leaves nothing
pending. Frames fed whole from such a point come out exactly, in order, ahead of any noise fed
after them, and a bad checksum there is a ``ChecksumMismatch`` of that very frame. Always: no
exception, only the protocol's events, and, once drained, less than the protocol's largest
frame kept. CAN decoders take whole frames, so their model is exact, frame by frame, queue
overflow included. The frames come from the codec tests' own round-trip strategies; the long
fuzz run is ``test_fuzz_decoders.py`` (slow), this one stays in the default run.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from itertools import pairwise
from typing import Any

import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule, run_state_machine_as_test

from busgate.codecs import ds_servo, inspire_la, zlac706_can, zlac706_rs232
from busgate.codecs.can_frame import CanFrame
from busgate.codecs.framing import ChecksumMismatch, Discarded
from busgate.codecs.zlac706_can.frames import ALARM_REGISTER
from busgate.codecs.zlac706_can.frames import Command as CanCommand
from busgate.codecs.zlac706_can.frames import Reply as CanReply
from busgate.codecs.zlac706_rs232.frames import Command as Rs232Command
from busgate.codecs.zlac706_rs232.frames import Reply as Rs232Reply
from tests import test_ds_servo_codec as ds_tests
from tests import test_inspire_la_codec as la_tests
from tests import test_zlac706_can_codec as can_tests
from tests import test_zlac706_rs232_codec as rs232_tests
from tests.conftest import ERROR_EVENTS

MODEST = settings(max_examples=50, stateful_step_count=30, deadline=None)


@dataclass(frozen=True)
class Codec:
    """One decoder, the strategy of frames it decodes and how they are encoded."""

    decoder: Callable[[], Any]
    frames: st.SearchStrategy
    encode: Callable[[Any], Any]
    kinds: Any  # the protocol's event types (a union), besides ``ERROR_EVENTS``


STREAM_CODECS = {
    "inspire_la.CommandDecoder": Codec(
        inspire_la.CommandDecoder, la_tests.commands, inspire_la.encode, inspire_la.Frame),
    "inspire_la.ReplyDecoder": Codec(
        inspire_la.ReplyDecoder, la_tests.replies, inspire_la.encode, inspire_la.Frame),
    "ds_servo.CommandDecoder": Codec(
        ds_servo.CommandDecoder, ds_tests.commands, ds_servo.encode, ds_servo.Command),
    "ds_servo.ReplyDecoder": Codec(
        ds_servo.ReplyDecoder, ds_tests.replies, ds_servo.encode, ds_servo.StatusReply),
    "zlac706_rs232.CommandDecoder": Codec(
        zlac706_rs232.CommandDecoder, rs232_tests.commands, zlac706_rs232.encode, Rs232Command),
    "zlac706_rs232.ReplyDecoder": Codec(
        zlac706_rs232.ReplyDecoder, rs232_tests.replies, zlac706_rs232.encode, Rs232Reply),
}

# "No such register EB" is byte for byte an alarm report when its four value bytes are equal
# (see the CAN decoder's docstring), so replies about register EB are left out.
_unambiguous_replies = can_tests.replies.filter(
    lambda frame: not (isinstance(frame, zlac706_can.NoSuchRegister)
                       and frame.register == ALARM_REGISTER))  # fmt: skip
CAN_CODECS = {
    "zlac706_can.CommandDecoder": Codec(
        zlac706_can.CommandDecoder, can_tests.commands, zlac706_can.encode, CanCommand),
    "zlac706_can.ReplyDecoder": Codec(
        zlac706_can.ReplyDecoder, _unambiguous_replies, zlac706_can.encode, CanReply),
}


def split_at(wire: bytes, cuts: list[int]) -> list[bytes]:
    """``wire`` cut at the positions ``cuts`` name (taken modulo its length)."""
    points = [0, *sorted({cut % len(wire) for cut in cuts} - {0}), len(wire)]
    return [wire[start:end] for start, end in pairwise(points)]


@st.composite
def fragments(draw, codec: Codec) -> bytes:
    """A piece of a real frame: what a reconnect or a lost byte leaves on the line."""
    wire = codec.encode(draw(codec.frames))
    start = draw(st.integers(0, len(wire) - 1))
    return wire[start : draw(st.integers(start + 1, len(wire)))]


def stream_machine(codec: Codec) -> type[RuleBasedStateMachine]:
    """A state machine over ``codec``'s byte-stream decoder (see the module docstring)."""
    noise = st.binary(min_size=1, max_size=64) | fragments(codec)

    class StreamDecoderMachine(RuleBasedStateMachine):
        def __init__(self) -> None:
            super().__init__()
            self.decoder = codec.decoder()
            self.in_step = True  # the next byte fed starts a frame for the decoder too
            self.expected: list[object] = []  # what the next drain must begin with

        @rule(frame=codec.frames, cuts=st.lists(st.integers(1, 1000), max_size=3))
        def feed_frame_in_pieces(self, frame, cuts) -> None:
            *pieces, last = split_at(codec.encode(frame), cuts)
            for piece in pieces:
                self.decoder.feed(piece)
                self.drain_and_check()
            self.decoder.feed(last)
            if self.in_step:
                self.expected.append(frame)

        @rule(data=noise)
        def feed_noise(self, data) -> None:
            self.decoder.feed(data)
            self.in_step = False

        @rule(frame=codec.frames, flip=st.integers(1, 255))
        def feed_bad_checksum(self, frame, flip) -> None:
            wire = codec.encode(frame)
            bad = wire[:-1] + bytes([wire[-1] ^ flip])
            self.decoder.feed(bad)
            if self.in_step:
                self.expected.append(ChecksumMismatch(bad, wire[-1], bad[-1]))
            self.in_step = False

        @rule()
        def drain(self) -> None:
            self.drain_and_check()
            assert self.decoder.pending == 0 or not self.in_step, "whole frames drain to empty"
            self.in_step = self.decoder.pending == 0

        def drain_and_check(self) -> None:
            events = list(self.decoder.events())
            for event in events:
                assert isinstance(event, (*ERROR_EVENTS, codec.kinds)), event
            assert events[: len(self.expected)] == self.expected
            if self.in_step:
                assert events == self.expected
            self.expected.clear()
            assert self.decoder.pending < self.decoder.max_frame

        def teardown(self) -> None:
            self.drain_and_check()

    return StreamDecoderMachine


def _matches(event: object, expectation: object) -> bool:
    """``expectation``: the frame itself, a ``Discarded`` (its reason not compared) or None
    (noise: any event of the protocol)."""
    if expectation is None:
        return True
    if isinstance(expectation, Discarded):
        return isinstance(event, Discarded) and event.data == expectation.data
    return event == expectation


def can_machine(codec: Codec) -> type[RuleBasedStateMachine]:
    """A state machine over ``codec``'s CAN decoder, modelled message by message."""

    class CanDecoderMachine(RuleBasedStateMachine):
        def __init__(self) -> None:
            super().__init__()
            self.decoder = codec.decoder()
            self.queue: deque[object] = deque()  # per queued message, what it must decode to
            self.dropped = 0

        def feed(self, message: CanFrame, expectation: object) -> None:
            self.decoder.feed(message)
            if len(self.queue) == self.decoder.max_pending:
                self.queue.popleft()
                self.dropped += 1
            self.queue.append(expectation)

        @rule(frame=codec.frames)
        def feed_frame(self, frame) -> None:
            self.feed(codec.encode(frame), frame)

        @rule(message=can_tests.can_frames)
        def feed_noise(self, message) -> None:
            self.feed(message, None)

        @rule(frame=codec.frames, keep=st.integers(0, 8), high_byte=st.integers(1, 255))
        def feed_malformed(self, frame, keep, high_byte) -> None:
            """Cut short to ``keep`` bytes, or (``keep`` 8) a non-zero register high byte."""
            message = codec.encode(frame)
            data = bytearray(message.data)
            data[2] = high_byte
            bad = CanFrame(message.arbitration_id, bytes(data[:keep]))
            self.feed(bad, Discarded(bad.data, "malformed"))

        @rule(extra=st.integers(1, 50))
        def flood(self, extra) -> None:
            """More messages than the queue holds: the oldest go, reported as one event."""
            for _ in range(self.decoder.max_pending + extra):
                self.feed(CanFrame(0x7FF, b""), Discarded(b"", "not 8 bytes"))

        @rule()
        def drain(self) -> None:
            events = list(self.decoder.events())
            if self.dropped:
                first = events.pop(0)
                assert isinstance(first, Discarded) and first.data == b""
                assert first.reason.startswith(f"{self.dropped} frames dropped")
            assert len(events) == len(self.queue)
            for event, expectation in zip(events, self.queue, strict=True):
                assert isinstance(event, (Discarded, codec.kinds)), event
                assert _matches(event, expectation), (event, expectation)
            self.queue.clear()
            self.dropped = 0

        @invariant()
        def queue_is_bounded(self) -> None:
            assert self.decoder.pending == len(self.queue) <= self.decoder.max_pending

    return CanDecoderMachine


@pytest.mark.parametrize("codec", STREAM_CODECS.values(), ids=STREAM_CODECS)
def test_stream_decoder_keeps_in_step_with_the_wire(codec: Codec) -> None:
    run_state_machine_as_test(stream_machine(codec), settings=MODEST)


@pytest.mark.parametrize("codec", CAN_CODECS.values(), ids=CAN_CODECS)
def test_can_decoder_answers_every_message_in_order(codec: Codec) -> None:
    run_state_machine_as_test(can_machine(codec), settings=MODEST)
