"""``busgate bench`` end to end: it starts the simulator, runs the real bus, and reports the
figures it promises. Only facts that hold by construction are asserted (the gap, no interval
under the period, something exchanged); rates and jitter depend on the machine and belong to
the README, and so do the device side's figures: the simulator stamps a frame when it reads
the pty, on the same cores, so a late read makes a gap look short that was not."""

from __future__ import annotations

import json
import subprocess
import sys

from busgate.gateway.cli import build_parser, main

#: What the device side reports, whatever its values.
DEVICE_SIDE = {"frames_received", "smallest_gap_after_reply_ms", "gaps_after_reply_below_minimum",
               "follow_frames", "smallest_follow_interval_ms", "follow_intervals_under_period"}


def bench(*arguments: str) -> dict:
    command = [sys.executable, "-m", "busgate.gateway.cli", "bench", "--json", *arguments]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def exchanged(figures: dict) -> float:
    """Frames sent in the measured window: a count, whatever the rate."""
    return figures["frames_out_per_s"] * figures["seconds"]


def test_bench_reports_what_it_achieved_on_the_simulator() -> None:
    figures = bench("--protocol", "inspire_la", "--ids", "1,2", "--seconds", "1",
                    "--reply-margin-ms", "5")  # a loaded host: polls still fit between ticks
    assert exchanged(figures) >= 1 and figures["frames_in_per_s"] > 0
    assert figures["smallest_gap_ms"] >= 1.0
    assert figures["follow_intervals"] >= 1 and figures["follow_error_min_ms"] >= 0
    device = figures["device_side"]
    assert device.keys() >= DEVICE_SIDE, sorted(device)
    assert device["frames_received"] >= 1, "the simulator's record covers the window"


def test_the_polling_yardstick_exchanges_with_every_device_on_the_same_port() -> None:
    """Polling only, ``--baseline`` is a bare polling loop: it gets replies (a loop that wrote
    without reading would count every poll a timeout), and its rate is the same order as the
    gateway's (both wait the reply and the gap)."""
    figures = bench("--protocol", "inspire_la", "--ids", "1,2", "--seconds", "1",
                    "--follow-period-ms", "0", "--poll-hz", "1000", "--baseline")
    bare = figures["baseline"]
    assert bare["frames_out_per_s"] > 0 and bare["timeouts"] < bare["frames_out_per_s"] / 10
    assert figures["frames_out_per_s"] > bare["frames_out_per_s"] / 4
    assert "follow_error_p99_ms" not in bare


def test_bench_on_can_through_the_slcan_simulator() -> None:
    figures = bench("--protocol", "zlac706_can", "--seconds", "1", "--follow-period-ms", "20",
                    "--reply-margin-ms", "10")
    assert exchanged(figures) >= 1 and figures["follow_intervals"] >= 1
    assert figures["follow_error_min_ms"] >= 0


def test_bench_refuses_a_bad_setting_in_one_line() -> None:
    command = [sys.executable, "-m", "busgate.gateway.cli", "bench", "--protocol", "inspire_la",
               "--follow-period-ms", "5", "--seconds", "1"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "follow_period_ms" in result.stderr


def test_kind_is_the_protocol_option_under_its_earlier_name(capsys) -> None:
    """Scripts written for earlier releases say ``--kind``."""
    assert build_parser("bench").parse_args(["bench", "--kind", "zlac706_can"]).protocol == (
        "zlac706_can")
    assert main(["bench", "--kind", "inspire_la", "--ids", ","]) == 2
    assert capsys.readouterr().err == "busgate bench: error: --ids names no device\n"
