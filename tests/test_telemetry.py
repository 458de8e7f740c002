"""What the bus thread publishes of its devices (gateway/scheduler/devices.py, telemetry.py),
with real drivers on a fake clock: frames nobody asked for go to the driver of the device
they name and make news (a heartbeat once whole); a published state is stamped with wall
time in one place and marked stale after three poll periods; a device's heartbeats are
checked before each publication; events go out, a reboot is handed back so that its stream
ends."""

from __future__ import annotations

import logging
import time

from busgate.codecs import zlac706_can as zcan
from busgate.codecs.can_frame import CanFrame
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.drivers.zlac706_rs232 import Zlac706Rs232Driver
from busgate.gateway.scheduler.devices import BusDevices
from busgate.gateway.scheduler.telemetry import STALE_PERIODS, Telemetry


def heartbeat(node: int, data: str) -> object:
    decoder = zcan.ReplyDecoder()
    decoder.feed(CanFrame(node, bytes.fromhex(data)))
    (event,) = decoder.events()
    return event


def telemetry_of(devices: BusDevices, poll_periods: dict[str, float]):
    events, states = [], []
    telemetry = Telemetry("can0", devices, poll_periods, on_event=events.append,
                          on_state=lambda device, state: states.append((device, state)))
    return telemetry, events, states


def test_a_frame_nobody_asked_for_goes_to_the_device_it_names_news_once_its_heartbeat_is_whole():
    left, right = Zlac706CanDriver("left", 1), Zlac706CanDriver("right", 2)
    devices = BusDevices([left, right])
    assert devices.take_news() == {"left", "right"}, "every device's first state is news"
    devices.unsolicited(heartbeat(2, "00fe00200001e1e2"), 1.0)  # manual: position 123362
    devices.unsolicited(heartbeat(9, "00fe00200001e1e2"), 1.0)  # a node of no device: nobody's
    assert (left.measured["position"], right.measured["position"]) == (None, 123362)
    assert not devices.has_news, "half a heartbeat: its current and speed are still to come"
    devices.unsolicited(heartbeat(2, "00fe0021001e043f"), 1.0)  # manual: 0.30 A, 398 rpm
    assert devices.has_news and devices.take_news() == {"right"}
    assert not devices.has_news and devices.take_news() == set()
    devices.unsolicited(heartbeat(2, "00fe0021001e043f"), 1.01)  # its other half came first
    devices.unsolicited(heartbeat(2, "00fe00200001e1e3"), 1.01)
    assert devices.take_news() == {"right"}
    devices.unsolicited(heartbeat(2, "00fe00200001e1e4"), 1.02)  # its other half lost:
    devices.unsolicited(heartbeat(2, "00fe00200001e1e5"), 1.03)  # the next one's is news
    assert devices.take_news() == {"right"} and right.measured["position"] == 123365
    devices.unsolicited(heartbeat(2, "00ff00eb08080808"), 1.04)  # manual: an alarm report
    assert devices.take_news() == {"right"}, "an alarm report is news at once"


def test_two_heartbeats_of_one_device_taken_in_one_look_make_two_states_in_order():
    wheel, other = Zlac706CanDriver("wheel", 1, heartbeat_ms=10), Zlac706CanDriver("other", 2)
    devices = BusDevices([wheel, other])
    telemetry, events, states = telemetry_of(devices, {})
    telemetry.publish(0.0)  # the first states
    del states[:]
    for position, when in ((100, 1.00), (200, 1.01)):  # one look takes both heartbeats
        devices.unsolicited(heartbeat(1, f"00fe0020{position:08x}"), when)
        devices.unsolicited(heartbeat(1, "00fe0021001e043f"), when)
    assert [(d, s["position"]) for d, s in states] == [("wheel", 100)], "before 200 came in"
    assert telemetry.publish(1.02) == []
    assert [(d, s["position"]) for d, s in states] == [("wheel", 100), ("wheel", 200)]
    assert [e.type for e in events] == ["online"], "its events with the look's publication"
    # A look takes one heartbeat whole and the next one's first half: the first's state at
    # once, the next's only once it is whole (not its position with the speed before).
    devices.unsolicited(heartbeat(1, "00fe0020000000c8"), 1.03)
    devices.unsolicited(heartbeat(1, "00fe0021001e043f"), 1.03)
    devices.unsolicited(heartbeat(1, "00fe00200000012c"), 1.04)
    telemetry.publish(1.045)
    assert [s["position"] for _, s in states[2:]] == [200]
    devices.unsolicited(heartbeat(1, "00fe0021001e043f"), 1.04)
    telemetry.publish(1.05)
    assert [s["position"] for _, s in states[2:]] == [200, 300]


