"""A bus that is down (gateway/scheduler/link.py), on a fake clock: the waits between attempts
to open it double up to their cap and start over once it was up, and while it stays down it
is reported at its first failure and then at most once every ``DOWN_REPORT_S``; a bus lost
soon after it opens is opened again after the backoff, not at once, and said once a minute."""

from __future__ import annotations

import logging
import math

import pytest

from busgate.errors import BusUnavailableError
from busgate.gateway.scheduler.link import (
    BACKOFF_FIRST_S,
    BACKOFF_MAX_S,
    DOWN_REPORT_S,
    STABLE_S,
    Reconnect,
)

GONE = BusUnavailableError("/dev/ttyUSB0 does not exist on this host")


def test_waits_double_to_their_cap_and_start_over_once_the_bus_was_up():
    reconnect = Reconnect("uart0")
    waits = [reconnect.failed(GONE, moment=float(i)) for i in range(7)]
    assert waits == [0.1, 0.2, 0.4, 0.8, 1.6, 2.0, 2.0]
    assert (waits[0], max(waits)) == (BACKOFF_FIRST_S, BACKOFF_MAX_S)
    assert reconnect.opened(7.0) is False, "the first time up is no reconnect"
    assert reconnect.failed(GONE, moment=100.0) == BACKOFF_FIRST_S
    assert reconnect.opened(101.0) is True, "up again: a reconnect"


def test_a_bus_that_stays_down_is_reported_once_then_once_a_minute(caplog):
    reconnect = Reconnect("uart0")
    with caplog.at_level(logging.WARNING, logger="busgate.gateway.scheduler.link"):
        for moment in (1000.0, 1002.0, 1004.0, 1000.0 + DOWN_REPORT_S - 0.1):
            reconnect.failed(GONE, moment)
        assert [r.getMessage() for r in caplog.records] == [
            f"bus uart0 down: {GONE}; retrying every 0.1-2 s"]
        reconnect.failed(GONE, 1000.0 + DOWN_REPORT_S)
        reconnect.failed(GONE, 1000.0 + DOWN_REPORT_S + 1)
        assert caplog.records[-1].getMessage() == (
            f"bus uart0 still down after 60 s (4 attempts): {GONE}")
        assert len(caplog.records) == 2
        reconnect.opened(1999.0)
        reconnect.failed(GONE, 2000.0)  # down again: a first failure, reported at once
        assert caplog.records[-1].getMessage().startswith("bus uart0 down: ")


def test_a_bus_lost_soon_after_each_opening_waits_its_backoff_and_is_summed_up(caplog):
    """A wedged adapter: it opens, the first write times out, and so on. Reopened at once,
    it took a core and logged two lines twice a second for ever."""
    reconnect = Reconnect("uart0")
    blocked = BusUnavailableError("/dev/ttyUSB0: Write timeout")
    moment, retries = 0.0, []
    with caplog.at_level(logging.INFO, logger="busgate.gateway.scheduler.link"):
        reconnect.opened(moment)
        assert reconnect.lost(blocked, 100.0) is True and reconnect.retry_at == -math.inf
        moment = 100.0
        for _ in range(40):
            reconnect.opened(moment)
            said = reconnect.lost(blocked, moment + 0.5)
            retries.append(reconnect.retry_at - (moment + 0.5))
            assert said is (len(retries) == 1), "the first quick loss only, then summed up"
            moment = reconnect.retry_at
        assert retries[:6] == pytest.approx([0.1, 0.2, 0.4, 0.8, 1.6, 2.0])
        assert max(retries) == pytest.approx(BACKOFF_MAX_S)
        summaries = [r.getMessage() for r in caplog.records]
        assert len(summaries) == 1 and summaries[0].startswith(
            "bus uart0 lost again within 5 s of opening, ")  # once in 60 s of this
        reconnect.opened(moment)
        reconnect.still_up(moment + STABLE_S - 0.1)
        assert reconnect.quick_losses == 40
        reconnect.still_up(moment + STABLE_S)
        assert caplog.records[-1].getMessage() == (
            "bus uart0 up for 5 s again, after 40 losses soon after opening")
    assert reconnect.quick_losses == 0
    assert reconnect.lost(blocked, moment + 100.0) is True  # a loss after it stayed up
    assert reconnect.failed(blocked, moment + 100.0) == BACKOFF_FIRST_S
