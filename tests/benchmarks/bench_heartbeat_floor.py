"""The heartbeats' floor: what the gateway's heartbeat figure costs beside the least Python that
publishes the same states, turn about in one run.

Not a test (pytest does not collect it). ``bench_zenoh.telemetry_cpu_apart``'s setup (20
ZLAC706 heartbeating every 10 ms, four buses of five, each bus's simulator in a process of its
own behind ``unix_can.py``, a subscriber in a child) run twice a pair: once with the gateway,
once with a bare loop in its place. The bare loop is what the gateway must do at least, in
the shape the gateway does it: one thread a bus that looks at its socket every
``CanBusOwner.idle_batch_s`` and takes every waiting frame with its receive time, pairs a
heartbeat's two frames into one state (``ts``, device, position, current, speed), and a
publishing thread that puts the states with zenoh every ``TELEMETRY_EVERY_S``. No codec, no
driver, no joint, no check: its CPU is the host's price of the wake-ups, the syscalls, the
zenoh puts and a minimum of Python at that hour, so the pair says how far the gateway is from
what the host allows (the goal, 10 % of a core, is a figure of the host). The floor moves with
the host's load as much as the gateway does: compare ratios over several pairs, not one.

    .venv/bin/python tests/benchmarks/bench_heartbeat_floor.py [PAIRS] [SECONDS]
"""

from __future__ import annotations

import collections
import socket
import statistics
import subprocess
import sys
import threading
import time

import orjson
import unix_can
import zenoh
from bench_zenoh import SUBSCRIBER, _apart_simulators, free_endpoint, telemetry_cpu_apart
from usage import arguments

from busgate.codecs.zlac706_can.frames import HeartbeatRegister
from busgate.codecs.zlac706_common import amps_from_current_raw, rpm_from_speed_raw
from busgate.gateway.api.bridge import TELEMETRY_EVERY_S
from busgate.gateway.bus.can_owner import (
    CANFD_MTU,
    RECEIVE_TIME_SPACE,
    SOCKETCAN_HEADER,
    TIMESPEC,
    CanBusOwner,
)
from busgate.schemas.zenoh_session import session_config

BUSES, NODES = 4, range(1, 6)
POSITION = int(HeartbeatRegister.POSITION)


def bare_cpu(seconds: float) -> tuple[float, float]:
    """The bare loop's CPU in % of a core, and the states a second the subscriber took."""
    with _apart_simulators(BUSES, 10) as channels:
        endpoint = free_endpoint()
        session = zenoh.open(session_config(listen=[endpoint]))
        publishers = {
            (bus, node): session.declare_publisher(
                f"busgate/bench/dev/w{bus}-{node}/state",
                congestion_control=zenoh.CongestionControl.DROP,
            )
            for bus in range(BUSES)
            for node in NODES
        }
        states: collections.deque = collections.deque()
        stop = threading.Event()
        threads = [
            threading.Thread(target=_bus, args=(bus, channel, states, stop))
            for bus, channel in enumerate(channels)
        ]
        threads.append(threading.Thread(target=_publish, args=(publishers, states, stop)))
        for thread in threads:
            thread.start()
        try:
            time.sleep(1.0)
            return _measured(endpoint, seconds)
        finally:
            stop.set()
            for thread in threads:
                thread.join()
            session.close()


def _bus(bus: int, channel: str, states: collections.deque, stop: threading.Event) -> None:
    """Every look: each waiting frame, a state made when a heartbeat's second frame comes."""
    bus_end = unix_can.UnixCanBus(channel)  # kept: its end closes the socket
    sock = bus_end.socket
    positions: dict[int, tuple[int, float]] = {}
    try:
        while not stop.wait(CanBusOwner.idle_batch_s):
            while True:
                try:
                    frame, times, _, _ = sock.recvmsg(
                        CANFD_MTU, RECEIVE_TIME_SPACE, socket.MSG_DONTWAIT
                    )
                except BlockingIOError:
                    break
                node, length = SOCKETCAN_HEADER.unpack_from(frame)
                data = frame[SOCKETCAN_HEADER.size : SOCKETCAN_HEADER.size + length]
                seconds, nanoseconds = TIMESPEC.unpack_from(times[0][2])
                if data[3] == POSITION:
                    position = int.from_bytes(data[4:], "big", signed=True)
                    positions[node] = (position, seconds + nanoseconds * 1e-9)
                elif node in positions:
                    position, ts = positions.pop(node)
                    speed = int.from_bytes(data[6:], "big", signed=True)
                    state = {
                        "ts": ts,
                        "device": f"w{bus}-{node}",
                        "position": position,
                        "current_a": amps_from_current_raw(int.from_bytes(data[4:6], "big")),
                        "speed_rpm": rpm_from_speed_raw(speed),
                    }
                    states.append(((bus, node), state))
    finally:
        bus_end.shutdown()


def _publish(publishers: dict, states: collections.deque, stop: threading.Event) -> None:
    while not stop.wait(TELEMETRY_EVERY_S):
        while states:
            key, state = states.popleft()
            publishers[key].put(orjson.dumps(state))


def _measured(endpoint: str, seconds: float) -> tuple[float, float]:
    """This process's CPU while the subscriber counts the states for ``seconds``."""
    subscriber = subprocess.Popen(
        [sys.executable, "-c", SUBSCRIBER, endpoint, str(seconds)],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        subscriber.stdout.readline()  # ready
        cpu, started = time.process_time(), time.monotonic()
        received = int(subscriber.stdout.readline())
        cpu, elapsed = time.process_time() - cpu, time.monotonic() - started
        return 100 * cpu / elapsed, received / seconds
    finally:
        subscriber.stdout.read()  # its ts steps and ages: not used here
        subscriber.wait(10)


def main() -> int:
    given = arguments(
        __doc__,
        ("pairs", int, 3, "how many pairs, gateway then bare loop"),
        ("seconds", float, 10.0, "how long each measures"),
    )
    pairs, seconds = given.pairs, given.seconds
    ratios = []
    for pair in range(1, pairs + 1):
        floor, floor_rate = bare_cpu(seconds)
        gateway, gateway_rate = telemetry_cpu_apart(seconds)
        ratios.append(gateway / floor)
        print(
            f"pair {pair}: bare loop {floor:.1f} % ({floor_rate:.0f} states/s), "
            f"gateway {gateway:.1f} % ({gateway_rate:.0f} states/s): {gateway / floor:.2f}×",
            flush=True,
        )
    print(f"gateway / bare loop: median {statistics.median(ratios):.2f}× of {pairs} pairs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
