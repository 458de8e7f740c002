"""What a CAN owner's look at its bus costs a frame: the idle work of a heartbeat bus.

Not a test (pytest does not collect it). A ``CanBusOwner`` on ``interface = "socketcan"``,
whose class is ``unix_can.UnixCanBus`` here (this host has no SocketCAN), and the bus's far
end in this process. Each round the far end sends a batch of heartbeats (five nodes, eight
frames: what an idle bus takes in a look), the thread sleeps half a millisecond (as the owner
pauses between looks, so the look starts cold), and one look (``take_unsolicited``) takes
them: its thread CPU a frame, the median of ``RUNS`` runs of ``ROUNDS`` rounds. Then the whole
of a heartbeat bus thread's work, on a bus runner built as the daemon builds it (five ZLAC706,
not started): each round five heartbeats (ten frames, a position and a current-and-speed
each), a pause of the owner's ``idle_batch_s`` (as the daemon's looks are apart), one look and
the states published: its thread CPU a heartbeat in three parts, the look (the owner: receive,
date, decode), the devices and their drivers, and the states (``Telemetry.publish``). The
figures depend on the host: compare checkouts turn about (each with its own checkout's venv,
this file and ``unix_can.py`` copied in).

    .venv/bin/python tests/benchmarks/bench_can_look.py [RUNS]
"""

from __future__ import annotations

import os
import statistics
import sys
import threading
import time

import can
import unix_can
from usage import arguments

from busgate.codecs import zlac706_can as zcan
from busgate.gateway.bus.can_owner import CanBusOwner
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.service.assembly import build_bus
from busgate.schemas.config import parse_config

ROUNDS = 3000
#: Five nodes' heartbeat positions, three of them twice: one look's worth.
BATCH = [
    can.Message(arbitration_id=node, data=bytes.fromhex("00fe002000000007"), is_extended_id=False)
    for node in (1, 2, 3, 4, 5, 1, 2, 3)
]


def look_cost_us() -> float:
    """One run: the thread CPU of a look, in µs a frame."""
    unix_can.register()
    channel = f"look-{os.getpid()}"
    heard: list[object] = []
    owner = CanBusOwner(
        "socketcan", channel, {}, zcan, link_timing("zlac706_can", 500_000, margin_s=0.002),
        BusCounters(0.0), on_unsolicited=lambda event, when: heard.append(event),
    )
    with unix_can.listening(channel) as server:
        opening = threading.Thread(target=owner.open)
        opening.start()
        far = unix_can.UnixCanBus(channel, accepted=server.accept()[0])
        opening.join()
    spent = 0.0
    try:
        for _ in range(ROUNDS):
            for message in BATCH:
                far.send(message)
            time.sleep(0.0005)
            start = time.thread_time()
            owner.take_unsolicited()
            spent += time.thread_time() - start
    finally:
        owner.close()
        far.shutdown()
    if len(heard) != ROUNDS * len(BATCH):
        raise RuntimeError(f"{len(heard)} heartbeats heard of {ROUNDS * len(BATCH)}")
    return spent * 1e6 / len(heard)


#: The rounds of ``heartbeat_cost_us`` (each sleeps an idle batch: some 2.5 s a run).
HEARTBEAT_ROUNDS = 300
NODES = range(1, 6)


def heartbeat_cost_us() -> tuple[float, float, float]:
    """One run: a heartbeat bus thread's CPU a heartbeat, in µs: the look, the devices and
    drivers, the states."""
    unix_can.register()
    channel = f"heartbeats-{os.getpid()}"
    config = parse_config({"gateway": {"name": "bench"}, "buses": [{
        "name": "can0", "transport": "can", "interface": unix_can.INTERFACE, "channel": channel,
        "devices": [{"name": f"w{n}", "kind": "zlac706", "id": n, "heartbeat_ms": 10}
                    for n in NODES]}]})
    states: list[dict] = []
    runner = build_bus(config.buses[0], on_state=lambda device, state: states.append(state))
    owner, telemetry = runner.owner, runner.telemetry
    with unix_can.listening(channel) as server:
        opening = threading.Thread(target=owner.open)
        opening.start()
        far = unix_can.UnixCanBus(channel, accepted=server.accept()[0])
        opening.join()
    to_devices, in_devices = owner.on_unsolicited, [0.0]

    def timed(event: object, when: float) -> None:
        start = time.thread_time()
        to_devices(event, when)
        in_devices[0] += time.thread_time() - start

    owner.on_unsolicited = timed
    looking = publishing = 0.0
    try:
        for round_ in range(HEARTBEAT_ROUNDS):
            for node in NODES:  # as a simulated node sends them: the codec's own frames
                far.send(_message(zcan.HeartbeatPosition(node, round_ * 7 + node)))
                far.send(_message(zcan.HeartbeatCurrentSpeed(node, 50, 256)))
            time.sleep(owner.idle_batch_s)
            start = time.thread_time()
            owner.take_unsolicited()
            looked = time.thread_time()
            telemetry.publish(now())
            publishing += time.thread_time() - looked
            looking += looked - start
    finally:
        owner.close()
        far.shutdown()
    if len(states) < HEARTBEAT_ROUNDS * len(NODES):
        raise RuntimeError(f"{len(states)} states of {HEARTBEAT_ROUNDS * len(NODES)} heartbeats")
    beats = HEARTBEAT_ROUNDS * len(NODES) / 1e6
    return (looking - in_devices[0]) / beats, in_devices[0] / beats, publishing / beats


def _message(event: object) -> can.Message:
    frame = zcan.encode(event)
    return can.Message(arbitration_id=frame.arbitration_id, data=frame.data, is_extended_id=False)


def main() -> int:
    runs = arguments(__doc__, ("runs", int, 3, "how many runs")).runs
    costs = [look_cost_us() for _ in range(runs)]
    print(f"a look at a SocketCAN-like bus: {statistics.median(costs):.2f} µs of thread CPU a "
          f"frame (median of {runs} runs: {', '.join(f'{c:.2f}' for c in costs)})")
    parts = [heartbeat_cost_us() for _ in range(runs)]
    look, devices, states = (statistics.median(part) for part in zip(*parts, strict=True))
    print(f"a heartbeat bus thread, µs of thread CPU a heartbeat (median of {runs} runs): "
          f"{look + devices + states:.1f} in all, the look {look:.1f}, the devices and drivers "
          f"{devices:.1f}, the states {states:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