def test_a_reply_comes_from_the_device_with_its_id_now_or_a_point_to_point_lines_one():
    la1, la2 = InspireLaDriver("la1", 1), InspireLaDriver("la2", 2)
    devices = BusDevices([la1, la2])
    [status] = la2.poll()
    assert devices.answering(status.expected) is la2
    la2.device_id = 7  # its set_id confirmed: replies from 2 are nobody's now
    assert devices.answering(status.expected) is None
    wheel = Zlac706Rs232Driver("wheel", 1)
    [monitor] = wheel.poll()
    assert monitor.expected.source_id is None  # RS232 frames carry no id
    assert BusDevices([wheel]).answering(monitor.expected) is wheel


def test_a_published_state_is_stamped_with_wall_time_and_stale_after_three_poll_periods():
    la1 = InspireLaDriver("la1", 1)
    telemetry, _, _ = telemetry_of(BusDevices([la1]), {"la1": 0.02})
    before = time.time()
    state = telemetry.reply_state(la1, 10.0)
    assert before <= state["ts"] <= time.time(), "wall time, not the bus thread's clock"
    assert state["stale"] is True, "no reply yet"
    la1.heard(10.0)
    assert telemetry.reply_state(la1, 10.0 + STALE_PERIODS * 0.02 - 0.001)["stale"] is False
    assert telemetry.reply_state(la1, 10.0 + STALE_PERIODS * 0.02 + 0.001)["stale"] is True
    unpolled, _, _ = telemetry_of(BusDevices([la1]), {})
    assert unpolled.reply_state(la1, 1e6)["stale"] is False, "a device polled at no rate"


def test_publishing_checks_heartbeats_sends_events_and_a_state_per_device_with_news():
    wheel = Zlac706CanDriver("wheel", 1, heartbeat_ms=100)
    la1 = InspireLaDriver("la1", 3)
    devices = BusDevices([wheel, la1])
    telemetry, events, states = telemetry_of(devices, {})
    assert telemetry.publish(0.0) == [] and [device for device, _ in states] == ["wheel", "la1"]
    devices.unsolicited(heartbeat(1, "00fe00200001e1e2"), 1.0)
    telemetry.publish(1.05)
    assert [e.type for e in events] == ["online"] and states[-1][0] == "wheel"
    assert telemetry.states["wheel"]["online"] is True
    telemetry.publish(1.5)  # three heartbeat intervals without one: checked here
    assert [e.type for e in events] == ["online", "offline"] and len(states) == 4
    assert telemetry.states["wheel"]["online"] is False
    telemetry.publish(1.6)
    assert len(states) == 4, "no news, no events: nothing published"
    la1.rebooted("a test")
    assert telemetry.publish(1.7) == ["la1"] and events[-1].type == "rebooted"


def test_a_flapping_fault_is_every_event_published_and_a_line_a_second_the_last_one_last(caplog):
    la1 = InspireLaDriver("la1", 3)
    telemetry, events, _ = telemetry_of(BusDevices([la1]), {})
    with caplog.at_level(logging.INFO, logger="busgate.gateway.scheduler.telemetry"):
        for n in range(20):  # a fault raised and cleared at 50 Hz, for 0.4 s
            la1.emit("fault", faults=["stall"] if n % 2 == 0 else [])
            telemetry.publish(n * 0.02)
        lines = [r.getMessage() for r in caplog.records]
        assert len(events) == 20 and lines == ["bus can0 device la1: fault (faults=['stall'])"]
        la1.emit("rebooted")  # another kind: its own line at once
        telemetry.publish(0.5)
        assert caplog.records[-1].getMessage() == "bus can0 device la1: rebooted"
        telemetry.publish(0.99)
        assert len(caplog.records) == 2, "held back within the second"
        telemetry.publish(1.0)  # the last held back, once its second is over
        assert caplog.records[-1].getMessage() == ("bus can0 device la1: fault (faults=[]) "
            "[18 more fault lines held back before this one]")
        la1.emit("fault", faults=["stall"])
        telemetry.publish(2.5)
        assert caplog.records[-1].getMessage() == "bus can0 device la1: fault (faults=['stall'])"
