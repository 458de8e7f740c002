"""A bus that is down (gateway/scheduler/link.py), on a fake clock: the waits between attempts
to open it double up to their cap and start over once it was up, and while it stays down it
is reported at its first failure and then at most once every ``DOWN_REPORT_S``."""

from __future__ import annotations

import logging

from busgate.errors import BusUnavailableError
from busgate.gateway.scheduler.link import (
    BACKOFF_FIRST_S,
    BACKOFF_MAX_S,
    DOWN_REPORT_S,
    Reconnect,
)

GONE = BusUnavailableError("/dev/ttyUSB0 does not exist on this host")


def test_waits_double_to_their_cap_and_start_over_once_the_bus_was_up():
    reconnect = Reconnect("uart0")
    waits = [reconnect.failed(GONE, moment=float(i)) for i in range(7)]
    assert waits == [0.1, 0.2, 0.4, 0.8, 1.6, 2.0, 2.0]
    assert (waits[0], max(waits)) == (BACKOFF_FIRST_S, BACKOFF_MAX_S)
    assert reconnect.opened() is False, "the first time up is no reconnect"
    assert reconnect.failed(GONE, moment=100.0) == BACKOFF_FIRST_S
    assert reconnect.opened() is True, "up again: a reconnect"


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
        reconnect.opened()
        reconnect.failed(GONE, 2000.0)  # down again: a first failure, reported at once
        assert caplog.records[-1].getMessage().startswith("bus uart0 down: ")
