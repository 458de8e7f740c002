"""A ZLAC706 CAN bus run by the real bus runner: on python-can's virtual bus, and through the
simulated SLCAN adapter on a pty that can be unplugged and plugged back in."""

from __future__ import annotations

import itertools
import time

import can
import pytest

from busgate.codecs import zlac706_can as zcan
from busgate.gateway.assembly import build_bus
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.pty_link import PtyLink
from busgate.gateway.sim.slcan import SlcanAdapter
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.config import CanBus

_channels = itertools.count()


def can_bus(interface: str, channel: str, **options) -> CanBus:
    devices = [{"name": "wheel", "kind": "zlac706", "id": 1, "heartbeat_ms": 50, "poll_hz": 5}]
    return CanBus(name="can0", transport="can", interface=interface, channel=channel,
                  devices=devices, options=options)


@pytest.fixture
def virtual_channel():
    channel = f"test-can-runner-{next(_channels)}"
    simulator = CanSimulator(zcan, [Zlac706CanDevice(1, heartbeat_ms=50)],
                             bus=can.Bus(interface="virtual", channel=channel)).start()
    yield channel, simulator
    simulator.stop()


def test_heartbeats_bring_the_node_online_and_speed_is_kept_alive(
    wait_for, virtual_channel
) -> None:
    channel, simulator = virtual_channel
    runner = build_bus(can_bus("virtual", channel)).start()
    try:
        wait_for(lambda: runner.drivers["wheel"].online)
        driver = runner.drivers["wheel"]
        for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}',
                     '{"op":"velocity","rpm":300}'):
            runner.submit("wheel", driver.parse(text)).result(2)
        wait_for(lambda: (runner.states["wheel"].get("speed_rpm") or 0) > 100)
        time.sleep(1.0)
        speed_writes = [r.start for r in simulator.recorder.received()
                        if r.wire.startswith("001#00fa0011")]
        gaps = [b - a for a, b in itertools.pairwise(speed_writes)]
        assert len(speed_writes) >= 3 and max(gaps) < 0.5, "refreshed before the 500 ms lock"
        assert (runner.states["wheel"].get("speed_rpm") or 0) > 100, "the shaft never locked"
    finally:
        runner.stop()
    stops = [r.wire for r in simulator.recorder.received()]
    assert "001#00fa00100000000f" in stops, "stopping the bus releases the motor"


def test_lost_heartbeats_mark_the_node_offline(wait_for, virtual_channel) -> None:
    channel, simulator = virtual_channel
    events = []
    runner = build_bus(can_bus("virtual", channel), on_event=events.append).start()
    try:
        wait_for(lambda: runner.drivers["wheel"].online)
        simulator.faults.configure(silent_ids=frozenset({1}))
        simulator.devices[0].heartbeat_s = 0
        wait_for(lambda: not runner.drivers["wheel"].online)
        assert [e.type for e in events].count("offline") == 1
    finally:
        runner.stop()


def test_slcan_adapter_unplugged_and_back(wait_for, tmp_path) -> None:
    channel = f"test-can-slcan-{next(_channels)}"
    simulator = CanSimulator(zcan, [Zlac706CanDevice(1, heartbeat_ms=50)],
                             bus=can.Bus(interface="virtual", channel=channel)).start()
    by_id = str(tmp_path / "usb-canable")  # the stable name udev gives a real adapter
    adapter = SlcanAdapter(channel, link=PtyLink(by_id)).start()
    runner = build_bus(can_bus("slcan", by_id, sleep_after_open=0)).start()
    try:
        wait_for(lambda: runner.drivers["wheel"].online)
        adapter.unplug()
        wait_for(lambda: not runner.drivers["wheel"].online)
        adapter.replug()
        wait_for(lambda: runner.drivers["wheel"].online, timeout=8)
        assert runner.statistics().reconnects >= 1
    finally:
        runner.stop()
        adapter.stop()
        simulator.stop()
