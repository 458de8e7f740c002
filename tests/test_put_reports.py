"""A refused put is told as a ``command_refused`` event at most once a device every 0.1 s, an
e-stop as an ``estop`` event at most once every 0.1 s; the ones withheld are counted in the
next told (``suppressed``), and the last of a burst is told once its interval has passed: a
fake clock, no zenoh."""

from __future__ import annotations

from busgate.gateway.api.put_reports import PutReports
from busgate.gateway.drivers.base import DeviceEvent
from busgate.schemas.events import EVENT_ADAPTER
from tests.test_schema_export import assert_valid, event_body


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def error(n: int) -> dict:
    return {"code": "bad_command", "message": f"refusal {n}"}


def reports(clock: Clock) -> tuple[PutReports, list[DeviceEvent]]:
    told: list[DeviceEvent] = []
    return PutReports({"la1", "la2"}, told.append, clock=clock), told


def assert_events_valid(told: list[DeviceEvent]) -> None:
    """Every event told matches the exported event schema and the pydantic model."""
    for event in told:
        assert_valid("event.json", event_body(event))
        EVENT_ADAPTER.validate_python(event_body(event))


def told_as(told: list[DeviceEvent]) -> list[tuple[str, str, int | None]]:
    return [(e.device, e.fields["message"], e.fields.get("suppressed")) for e in told]


def test_a_burst_is_told_first_and_last_with_what_was_withheld_between() -> None:
    clock = Clock()
    refusals, told = reports(clock)
    for n in range(50):  # 50 bad puts in 49 ms
        refusals.refused("la1", error(n))
        clock.now += 0.001
    refusals.flush()  # the interval has not passed: the last waits
    assert told_as(told) == [("la1", "refusal 0", None)]
    clock.now = 0.1
    refusals.flush()
    refusals.flush()  # told once
    assert told_as(told) == [("la1", "refusal 0", None), ("la1", "refusal 49", 48)]
    assert len(told) + sum(e.fields.get("suppressed", 0) for e in told) == 50  # none lost


def test_a_refusal_after_the_interval_is_told_at_once_counting_the_withheld() -> None:
    clock = Clock()
    refusals, told = reports(clock)
    refusals.refused("la1", error(1))
    refusals.refused("la1", error(2))
    refusals.refused("la1", error(3))
    clock.now += 0.1
    refusals.refused("la1", error(4))  # told now: 2 and 3 were withheld
    refusals.flush()
    assert told_as(told) == [("la1", "refusal 1", None), ("la1", "refusal 4", 2)]
    clock.now += 0.05
    refusals.refused("la1", error(5))  # 0.05 s after the last told: withheld
    assert len(told) == 2


def test_each_device_has_its_own_interval_and_unknown_names_share_one() -> None:
    clock = Clock()
    refusals, told = reports(clock)
    refusals.refused("la1", error(1))
    refusals.refused("la2", error(2))
    refusals.refused("nope", error(3))
    refusals.refused("x" * 30_000, error(4))  # another unknown name: the shared slot's turn
    for n in range(1000):
        refusals.refused(f"ghost{n}", error(5))
    assert [e.device for e in told] == ["la1", "la2", "nope"]
    assert len(refusals._slots) == 3  # la1, la2, and every unknown name in one
    clock.now += 0.1
    refusals.flush()
    assert told_as(told)[-1] == ("ghost999", "refusal 5", 1000)


def test_the_events_match_the_event_schema() -> None:
    clock = Clock()
    refusals, told = reports(clock)
    refusals.refused("la1", error(1))
    refusals.refused("la1", error(2))
    refusals.refused("la1", error(3))
    clock.now += 0.2
    refusals.flush()
    assert [e.fields.get("suppressed") for e in told] == [None, 1]
    assert_events_valid(told)


def test_at_the_stop_every_withheld_refusal_is_told() -> None:
    clock = Clock()
    refusals, told = reports(clock)
    for n in range(3):
        refusals.refused("la1", error(n))
    refusals.flush()
    assert len(told) == 1
    refusals.flush(every=True)  # the gateway stops: no round comes after this one
    assert told_as(told)[-1] == ("la1", "refusal 2", 1)


def test_estops_in_a_loop_are_told_first_and_last_in_a_slot_of_their_own() -> None:
    """A client putting e-stops in a loop makes one event (and log line) every 0.1 s, not one
    a put, whoever names itself; a device's refusals and the resets meanwhile keep their own
    interval."""
    clock = Clock()
    reports_, told = reports(clock)
    for n in range(100):  # 100 e-stops in 0.1 s, under ever new names
        clock.now = n / 1000
        reports_.estop("busgate/gw/estop", f"panel{n}")
        if n == 1:
            reports_.refused("la1", error(1))
    reports_.flush()
    assert [(e.type, e.fields.get("client")) for e in told] == [
        ("estop", "panel0"),
        ("command_refused", None),
    ]
    reports_.estop_reset("panel")  # its own slot: told at once, behind the e-stops withheld
    assert [(e.type, e.fields) for e in told[-2:]] == [
        ("estop", {"key": "busgate/gw/estop", "client": "panel99", "suppressed": 98}),
        ("estop_reset", {"client": "panel"}),
    ]
    clock.now = 0.1
    reports_.flush()
    assert len(told) == 4  # nothing was left to tell
    assert len(reports_._slots) == 3
    assert_events_valid(told)


def test_an_estop_after_a_withheld_reset_is_told_behind_it() -> None:
    """The journal's order is the puts': a reset withheld in its interval is told before an
    e-stop that comes after it."""
    clock = Clock()
    reports_, told = reports(clock)
    reports_.estop_reset("panel")
    clock.now = 0.01
    reports_.estop_reset("panel")  # withheld
    clock.now = 0.02
    reports_.estop("busgate/gw/estop", "panel")
    assert [e.type for e in told] == ["estop_reset", "estop_reset", "estop"]
    assert "suppressed" not in told[1].fields  # told itself, not counted in another
