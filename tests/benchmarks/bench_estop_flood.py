"""E-stops put in a loop on a demo: does the gateway keep up, and what does it tell?

Not a test (pytest does not collect it). Everything on this machine, on 127.0.0.1 with
multicast scouting off: ``busgate demo`` as a child process (its buses over its workers), a
zenoh session here; every process ended by its PID.

    .venv/bin/python tests/benchmarks/bench_estop_flood.py [--rate 2000] [--seconds 2]

One session puts an e-stop (``{"client": "flooder"}``) on ``busgate/demo/estop`` ``--rate``
times a second for ``--seconds`` (paced by a sleep, so the rate is at most that), subscribed
to the demo's events. Printed: the puts; how many the gateway had told (its ``estop`` events,
each with the ``suppressed`` it counts) when the last put went and each half second after,
until all are or 15 s have passed; the events; a status query on the same session and how
long its answer took (behind what the session sent before it); the demo's RSS before and
after. Then a reset put, and whether ``la1`` moves again (it should: the reset is the last
word).

Run with another checkout's interpreter (``OTHER/.venv/bin/python tests/benchmarks/...``) it
runs that checkout's demo.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.*

import zenoh
from bench_flight import rss_mib  # sibling scripts': their folder is on the path
from bench_scale import positive

from busgate.schemas.zenoh_session import session_config
from tests.conftest import unused_loopback_port
from tests.gateway_process import DemoProcess

DRAIN_S = 15.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--rate", type=positive(float), default=2000.0, help="puts a second at most"
    )
    parser.add_argument("--seconds", type=positive(float), default=2.0)
    args = parser.parse_args()
    demo = DemoProcess(f"tcp/127.0.0.1:{unused_loopback_port()}", "--no-dashboard")
    told: list[dict] = []
    try:
        with zenoh.open(session_config(mode="client", connect=[demo.endpoint])) as session:
            session.declare_subscriber(
                "busgate/demo/events",
                lambda sample: told.append(json.loads(sample.payload.to_bytes())),
            )
            time.sleep(1.0)
            rss_before = rss_mib(demo.process.pid)
            puts, start = 0, time.monotonic()
            while time.monotonic() - start < args.seconds:
                session.put("busgate/demo/estop", b'{"client": "flooder"}')
                puts += 1
                time.sleep(1 / args.rate)
            last_put = time.monotonic()
            took_s = last_put - start
            print(f"{puts} e-stops put in {took_s:.2f} s ({puts / took_s:.0f}/s)")

            def counted() -> int:
                return sum(1 + e.get("suppressed", 0) for e in told if e["type"] == "estop")

            while True:
                since = time.monotonic() - last_put
                print(f"  {since:5.2f} s after the last put: {counted()} told")
                if counted() >= puts or since > DRAIN_S:
                    break
                time.sleep(0.5)
            kinds = Counter(f"{e['type']} {e['device']}" for e in told if e["type"] != "estop")
            print(f"estop events: {len(told) - kinds.total()}; other events: {dict(kinds)}")
            asked = time.monotonic()
            replies = list(session.get("busgate/demo/dev/la1/cmd", payload=b'{"op":"status"}',
                                       timeout=30))  # fmt: skip
            answer = replies[0].ok.payload.to_bytes() if replies and replies[0].ok else b"none"
            print(f"a status query on the same session answered in "
                  f"{time.monotonic() - asked:.3f} s: {answer[:60]!r}")  # fmt: skip
            rss_after = rss_mib(demo.process.pid)
            print(f"the demo's RSS: {rss_before:.1f} MiB before, {rss_after:.1f} after")
            session.put("busgate/demo/estop/reset", b'{"client": "flooder"}')
            time.sleep(1.0)
            replies = list(session.get("busgate/demo/dev/la1/cmd", timeout=10,
                                       payload=b'{"op":"move","position":900}'))  # fmt: skip
            moved = bool(replies) and replies[0].ok is not None
            body = (replies[0].ok or replies[0].err).payload.to_bytes() if replies else b"none"
            print(f"la1 moved after the reset: {moved and json.loads(body).get('ok')}")
    finally:
        demo.terminate()


if __name__ == "__main__":
    main()
