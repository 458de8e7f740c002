"""What ``busgate record`` costs, and how well ``busgate replay`` keeps a recording's pace.

Not a test (pytest does not collect it). Everything on this machine, on 127.0.0.1 with
multicast scouting off: ``busgate demo`` (7 devices) as a child process, ``busgate record``
and ``busgate replay`` as child processes, a subscriber here; every process ended by its PID.

    .venv/bin/python tests/benchmarks/bench_record.py [--seconds 10]

1. Recording: ``busgate record`` of everything under the prefix for ``--seconds``: messages
   and bytes per second (the file's size, per device), and the recorder's CPU (utime + stime
   from /proc, % of one core).
2. Replay: the file published again at speed 1 under another prefix, received here: for
   every pair of consecutive messages of a channel, the received spacing against the
   recorded one (log times), p50/p99/max of the difference in ms.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.*

import busgate.client as bc
from busgate.gateway.bus.stats import percentile
from busgate.gateway.cli.bench import cpu_s
from busgate.gateway.recording import mcap_log
from tests.conftest import unused_loopback_port
from tests.gateway_process import BUSGATE, DemoProcess

DEVICES = 7


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    args = parser.parse_args()
    demo = DemoProcess(f"tcp/127.0.0.1:{unused_loopback_port()}", "--no-dashboard")
    path = Path(tempfile.mkdtemp(prefix="bench-record-")) / "demo.mcap"
    try:
        recorder = subprocess.Popen(
            [
                *BUSGATE,
                "record",
                "--connect",
                demo.endpoint,
                "-o",
                str(path),
                "--seconds",
                str(args.seconds),
            ],
            stderr=subprocess.PIPE,
            text=True,
        )
        recorder.stderr.readline()  # recording: its subscriptions are declared
        cpu_before, started = cpu_s(f"/proc/{recorder.pid}/stat"), time.monotonic()
        cpu = cpu_before
        while recorder.poll() is None:
            reading = cpu_s(f"/proc/{recorder.pid}/stat")  # the last reading before it ends
            cpu = cpu if math.isnan(reading) else reading
            time.sleep(0.2)
        elapsed = time.monotonic() - started
        with path.open("rb") as stream:
            found = mcap_log.summary(stream)
        size = path.stat().st_size
        print(
            f"1. busgate record, {args.seconds:g} s of the demo ({DEVICES} devices): "
            f"{found['messages'] / args.seconds:.0f} messages/s, {size / args.seconds / 1024:.1f}"
            f" KiB/s in the file ({size / args.seconds / DEVICES / 1024:.2f} KiB/s per "
            f"device); the recorder {100 * (cpu - cpu_before) / elapsed:.1f} % of one core"
        )
        heard: list[tuple[str, float]] = []
        with bc.connect(demo.endpoint, client_id="bench-record") as client:
            end = client.subscribe_raw(
                "replayed/**", lambda key, payload, ns: heard.append((key, time.monotonic()))
            )
            subprocess.run(
                [*BUSGATE, "replay", str(path), "--connect", demo.endpoint, "--prefix", "replayed"],
                check=True,
                capture_output=True,
            )
            time.sleep(0.5)
            end()
        with path.open("rb") as stream:
            recorded = [
                (m.topic, m.log_time_ns / 1e9)
                for m in mcap_log.messages(stream)
                if m.topic.rsplit("/", 1)[-1] in mcap_log.REPLAYED_LEAVES
            ]
        errors = []
        for topic in {t for t, _ in recorded}:
            ours = [at for t, at in recorded if t == topic]
            got = [at for key, at in heard if key == "replayed" + topic[len("busgate") :]]
            for n in range(1, min(len(ours), len(got))):
                errors.append(abs((got[n] - got[n - 1]) - (ours[n] - ours[n - 1])))
        ordered = sorted(errors)
        print(
            f"2. busgate replay at speed 1: {len(heard)} of {len(recorded)} messages heard; "
            f"spacing error p50 {1000 * percentile(ordered, 0.5):.2f} ms, p99 "
            f"{1000 * percentile(ordered, 0.99):.2f} ms, max {1000 * ordered[-1]:.2f} ms "
            f"(n={len(ordered)})"
        )
    finally:
        demo.terminate()


if __name__ == "__main__":
    main()
