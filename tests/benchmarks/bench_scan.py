"""How long a full scan of an Inspire LA bus at 921600 baud takes, through the gateway's API.

Not a test (pytest does not collect it):

    .venv/bin/python tests/benchmarks/bench_scan.py

Three simulated actuators (ids 1-3) answer and 251 ids stay silent; each silent id costs one
reply window (no retries, no hold-off), while the actuators keep their 10 Hz polls. Prints
each of five scans' duration and the gateway's own plan for it (the worst case of every probe
plus the gap).
"""

from __future__ import annotations

import time

from usage import arguments

from busgate.codecs import inspire_la as la
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.api.group import scan_requests
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.config import SerialBus

RUNS = 5


def main() -> None:
    arguments(__doc__)
    with SerialSimulator(la, [InspireLaDevice(i) for i in (1, 2, 3)], baudrate=921_600) as sim:
        bus = SerialBus(name="uart0", transport="serial", port=sim.port, baudrate=921_600,
                        devices=[{"name": f"la{i}", "kind": "inspire_la", "id": i}
                                 for i in (1, 2, 3)])
        runner = build_bus(bus).start()
        try:
            api = GatewayApi("gw", {"uart0": runner})
            while not all(driver.online for driver in runner.drivers.values()):
                time.sleep(0.01)
            timing = runner.timing
            planned = sum(timing.worst_case(p) + timing.gap_s for p in scan_requests("inspire_la",
                                                                                      None))
            durations = []
            for _ in range(RUNS):
                started = time.perf_counter()
                reply = api.bus_command("uart0", b'{"op":"scan"}').result(15)
                durations.append(time.perf_counter() - started)
                assert [found["id"] for found in reply["found"]] == [1, 2, 3], reply
        finally:
            runner.stop()
    print(f"full scan, 254 ids (3 answering) at 921600 baud: "
          f"{', '.join(f'{d:.2f}' for d in durations)} s; planned {planned:.2f} s")


if __name__ == "__main__":
    main()
