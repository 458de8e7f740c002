"""What it costs to cross from the gateway's main process to a bus worker and back: the
measure that chose how bus workers talk to the gateway (docs/workers.md).

Not a test (pytest does not collect it). Two processes on this machine: this one (the main
process) and a child (the worker). Each way, the same messages cross the two ways a worker
could be reached, in the same run, turn about:

- ``pipe``: a Unix socket pair (``SOCK_SEQPACKET``: one message per send, never split or
  merged), each message pickled;
- ``zenoh``: a put from this process's session to a subscriber in the child's session over
  ``tcp/127.0.0.1`` (multicast scouting off), each message JSON as the gateway publishes it.

Main → worker: follow targets (``("follow", device, {"position": …})``) at ``--rate`` per
second, the e-stop among them. Worker → main: device states (the dict a driver publishes,
13 fields) at the same rate. Latency: receive time less send time, both ``time.perf_counter``
(CLOCK_MONOTONIC, one clock for every process of the host). CPU: utime + stime of each
process over the phase, per message.

    .venv/bin/python tests/benchmarks/bench_crossing.py [--seconds 5] [--rate 2000] [--rounds 2]
"""

from __future__ import annotations

import argparse
import os
import pickle
import socket
import subprocess
import sys
import threading
import time

import orjson
import zenoh
from bench_zenoh import free_endpoint, ms

from busgate.schemas.zenoh_session import session_config

STATE = {
    "ts": 1764680000.123456,
    "online": True,
    "stale": False,
    "estopped": False,
    "mode": "follow",
    "position": 1234,
    "target_position": 1240,
    "force_n": 1.5,
    "current_ma": 120,
    "temperature_c": 31,
    "faults": [],
    "last_reply_age_s": 0.002,
    "enabled": True,
}
TARGET = {"position": 1234}


def cpu_s() -> float:
    times = os.times()
    return times.user + times.system


# -- the child: the worker's side ---------------------------------------------------------------


def child(fd: int, listen: str, seconds: float, rate: int) -> None:
    """Receive main's messages both ways and answer with states both ways; report over the
    pipe: latencies of what arrived, CPU of each phase."""
    pipe = socket.socket(fileno=fd)
    session = zenoh.open(session_config(listen=[listen]))
    arrived: list[float] = []

    def on_sample(sample: zenoh.Sample) -> None:
        message = orjson.loads(sample.payload.to_bytes())
        arrived.append(time.perf_counter() - message["sent"])

    subscriber = session.declare_subscriber("bench/crossing/in", on_sample)
    publisher = session.declare_publisher("bench/crossing/out")
    for way in ("pipe", "zenoh"):
        arrived.clear()
        pipe.send(b"ready")
        start = cpu_s()
        if way == "pipe":
            while True:
                message = pickle.loads(pipe.recv(65536))
                if message is None:
                    break
                arrived.append(time.perf_counter() - message[3])
        else:
            pipe.recv(16)  # main's "done"
        inbound_cpu = cpu_s() - start
        got = list(arrived)
        start = cpu_s()
        send_states(way, pipe, publisher, seconds, rate)
        outbound_cpu = cpu_s() - start
        pipe.send(pickle.dumps(("report", way, got, inbound_cpu, outbound_cpu)))
    subscriber.undeclare()
    session.close()


def send_states(
    way: str, pipe: socket.socket, publisher: zenoh.Publisher, seconds: float, rate: int
) -> None:
    period = 1.0 / rate
    deadline = time.perf_counter()
    end = deadline + seconds
    while deadline < end:
        deadline += period
        time.sleep(max(0.0, deadline - time.perf_counter()))
        state = dict(STATE, sent=time.perf_counter())
        if way == "pipe":
            pipe.send(pickle.dumps(("state", "la1", state), pickle.HIGHEST_PROTOCOL))
        else:
            publisher.put(orjson.dumps(state))
    if way == "pipe":
        pipe.send(pickle.dumps(None))
    else:
        time.sleep(0.2)
        publisher.put(b"{}")


