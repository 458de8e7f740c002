"""What a CAN owner's look at its bus costs a frame: the idle work of a heartbeat bus.

Not a test (pytest does not collect it). A ``CanBusOwner`` on ``interface = "socketcan"``,
whose class is ``unix_can.UnixCanBus`` here (this host has no SocketCAN), and the bus's far
end in this process. Each round the far end sends a batch of heartbeats (five nodes, eight
frames: what an idle bus takes in a look), the thread sleeps half a millisecond (as the owner
pauses between looks, so the look starts cold), and one look (``take_unsolicited``) takes
them: its thread CPU a frame, the median of ``RUNS`` runs of ``ROUNDS`` rounds. The figure
depends on the host: compare checkouts turn about (each with its own checkout's venv, this
file and ``unix_can.py`` copied in).

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

from busgate.codecs import zlac706_can as zcan
from busgate.gateway.bus.can_owner import CanBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.families import link_timing

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


def main() -> int:
    runs = int(sys.argv[1]) if len(sys.argv) > 1 else 3
    costs = [look_cost_us() for _ in range(runs)]
    print(f"a look at a SocketCAN-like bus: {statistics.median(costs):.2f} µs of thread CPU a "
          f"frame (median of {runs} runs: {', '.join(f'{c:.2f}' for c in costs)})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
