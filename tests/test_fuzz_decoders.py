"""Every decoder under a long Hypothesis run: arbitrary chunks of bytes (or CAN frames), fed
in any split, only ever make events, keep the buffer bounded, and decode a valid frame that
follows the noise. Slow: outside the default run (``.venv/bin/python -m pytest -m slow``)."""

from __future__ import annotations

import time

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from busgate.codecs import ds_servo, inspire_la, zlac706_can, zlac706_rs232
from busgate.codecs.can_frame import CanFrame
from busgate.codecs.framing import ChecksumMismatch, Discarded

pytestmark = pytest.mark.slow

LONG = settings(max_examples=5000, deadline=None, suppress_health_check=list(HealthCheck))

STREAM_DECODERS = [
    (inspire_la.ReplyDecoder, bytes.fromhex("aa55040101625802c2")),
    (inspire_la.CommandDecoder, bytes.fromhex("55aa04032137e8034a")),
    (ds_servo.ReplyDecoder, bytes.fromhex("fff50104 0007fff4".replace(" ", ""))),
    (ds_servo.CommandDecoder, bytes.fromhex("ffff0104023802be")),
    (zlac706_rs232.ReplyDecoder, bytes.fromhex("e1001cfd")),
    (zlac706_rs232.CommandDecoder, bytes.fromhex("0527103c")),
]


@pytest.mark.parametrize(("decoder_class", "good"), STREAM_DECODERS)
def test_stream_decoders_survive_anything(decoder_class, good) -> None:
    @LONG
    @given(st.lists(st.binary(max_size=300), max_size=40))
    def run(chunks):
        decoder = decoder_class()
        for chunk in chunks:
            decoder.feed(chunk)
            events = list(decoder.events())
            assert decoder.pending < decoder.max_frame
            for event in events:
                assert not isinstance(event, Exception)
        # Noise can open a long (bad) frame that swallows what follows; once enough bytes have
        # come for that frame to fail its checksum, the decoder resynchronises on good frames.
        repeats = decoder.max_frame // len(good) + 2
        decoder.feed(good * repeats)
        tail = [e for e in decoder.events() if not isinstance(e, Discarded | ChecksumMismatch)]
        assert tail, "good frames after the noise decode"

    run()


@pytest.mark.parametrize("decoder_class", [zlac706_can.ReplyDecoder, zlac706_can.CommandDecoder])
def test_can_decoders_survive_any_frame(decoder_class) -> None:
    frames = st.builds(CanFrame, st.integers(0, 0x7FF), st.binary(max_size=8))

    @LONG
    @given(st.lists(frames, max_size=200))
    def run(batch):
        decoder = decoder_class()
        for frame in batch:
            decoder.feed(frame)
        assert len(list(decoder.events())) == len(batch)

    run()


def _decode_all(decoder_class, data: bytes, chunk: int = 64) -> float:
    """Seconds to feed ``data`` in ``chunk``-byte reads and drain every event (best of 5: the
    best run is the one the shared machine disturbed least)."""
    best = float("inf")
    for _ in range(5):
        decoder = decoder_class()
        started = time.perf_counter()
        for offset in range(0, len(data), chunk):
            decoder.feed(data[offset : offset + chunk])
            for _event in decoder.events():
                pass
        best = min(best, time.perf_counter() - started)
    return best


@pytest.mark.parametrize(("decoder_class", "good"), STREAM_DECODERS)
def test_stream_decoders_take_linear_time_on_hostile_input(decoder_class, good) -> None:
    """The worst inputs for a resynchronising decoder: its own header over and over (each a
    candidate frame start), and frames cut short before their checksum. Ten times the bytes
    must take about ten times as long, not a hundred (a rescan per byte would be quadratic):
    the bound, 40, leaves room for a loaded machine (idle, the ratios are 8-15) and still
    catches a quadratic decoder."""
    header, truncated = good[:2], good[:-1]
    for pattern in (header, truncated, bytes(range(256))):
        small = pattern * (20_000 // len(pattern))
        ratio = _decode_all(decoder_class, small * 10) / _decode_all(decoder_class, small)
        assert ratio < 40, f"{decoder_class.__qualname__} on {pattern[:8].hex()}…: ×{ratio:.1f}"