# -- the main process ---------------------------------------------------------------------------


def main_side(seconds: float, rate: int) -> list[dict]:
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    listen = free_endpoint()
    worker = subprocess.Popen(  # a fresh interpreter: zenoh's threads do not survive a fork
        [
            sys.executable,
            __file__,
            "--child",
            str(theirs.fileno()),
            listen,
            str(seconds),
            str(rate),
        ],
        pass_fds=[theirs.fileno()],
    )
    theirs.close()
    session = zenoh.open(session_config(connect=[listen]))
    publisher = session.declare_publisher("bench/crossing/in")
    states: list[float] = []
    done = threading.Event()

    def on_state(sample: zenoh.Sample) -> None:
        message = orjson.loads(sample.payload.to_bytes())
        if "sent" not in message:
            done.set()
        else:
            states.append(time.perf_counter() - message["sent"])

    subscriber = session.declare_subscriber("bench/crossing/out", on_state)
    time.sleep(1.0)  # the two sessions meet
    rows = []
    try:
        for way in ("pipe", "zenoh"):
            assert ours.recv(16) == b"ready"
            start = cpu_s()
            period, deadline = 1.0 / rate, time.perf_counter()
            end, sent = deadline + seconds, 0
            while deadline < end:
                deadline += period
                time.sleep(max(0.0, deadline - time.perf_counter()))
                moment = time.perf_counter()
                if way == "pipe":
                    ours.send(
                        pickle.dumps(("follow", "la1", TARGET, moment), pickle.HIGHEST_PROTOCOL)
                    )
                else:
                    publisher.put(orjson.dumps({"device": "la1", **TARGET, "sent": moment}))
                sent += 1
            if way == "pipe":
                ours.send(pickle.dumps(None))
            else:
                time.sleep(0.2)
                ours.send(b"done")
            outbound_cpu = cpu_s() - start
            states.clear()
            done.clear()
            start = cpu_s()
            got: list[float] = []
            if way == "pipe":
                while (message := pickle.loads(ours.recv(65536))) is not None:
                    got.append(time.perf_counter() - message[2]["sent"])
            else:
                done.wait(seconds + 5)
                got = list(states)
            inbound_cpu = cpu_s() - start
            _, _, arrived, child_in_cpu, child_out_cpu = pickle.loads(ours.recv(1 << 24))
            rows.append(row(way, "main → worker", sent, arrived, outbound_cpu + child_in_cpu))
            rows.append(row(way, "worker → main", sent, got, inbound_cpu + child_out_cpu))
    finally:
        subscriber.undeclare()
        session.close()
        worker.wait(timeout=10)
    return rows


def row(way: str, direction: str, sent: int, latencies: list[float], cpu: float) -> dict:
    return {
        "way": way,
        "direction": direction,
        "sent": sent,
        "arrived": len(latencies),
        "p50_ms": ms(latencies, 0.5) if latencies else None,
        "p99_ms": ms(latencies, 0.99) if latencies else None,
        "cpu_us_per_message": round(cpu / max(1, len(latencies)) * 1e6, 1),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--rate", type=int, default=2000, help="messages a second each way")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--child", nargs=4, help=argparse.SUPPRESS)  # the worker: fd, endpoint …
    args = parser.parse_args()
    if args.child:
        fd, listen, seconds, rate = args.child
        child(int(fd), listen, float(seconds), int(rate))
        return 0
    print("way    direction       sent  arrived  p50 ms  p99 ms  CPU µs/message (both ends)")
    for _ in range(args.rounds):
        for r in main_side(args.seconds, args.rate):
            print(
                f"{r['way']:<6} {r['direction']:<14} {r['sent']:>6} {r['arrived']:>8} "
                f"{r['p50_ms']!s:>7} {r['p99_ms']!s:>7} {r['cpu_us_per_message']:>8}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
