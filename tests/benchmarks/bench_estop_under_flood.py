"""An e-stop put while other clients flood the gateway with follow targets or commands: how
long until it reaches the buses?

Not a test (pytest does not collect it). The gateway's zenoh side (``ZenohBridge``) in this
process, on 127.0.0.1 with multicast scouting off, over one LA bus that is never opened, so
that what is timed is zenoh and the bridge alone: from a client's put on the e-stop key to the
moment the bridge hands the e-stop to its buses (``GatewayApi.stop_every_bus``). ``--floods``
child processes send to ``la1`` as fast as they can meanwhile (each its own session, as a
runaway control loop would), by ``--kind``: follow targets, commands put, commands got
(never waiting for the answers), or clients' liveliness tokens declared and undeclared;
each ends by its PID. The commands are ones no device
takes, refused at once: what is timed is the flood's cost to zenoh and the bridge. Printed:
p50, p90 and the worst of ``--estops`` e-stops, with no flood and with it.

    .venv/bin/python tests/benchmarks/bench_estop_under_flood.py [--floods 2] [--estops 25]
        [--kind follow|cmd-put|cmd-get|clients]

Run with another checkout's interpreter (``OTHER/.venv/bin/python tests/benchmarks/...``) it
times that checkout's bridge.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the repository: tests.*

import zenoh
from bench_scale import positive
from bench_zenoh import free_endpoint, ms

from busgate.gateway.api.bridge import ZenohBridge
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.bus.clock import tune_interpreter
from busgate.gateway.service.assembly import build_bus
from busgate.schemas.config import parse_config
from busgate.schemas.zenoh_session import session_config
from tests.test_zenoh_api import config_for

FLOODER = """
import sys, time, zenoh
from busgate.schemas.zenoh_session import session_config
session = zenoh.open(session_config(mode="client", connect=[sys.argv[1]]))
n = 0
while True:
    %s
    n += 1
"""
#: Each kind of flood's send, in ``FLOODER``'s loop.
FLOODS = {
    "follow": """session.put("busgate/gw1/dev/la1/follow", b'{"position": %d}' % (n % 2000))""",
    "cmd-put": """session.put("busgate/gw1/dev/la1/cmd", b'{"op": "no such op"}')""",
    "cmd-get": """session.get(
        "busgate/gw1/dev/la1/cmd", lambda reply: None, payload=b'{"op": "no such op"}')""",
    "clients": """session.liveliness().declare_token(f"busgate/clients/flood{n}").undeclare()""",
}
#: The e-stop's put, as the SDK puts it.
URGENT = {
    "priority": zenoh.Priority.REAL_TIME,
    "express": True,
    "congestion_control": zenoh.CongestionControl.BLOCK,
}


def estop_latencies(endpoint: str, handed: list[float], estops: int) -> list[float]:
    """Seconds from each put to its hand-over to the buses, ``estops`` of them 0.2 s apart."""
    latencies = []
    with zenoh.open(session_config(mode="client", connect=[endpoint])) as client:
        time.sleep(1.0)
        for _ in range(estops):
            handed.clear()
            put = time.time()
            client.put("busgate/gw1/estop", b'{"client": "bench"}', **URGENT)
            give_up = put + 5.0
            while not handed and time.time() < give_up:
                time.sleep(0.0002)
            latencies.append((handed[0] if handed else give_up) - put)
            time.sleep(0.2)
    return latencies


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--floods", type=positive(int), default=2)
    parser.add_argument("--estops", type=positive(int), default=25)
    parser.add_argument("--kind", choices=sorted(FLOODS), default="follow")
    args = parser.parse_args()
    tune_interpreter()  # as the daemon does
    logging.getLogger("busgate").setLevel(logging.ERROR)  # not a line an e-stop
    endpoint = free_endpoint()
    config = parse_config(config_for("/dev/null", endpoint))
    runners = {bus.name: build_bus(bus) for bus in config.buses}  # never started
    bridge = ZenohBridge(config, GatewayApi("gw1", runners), runners, deque(), deque())
    handed: list[float] = []
    bridge.api.stop_every_bus = lambda: handed.append(time.time()) or []  # type: ignore[method-assign]
    bridge.api.reset_every_bus = lambda sender: ([], [])  # type: ignore[method-assign]
    loop = asyncio.new_event_loop()
    bridge.open(loop)
    threading.Thread(target=loop.run_forever, daemon=True).start()
    try:
        for floods in (0, args.floods):
            flooders = [
                subprocess.Popen([sys.executable, "-c", FLOODER % FLOODS[args.kind], endpoint])
                for _ in range(floods)
            ]
            try:
                latencies = sorted(estop_latencies(endpoint, handed, args.estops))
            finally:
                for flooder in flooders:
                    flooder.kill()
                    flooder.wait()
            print(
                f"{floods} clients flooding ({args.kind}): put → e-stop handed to the buses "
                f"p50 {ms(latencies, .5)} ms, p90 {ms(latencies, .9)} ms, "
                f"worst {latencies[-1] * 1000:.1f} ms ({len(latencies)} e-stops)",
                flush=True,
            )
    finally:
        loop.call_soon_threadsafe(loop.stop)
        bridge.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
