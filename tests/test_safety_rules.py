"""Safety rules the README promises, each at the level the promise is made, so that breaking
one fails a test: a ZLAC706 speed stream that goes stale is brought to 0 rpm by the runner
itself; an idempotent request is tried exactly three times, anything else once; the payload
limit is 64 KiB to the byte. Real parts: the runner over python-can's virtual bus and the
ZLAC706 simulator, over a pty and the LA simulator."""

from __future__ import annotations

import itertools
import json

import can

from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.config import CanBus, SerialBus

_channels = itertools.count()
ZERO_RPM = "001#00fa001100000000"


def test_a_speed_stream_that_goes_stale_is_brought_to_zero_rpm_by_the_runner(wait_for):
    channel = f"test-safety-{next(_channels)}"
    simulator = CanSimulator(zcan, [Zlac706CanDevice(1, heartbeat_ms=50)],
                             bus=can.Bus(interface="virtual", channel=channel)).start()
    events = []
    bus = CanBus(name="can0", transport="can", interface="virtual", channel=channel,
                 reply_margin_ms=50, devices=[{"name": "wheel", "kind": "zlac706", "id": 1,
                                               "heartbeat_ms": 50, "follow_period_ms": 20}])
    runner = build_bus(bus, on_event=events.append).start()
    try:
        wait_for(lambda: runner.drivers["wheel"].online)
        driver = runner.drivers["wheel"]
        for text in ('{"op":"set_mode","mode":"velocity"}', '{"op":"enable"}'):
            runner.submit("wheel", driver.parse(text)).result(2)
        streamed = len(simulator.recorder.received())
        target = driver.follow_target({"rpm": 200})
        at_200 = str(type(driver).follow_request([(driver, target)]).wire)
        runner.follow("wheel", target, "velocity")  # and then nothing more
        wait_for(lambda: any(e.type == "stream_stale" for e in events), timeout=10)
        wait_for(lambda: ZERO_RPM in [r.wire for r in simulator.recorder.received()[streamed:]])
        sent = [r.wire for r in simulator.recorder.received()[streamed:]]
        first_stop = sent.index(ZERO_RPM)
        assert at_200 in sent[:first_stop], "the stream ran at 200 rpm first"
    finally:
        runner.stop()
        simulator.stop()


def test_an_idempotent_request_is_tried_three_times_anything_else_once(wait_for):
    """The README's number: "retried twice" after a timeout, so three frames in all."""
    with SerialSimulator(la, [InspireLaDevice(1), InspireLaDevice(2)],
                         baudrate=921_600) as simulator:
        bus = SerialBus(name="uart0", transport="serial", port=simulator.port,
                        baudrate=921_600, reply_margin_ms=50, devices=[
                            {"name": "la1", "kind": "inspire_la", "id": 1},
                            {"name": "la2", "kind": "inspire_la", "id": 2}])
        runner = build_bus(bus).start()
        api = GatewayApi("gw", {"uart0": runner})
        try:
            wait_for(lambda: runner.drivers["la2"].online)
            simulator.faults.configure(silent_ids=frozenset({2}))
            read = api.command("la2", b'{"op":"read","index":0,"length":1}').result(5)
            save = api.command("la2", b'{"op":"save"}').result(5)
            assert read["error"]["code"] == save["error"]["code"] == "device_timeout"
            simulator.faults.configure(silent_ids=frozenset())
            assert api.command("la1", b'{"op":"status"}').result(5)["ok"]  # the bus went on
            received = simulator.recorder.received()
            reads = la.encode(la.ReadCommand(2, 0, 1)).hex()
            saves = la.encode(la.ControlCommand(2, la.ControlCode.SAVE)).hex()
            assert [r.wire for r in received].count(reads) == 3
            assert [r.wire for r in received].count(saves) == 1
        finally:
            runner.stop()


def test_the_payload_limit_is_64_kib_to_the_byte(wait_for):
    """65,536 bytes are a command; 65,537 are ``too_large`` (the README's limit)."""
    with SerialSimulator(la, [InspireLaDevice(1)], baudrate=921_600) as simulator:
        bus = SerialBus(name="uart0", transport="serial", port=simulator.port,
                        baudrate=921_600, reply_margin_ms=50,
                        devices=[{"name": "la1", "kind": "inspire_la", "id": 1}])
        runner = build_bus(bus).start()
        api = GatewayApi("gw", {"uart0": runner})
        try:
            wait_for(lambda: runner.drivers["la1"].online)
            command = json.dumps({"op": "status"}).encode()
            at_limit = command + b" " * (65_536 - len(command))
            assert api.command("la1", at_limit).result(5)["ok"]
            over = api.command("la1", at_limit + b" ").result(5)
            assert over["error"]["code"] == "too_large"
            assert api.bus_command("uart0", at_limit + b" ").result(5)["error"]["code"] == (
                "too_large")
            assert api.follow("la1", at_limit + b" ")["error"]["code"] == "too_large"
        finally:
            runner.stop()
