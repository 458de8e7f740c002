"""``busgate bench`` end to end: it starts the simulator, runs the real bus, and reports the
figures it promises. Only facts that hold by construction are asserted (the gap, no interval
under the period); rates and jitter depend on this shared machine and belong to the README."""

from __future__ import annotations

import json
import subprocess
import sys


def bench(*arguments: str) -> dict:
    command = [sys.executable, "-m", "busgate.gateway.cli", "bench", "--json", *arguments]
    result = subprocess.run(command, capture_output=True, text=True, timeout=60, check=True)
    return json.loads(result.stdout)


def test_bench_reports_what_it_achieved_on_the_simulator() -> None:
    figures = bench("--kind", "inspire_la", "--ids", "1,2", "--seconds", "1")
    assert figures["frames_out_per_s"] > 50 and figures["frames_in_per_s"] > 0
    assert figures["smallest_gap_ms"] >= 1.0
    assert figures["follow_intervals"] > 20 and figures["follow_error_min_ms"] >= 0
    device = figures["device_side"]
    assert device["frames_received"] > 50 and device["gaps_after_reply_below_minimum"] == 0


def test_bench_on_can_through_the_slcan_simulator() -> None:
    figures = bench("--kind", "zlac706_can", "--seconds", "1", "--follow-period-ms", "20")
    assert figures["frames_out_per_s"] > 20 and figures["follow_intervals"] > 10


def test_bench_refuses_a_bad_setting_in_one_line() -> None:
    command = [sys.executable, "-m", "busgate.gateway.cli", "bench", "--kind", "inspire_la",
               "--follow-period-ms", "5", "--seconds", "1"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "follow_period_ms" in result.stderr
