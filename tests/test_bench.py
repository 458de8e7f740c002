"""``busgate bench`` end to end: it starts the simulator, runs the real bus, and reports the
figures it promises. Only facts that hold by construction are asserted (the gap, no interval
under the period, something exchanged); rates and jitter depend on the machine and belong to
the README, and so do the device side's figures: the simulator stamps a frame when it reads
the pty, on the same cores, so a late read makes a gap look short that was not."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from busgate.gateway.cli import bench as bench_module
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


@pytest.fixture
def nothing_opens(monkeypatch: pytest.MonkeyPatch) -> None:
    """A refusal comes before the simulator starts or a bus is built."""

    def opened(*_: object) -> None:
        raise AssertionError("the bench opened something before refusing")

    monkeypatch.setattr(bench_module, "SimProcess", opened)
    monkeypatch.setattr(bench_module, "build_bus", opened)


@pytest.mark.parametrize(
    ("arguments", "refusal"),
    [
        (["--protocol", "inspire_la", "--ids", "1,2,3", "--min-gap-ms", "0", "--poll-hz", "200"],
         "buses[0].min_gap_ms: inspire_la needs at least 1 ms"),
        (["--protocol", "inspire_la", "--ids", "1,1"],
         "buses[0].devices[1].id: id 1 is used twice on the bus"),
        (["--protocol", "zlac706_rs232", "--ids", "1,2"],
         "buses[0].devices: zlac706_rs232 frames carry no device id, so a port drives one "
         "device, not several"),
        (["--protocol", "inspire_la", "--port", "/dev/pts/nonexistent", "--ids", "999"],
         "buses[0].devices[0].id: 999 is outside 1–254"),
        (["--protocol", "inspire_la", "--port", "/dev/pts/nonexistent", "--ids", "255"],
         "buses[0].devices[0].id: 255 is outside 1–254"),
        # Refused by the bench, not by the simulator it would start (that told it twice).
        (["--protocol", "inspire_la", "--ids", "0"], "buses[0].devices[0].id: 0 is outside 1–254"),
    ],
)  # fmt: skip
def test_bench_runs_only_a_bus_a_config_would_accept(
    capsys: pytest.CaptureFixture[str], nothing_opens: None, arguments: list[str], refusal: str
) -> None:
    """The bench's bus is refused as a config file's would be, in the config's words."""
    assert main(["bench", "--seconds", "1", *arguments]) == 2
    assert capsys.readouterr().err == f"busgate bench: error: {refusal}\n"


@pytest.mark.parametrize(
    ("arguments", "refusal"),
    [
        (["--ids", "1,x"], "argument --ids: not a list of ids: '1,x'"),
        *((["--seconds", seconds, "--follow-period-ms", period],
           f"argument --seconds: must be a number of seconds above 0 and at most 31536000, "
           f"not {seconds}")
          for seconds in ("-1", "0", "nan", "inf") for period in ("0", "10")),
    ],
)  # fmt: skip
def test_bench_refuses_a_bad_option_value_as_it_parses(
    capsys: pytest.CaptureFixture[str], nothing_opens: None, arguments: list[str], refusal: str
) -> None:
    """As ``busgate sim`` refuses its ``--ids``; a measurement takes some time, and a finite
    one (a year at most)."""
    with pytest.raises(SystemExit) as exited:
        main(["bench", "--protocol", "inspire_la", *arguments])
    assert exited.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == f"busgate bench: error: {refusal}"
