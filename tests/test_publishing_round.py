"""The publishing loop's rounds: every ``TELEMETRY_EVERY_S`` while states come (or the joints
message's interval, when shorter), every ``PUBLISH_EVERY_S`` while the round has timed work of
its own, else a wait that the next state or event cuts short (``gateway/api/doorbell.py``).
No timing is judged here: the rounds are counted, and each wait is recorded by what ends it."""

from __future__ import annotations

import asyncio
import threading
from collections import deque

import pytest

from busgate.gateway.api import bridge as bridge_module
from busgate.gateway.api.bridge import (
    IDLE_WAIT_S,
    PUBLISH_EVERY_S,
    TELEMETRY_EVERY_S,
    ZenohBridge,
)
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.api.doorbell import Doorbell, Mailbox
from busgate.gateway.api.joints import JointsFeed
from busgate.gateway.service.assembly import build_bus
from busgate.schemas.config import parse_config

HANG_GUARD_S = 10.0  # a wait that never ends fails the test; nothing is timed against it

CONFIG = {
    "gateway": {"name": "gw1"},
    "buses": [{"name": "uart0", "transport": "serial", "port": "/dev/null", "baudrate": 921600,
               "devices": [{"name": "la1", "kind": "inspire_la", "id": 1, "poll_hz": 20}]}],
}


def test_a_ring_ends_a_wait_from_another_thread() -> None:
    async def scenario() -> None:
        doorbell = Doorbell()
        waiting = asyncio.ensure_future(doorbell.wait(HANG_GUARD_S * 10, lambda: False))
        await asyncio.sleep(0)  # the wait under way
        threading.Thread(target=doorbell.ring).start()
        await asyncio.wait_for(waiting, HANG_GUARD_S)

    asyncio.run(scenario())


def test_news_before_the_wait_ends_it_at_once_and_a_ring_nobody_waits_for_is_nothing() -> None:
    async def scenario() -> None:
        doorbell = Doorbell()
        doorbell.ring()  # before any wait: no loop to wake yet
        await asyncio.wait_for(doorbell.wait(HANG_GUARD_S * 10, lambda: True), HANG_GUARD_S)
        await asyncio.wait_for(doorbell.wait(0.001, lambda: False), HANG_GUARD_S)  # its timeout
        doorbell.ring()  # nobody waits now

    asyncio.run(scenario())


def test_a_mailbox_rings_on_every_append_and_keeps_its_bound() -> None:
    rings: list[None] = []
    mailbox = Mailbox(lambda: rings.append(None), maxlen=2)
    for item in "abc":
        mailbox.append(item)
    assert list(mailbox) == ["b", "c"] and len(rings) == 3


def test_a_joints_message_held_back_is_due_after_its_interval() -> None:
    feed = JointsFeed("gw1", [], min_interval_s=0.5)
    assert feed.due_in(10.0) is None  # nothing read again
    feed._read_again = True
    assert feed.due_in(10.0) == 0.0  # never sent: now
    feed._last_sent = 10.0
    assert feed.due_in(10.2) == pytest.approx(0.3)
    assert feed.due_in(11.0) == 0.0


class Rounds:
    """``publish_forever`` on a bridge with no session, each of its waits recorded: a
    round's sleep (``PUBLISH_EVERY_S``) or the doorbell's wait, with its timeout."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, poll_hz: float = 20) -> None:
        (bus,) = CONFIG["buses"]
        device = {**bus["devices"][0], "poll_hz": poll_hz}
        config = parse_config({**CONFIG, "buses": [{**bus, "devices": [device]}]})
        runners = {bus.name: build_bus(bus) for bus in config.buses}  # not started
        self.doorbell = Doorbell()
        self.states: deque = Mailbox(self.doorbell.ring, maxlen=100)
        self.bridge = ZenohBridge(config, GatewayApi("gw1", runners), runners,
                                  Mailbox(self.doorbell.ring, maxlen=100), self.states,
                                  self.doorbell)
        self.waits: list[tuple[str, float]] = []
        self.script: list = []  # what to do at each wait, in turn; at the end, stop
        self.stop = asyncio.Event()
        real_sleep, real_wait = asyncio.sleep, self.doorbell.wait

        async def sleep(seconds: float) -> None:
            self.waits.append(("round", seconds))
            self._next()
            await real_sleep(0)

        async def wait(timeout: float, has_news) -> None:
            self.waits.append(("idle", timeout))
            self._next()
            await real_wait(0, has_news)

        monkeypatch.setattr(bridge_module.asyncio, "sleep", sleep)
        monkeypatch.setattr(self.doorbell, "wait", wait)

    def _next(self) -> None:
        if self.script:
            self.script.pop(0)()
        else:
            self.stop.set()

    def run(self) -> list[tuple[str, float]]:
        asyncio.run(asyncio.wait_for(self.bridge.publish_forever(self.stop), HANG_GUARD_S))
        return self.waits


def test_a_loop_with_nothing_to_do_waits_for_news_and_rounds_while_states_come(monkeypatch):
    rounds = Rounds(monkeypatch)
    reading = [("la1", {"device": "la1", "ts": float(ts), "joint": {}}) for ts in (1, 2)]
    rounds.script = [lambda: rounds.states.append(reading[0]),
                     lambda: rounds.states.append(reading[1]), lambda: None]
    waits = rounds.run()
    assert waits[:3] == [
        ("idle", IDLE_WAIT_S),  # nothing to do: a wait, which a state cut short
        ("round", TELEMETRY_EVERY_S),  # it was published: a round, in which another came
        ("round", TELEMETRY_EVERY_S),  # published too; the joints message held back for it
    ]
    kind, timeout = waits[3]  # nothing came: a wait, to when the joints message is due
    assert kind == "idle" and 0 < timeout <= 1 / 20 and len(waits) == 4


def test_a_running_trajectory_keeps_the_rounds_going_at_the_quicker_period(monkeypatch):
    rounds = Rounds(monkeypatch)
    monkeypatch.setattr(type(rounds.bridge.trajectories), "running", property(lambda _: True))
    rounds.script = [lambda: rounds.states.append(("la1", {"device": "la1", "ts": 1.0}))]
    assert rounds.run() == [("round", PUBLISH_EVERY_S)] * 2  # states coming too


def test_telemetry_rounds_come_as_often_as_the_joints_message_may(monkeypatch):
    """A device polled every 4 ms: its joints message may go every 4 ms, so the rounds that
    carry states come that often, not every ``TELEMETRY_EVERY_S``."""
    rounds = Rounds(monkeypatch, poll_hz=250)
    rounds.script = [lambda: rounds.states.append(("la1", {"device": "la1", "ts": 1.0}))]
    assert rounds.run()[1] == ("round", 1 / 250)
