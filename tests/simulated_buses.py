"""A gateway's buses on simulators in the test's own process: three Inspire LA actuators on one
921600-baud pty (``uart0``: la1–la3), two DS servos on another at 1 Mbaud (``uart1``: arm1,
arm2), a ZLAC706 on python-can's virtual bus (``can0``: wheel), each bus with its real runner
and the ``GatewayApi`` over them, returned once every device is online.

``margin_ms`` is each bus's reply margin: room for a simulator that shares the process (and a
loaded machine's cores) with the gateway. It is also part of every exchange's worst case, and
the planner starts a poll between follow ticks only when its worst case fits: with a margin
above a follow period's room, no device is read while a stream or a trajectory ticks."""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Iterator
from dataclasses import dataclass

import can

from busgate.codecs import ds_servo as ds
from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.ds_servo import DsServoDevice
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.config import CanBus, SerialBus
from tests.conftest import wait_until

_channels = itertools.count()


def la_bus(port: str, margin_ms: float) -> SerialBus:
    return SerialBus(name="uart0", transport="serial", port=port, baudrate=921_600,
                     reply_margin_ms=margin_ms,
                     devices=[{"name": f"la{i}", "kind": "inspire_la", "id": i} for i in (1, 2, 3)])


def ds_bus(port: str, margin_ms: float) -> SerialBus:
    return SerialBus(name="uart1", transport="serial", port=port, baudrate=1_000_000,
                     reply_margin_ms=margin_ms,
                     devices=[{"name": "arm1", "kind": "ds_servo", "id": 1},
                              {"name": "arm2", "kind": "ds_servo", "id": 2}])


def can_bus(channel: str, margin_ms: float) -> CanBus:
    return CanBus(name="can0", transport="can", interface="virtual", channel=channel,
                  reply_margin_ms=margin_ms,
                  devices=[{"name": "wheel", "kind": "zlac706", "id": 5, "heartbeat_ms": 50}])


@dataclass
class SimulatedGateway:
    api: GatewayApi
    runners: dict[str, BusRunner]
    la_sim: SerialSimulator
    ds_sim: SerialSimulator
    can_sim: CanSimulator


@contextlib.contextmanager
def simulated_gateway(*, margin_ms: float) -> Iterator[SimulatedGateway]:
    la_sim = SerialSimulator(la, [InspireLaDevice(i) for i in (1, 2, 3)], baudrate=921_600)
    ds_sim = SerialSimulator(ds, [DsServoDevice(1), DsServoDevice(2)], baudrate=1_000_000)
    channel = f"test-buses-{next(_channels)}"
    can_sim = CanSimulator(zcan, [Zlac706CanDevice(5, heartbeat_ms=50)],
                           bus=can.Bus(interface="virtual", channel=channel))
    simulators = (la_sim, ds_sim, can_sim)
    for simulator in simulators:
        simulator.start()
    buses = [la_bus(la_sim.port, margin_ms), ds_bus(ds_sim.port, margin_ms),
             can_bus(channel, margin_ms)]
    runners = {bus.name: build_bus(bus).start() for bus in buses}
    try:
        api = GatewayApi("gw", runners)
        wait_until(lambda: all(driver.online for _, driver in api.devices.values()))
        yield SimulatedGateway(api, runners, la_sim, ds_sim, can_sim)
    finally:
        for runner in runners.values():
            runner.stop()
        for simulator in simulators:
            simulator.stop()
