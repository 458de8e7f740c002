"""Device-side figures from a simulator's wire record (``wire_analysis.analyse``), on records
written by hand: what counts as a gap, a follow interval, and a frame read in one go."""

from __future__ import annotations

import pytest

from busgate.gateway.sim.recorder import Recorder, WireRecord
from busgate.gateway.sim.wire_analysis import analyse

MS = 0.001


def rx(start_ms: float, frame: str = "Write", device_id: int | None = 1, *,
       arrived_ms: float | None = None) -> WireRecord:
    arrived = None if arrived_ms is None else arrived_ms * MS
    return WireRecord("rx", start_ms * MS, start_ms * MS + 0.2 * MS, "00", frame, device_id,
                      arrived)


def tx(start_ms: float, device_id: int = 1) -> WireRecord:
    return WireRecord("tx", start_ms * MS, start_ms * MS + 0.2 * MS, "00", "WriteAck", device_id)


def test_follow_intervals_are_per_device_so_two_streams_on_one_bus_are_not_halved() -> None:
    """Two ZLAC706 on CAN, each written every 20 ms, 10 ms apart from each other."""
    records = [rx(t + offset, device_id=node)
               for t in range(0, 100, 20) for node, offset in ((1, 0), (2, 10))]
    figures = analyse(records, min_gap_s=0.0, follow_frames=("Write",), follow_period_s=0.020)
    assert figures.follow_frames == 10
    assert figures.follow_intervals_under_period == 0
    assert figures.smallest_follow_interval_s == pytest.approx(0.020)


def test_an_early_tick_of_one_device_is_counted() -> None:
    records = [rx(0), rx(20), rx(39), rx(10, device_id=2), rx(30, device_id=2)]
    figures = analyse(records, min_gap_s=0.0, follow_frames=("Write",), follow_period_s=0.020)
    assert figures.follow_intervals_under_period == 1
    assert figures.smallest_follow_interval_s == pytest.approx(0.019)


def test_gaps_after_a_reply_and_after_a_silent_frame_are_told_apart() -> None:
    records = [rx(0.0, "Status"), tx(0.5), rx(1.2, "Status"),  # 0.5 ms after the reply's end
               rx(3.0, "Follow", None)]  # 1.6 ms after the last frame's end
    figures = analyse(records, min_gap_s=1 * MS)
    assert figures.gaps_after_reply_below_minimum == 1
    assert figures.smallest_gap_after_reply_s == pytest.approx(0.0005)
    assert figures.gaps_after_silent_frame_below_minimum == 0
    assert figures.mean_turnaround_s == pytest.approx(0.0003)


def test_frames_read_in_one_go_are_unresolved_not_a_short_gap_or_interval() -> None:
    records = [rx(0, arrived_ms=0.3), rx(0.3, arrived_ms=0.6), rx(0.5, arrived_ms=0.6)]
    figures = analyse(records, min_gap_s=1 * MS, follow_frames=("Write",),
                      follow_period_s=0.020)
    assert figures.unresolved == 1
    assert figures.gaps_after_silent_frame_below_minimum == 1  # the first two: read apart
    assert figures.follow_intervals_under_period == 1


def test_a_recorder_that_keeps_nothing_writes_every_record_to_its_file(tmp_path) -> None:
    """The demo's and ``busgate sim``'s recorders kept their last 100,000 records in memory,
    which nothing read: some 35 MB a simulator, grown over the first hour of a demo."""
    path = tmp_path / "wire.jsonl"
    records = [WireRecord("rx", n / 100, n / 100 + 0.001, "00", "Frame", 1) for n in range(5)]
    with path.open("w") as stream:
        recorder = Recorder(stream, keep=0)
        for record in records:
            recorder.record(record)
    assert recorder.records == [] and recorder.received() == []
    assert [WireRecord.from_json(line) for line in path.read_text().splitlines()] == records
    kept = Recorder(keep=2)
    for record in records:
        kept.record(record)
    assert kept.records == records[-2:]
