"""What each bus owner does while its bus is idle, as its interface declares it
(gateway/bus/owner.py): a serial owner has no idle work and only waits, in one pause; a CAN
owner takes in what came unasked, pauses at most ``idle_batch_s``, and again. A pause that is
cut short (new work for the bus) ends the wait. The pauses are the test's own, and say when
the wait was cut short; the CAN frames come over python-can's virtual bus."""

from __future__ import annotations

import itertools
import math

import can
import pytest

from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.gateway.bus.can_owner import CanBusOwner
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.owner import BusOwner
from busgate.gateway.bus.serial_owner import SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.families import link_timing

_channels = itertools.count()


def test_an_owner_lacking_part_of_the_interface_cannot_be_made():
    class HalfOwner(BusOwner):
        idle_batch_s = math.inf

        def open(self) -> None:
            pass

    with pytest.raises(TypeError, match="abstract"):
        HalfOwner()


def test_a_serial_owner_has_no_idle_work_it_waits_in_one_pause():
    """Not even open: idle, a serial owner does not touch its port."""
    timing = link_timing("inspire_la", 921_600, margin_s=0.002)
    owner = SerialBusOwner("/dev/no-such-port", la, timing, BusCounters(now()))
    assert owner.idle_batch_s == math.inf
    pauses = []
    assert owner.idle_until(now() + 30.0, lambda s: pauses.append(s) or True) is False
    assert len(pauses) == 1 and 29.0 < pauses[0] <= 30.0, "the whole wait, not in batches"
    assert owner.idle_until(now() - 1.0, pauses.append) is True and len(pauses) == 1


def test_a_can_owner_takes_in_what_came_unasked_between_pauses_of_one_batch():
    channel = f"idle-work-{next(_channels)}"
    heard = []
    timing = link_timing("zlac706_can", 500_000, margin_s=0.002)
    owner = CanBusOwner("virtual", channel, {}, zcan, timing, BusCounters(now()),
                        on_unsolicited=lambda event, when: heard.append(event))
    owner.open()
    node = can.Bus(interface="virtual", channel=channel)
    pauses, taken = [], []

    def pause(seconds: float) -> bool:
        """A heartbeat arrives during each pause; the third pause is cut short."""
        pauses.append(seconds)
        taken.append(len(heard))
        heartbeat = zcan.encode(zcan.HeartbeatPosition(1, len(pauses)))
        node.send(can.Message(arbitration_id=heartbeat.arbitration_id, data=heartbeat.data,
                              is_extended_id=False))
        return len(pauses) == 3

    try:
        assert owner.idle_until(now() + 30.0, pause) is False
        assert pauses == [owner.idle_batch_s] * 3 and owner.idle_batch_s < 0.01
        assert taken == [0, 1, 2], "what came during a pause is taken before the next one"
        assert owner.idle_until(now() - 1.0, pause) is True, "past its deadline: take, no pause"
        assert [event.position_raw for event in heard] == [1, 2, 3] and len(pauses) == 3
    finally:
        node.shutdown()
        owner.close()
