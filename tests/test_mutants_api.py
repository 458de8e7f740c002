"""What mutation testing (``python tools/mutation/run.py api``) found the API tests leaving open:
a claim over another client's claim is refused (and a claim lapses at its moment), what the
events of claims and of the deadman say, what ``info`` tells of each device, what every
refusal says (a bad payload, an unknown device or id, a scan too long for its bus, a bug),
and that a reply made from the bus's outcome is always one reply. The claim table on a fake
clock; the API on the LA simulator's pty and the ZLAC706 simulator on python-can's virtual
bus, as tests/test_api.py does, or on a bus runner never started where only the API's own
checks matter."""

from __future__ import annotations

import json
import logging
import math
import sys
from collections import deque
from concurrent.futures import Future
from types import SimpleNamespace

import pytest
import zenoh
from pydantic import BaseModel, Field, ValidationError

from busgate.codecs import inspire_la as la
from busgate.errors import CommandError, RefusedError
from busgate.gateway.api import commands
from busgate.gateway.api.bridge import ZenohBridge
from busgate.gateway.api.commands import (
    MAX_PAYLOAD,
    SCAN_MAX_S,
    SCAN_SLACK_S,
    GatewayApi,
    _chained,
    decode_object,
    error_reply,
)
from busgate.gateway.api.group import scan_requests
from busgate.gateway.api.put_reports import PutReports
from busgate.gateway.bus.clock import now
from busgate.gateway.bus.request import LinkTiming
from busgate.gateway.bus.serial_owner import SerialBusOwner
from busgate.gateway.bus.stats import BusCounters
from busgate.gateway.drivers.base import DeviceEvent, Effect
from busgate.gateway.drivers.families import link_timing
from busgate.gateway.scheduler.authority import Authority, ClaimTable
from busgate.gateway.scheduler.devices import BusDevices
from busgate.gateway.scheduler.runner import BusRunner
from busgate.gateway.service.assembly import build_bus
from busgate.schemas.api import MAX_VERSION
from busgate.schemas.config import parse_config
from busgate.schemas.replies import error_code
from tests import test_api
from tests.stand_in_driver import StandInDriver

#: The two buses of tests/test_api.py (LA and ZLAC706), as this module's fixture too.
gateway = test_api.gateway

# -- the claim table -------------------------------------------------------------------------


def test_a_claim_over_another_clients_claim_is_refused_naming_the_holder():
    claims = ClaimTable()
    claims.claim("la1", "alice", 10.0, now=100.0)
    with pytest.raises(RefusedError) as refused:
        claims.claim("la1", "bob", 10.0, now=105.0)
    assert refused.value.code == "claimed" and "alice" in str(refused.value)
    claims.claim("la1", "alice", 10.0, now=105.0)  # the holder renews
    claims.check("la1", "alice", now=114.0)
    with pytest.raises(RefusedError):  # renewed until 115
        claims.check("la1", "bob", now=114.0)


def test_a_claim_lapses_at_its_moment_and_anyone_may_release_a_free_device():
    claims = ClaimTable()
    claims.claim("la1", "alice", 10.0, now=100.0)
    claims.claim("la1", "bob", 10.0, now=110.0)  # alice's claim ended at 110
    with pytest.raises(RefusedError):
        claims.release("la1", "alice", now=111.0)
    claims.release("la1", "bob", now=111.0)
    claims.release("la1", "carol", now=112.0)  # nothing held: nothing to refuse
    claims.check("la1", "carol", now=112.0)


def test_a_hold_renewed_by_each_command_is_logged_once_and_keeps_others_out(caplog):
    """``ClaimTable.hold`` (the ROS face's claim, renewed with every command): new once,
    renewed silently, another client refused while it lasts, free at its moment."""
    claims = ClaimTable()
    with caplog.at_level("INFO"):
        assert claims.hold("la1", "ros", 0.5, now=100.0) is True
        assert claims.hold("la1", "ros", 0.5, now=100.25) is False  # renewed until 100.75
        with pytest.raises(RefusedError) as refused:
            claims.hold("la1", "teleop", 0.5, now=100.5)
        assert refused.value.code == "claimed" and "'ros'" in str(refused.value)
        assert claims.holder("la1", now=100.5) == "ros"
        assert claims.holder("la1", now=100.75) is None  # lapsed at its moment
        assert claims.holder("la2", now=100.0) is None
        assert claims.hold("la1", "teleop", 0.5, now=100.75) is True
    assert [r.getMessage() for r in caplog.records] == [
        "device la1 claimed by ros while its commands flow",
        "device la1: claim of ros lapsed",
        "device la1 claimed by teleop while its commands flow",
    ]


class Device(StandInDriver):
    """The least driver the authority needs: a name and an id."""

    reenable_op = "enable"


def authority_of_two() -> Authority:
    drivers = {"la1": Device("la1", 1), "la2": Device("la2", 2)}
    authority = Authority("uart0", drivers, clock=lambda: 100.0)
    authority.claims.claim("la1", "alice", 10.0, now=100.0)
    return authority


def test_stops_and_reads_pass_another_clients_claim_and_settings_do_not():
    authority = authority_of_two()
    authority.check([(frozenset({1}), Effect.STOP), (frozenset({1}), Effect.READ)], "bob")
    for effect in (Effect.SETTING, Effect.MOTION):
        with pytest.raises(RefusedError) as refused:
            authority.check([(frozenset({1}), effect)], "bob")
        assert refused.value.code == "claimed"


def test_the_devices_a_frame_moves_are_those_its_motion_names():
    authority = authority_of_two()
    names = [d.name for d in authority.addressed([(frozenset({2}), Effect.MOTION),
                                                  (frozenset({1}), Effect.SETTING)])]
    assert names == ["la2"]
    assert [d.name for d in authority.addressed([(None, Effect.MOTION)])] == ["la1", "la2"]
    stops = [(frozenset({1}), Effect.STOP), (frozenset({2}), Effect.MOTION)]
    assert [d.name for d in authority.addressed(stops, Effect.STOP)] == ["la1"]


def test_a_free_device_needs_no_claim_unless_one_is_required_and_says_so():
    authority = authority_of_two()
    authority.check([(frozenset({2}), Effect.MOTION)], "bob")  # la2 is free
    with pytest.raises(RefusedError) as refused:
        authority.check([(frozenset({2}), Effect.MOTION)], "bob", require_claim=True)
    assert refused.value.code == "not_claimed"
    assert str(refused.value) == (
        "la2 is not claimed by 'bob': its claim lapsed or was never taken; claim it again"
    )
    authority.check([(frozenset({1}), Effect.MOTION)], "alice", require_claim=True)
    with pytest.raises(RefusedError) as refused:  # no client: nobody's claim (not "None's")
        authority.check([(frozenset({2}), Effect.MOTION)], None, require_claim=True)
    assert (refused.value.code, str(refused.value)) == (
        "not_claimed", 'la2: the command asks for its client\'s claim and names no client: send '
        '"client" with it')


def test_every_effect_of_a_request_is_judged_not_only_the_first():
    authority = authority_of_two()
    with pytest.raises(RefusedError):
        authority.check([(frozenset({2}), Effect.READ), (frozenset({1}), Effect.MOTION)], "bob")


def test_reads_of_unknown_ids_pass_and_anything_else_to_them_is_refused():
    authority = authority_of_two()
    authority.check([(frozenset({7}), Effect.READ)], "bob")
    with pytest.raises(RefusedError) as refused:
        authority.check([(frozenset({7}), Effect.STOP)], "bob")
    assert refused.value.code == "unknown_device" and "7" in str(refused.value)


# -- the API ---------------------------------------------------------------------------------


def accepted(api: GatewayApi, device: str, command: dict) -> dict:
    reply = api.command(device, json.dumps(command).encode()).result(10)
    assert reply["ok"], reply
    return reply


def said(events: list[DeviceEvent], type_: str) -> list[tuple[str, dict]]:
    return [(e.device, e.fields) for e in events if e.type == type_]


def test_claims_and_releases_are_told_with_who_and_for_how_long(gateway):
    api, *_, events = gateway
    reply = accepted(api, "la2", {"op": "claim", "client": "alice", "ttl_s": 5})
    assert (reply["claimed_by"], reply["expires_in_s"]) == ("alice", 5.0)
    refused = api.command("la2", b'{"op":"claim","client":"bob"}').result(10)
    assert refused["error"]["code"] == "claimed"
    assert accepted(api, "la2", {"op": "release", "client": "alice"})["released"] is True
    assert said(events, "claimed") == [("la2", {"client": "alice", "ttl_s": 5.0})]
    assert said(events, "released") == [("la2", {"client": "alice"})]


def test_a_client_refused_a_speed_is_not_the_one_whose_going_stops_the_wheel(gateway):
    """An outside audit: a client refused a one-shot speed (the wheel claimed by another) was
    taken for its deadman's, and its going stopped the wheel the holder drove."""
    api, *_, events = gateway
    for op in ({"op": "set_mode", "mode": "velocity"}, {"op": "enable"}):
        accepted(api, "wheel", op)
    accepted(api, "wheel", {"op": "claim", "client": "teleop"})
    accepted(api, "wheel", {"op": "velocity", "rpm": 200, "client": "teleop"})
    refused = api.command("wheel", b'{"op":"velocity","rpm":10,"client":"other"}').result(10)
    assert refused["error"]["code"] == "claimed"
    api.client_left("other")
    assert said(events, "stopped") == []
    api.client_left("teleop")
    assert said(events, "stopped") == [("wheel", {"client": "teleop", "reason": "client gone"})]


def test_the_deadman_tells_what_it_released_stopped_and_why(wait_for, gateway):
    api, *_, events = gateway
    for op in ({"op": "set_mode", "mode": "velocity"}, {"op": "enable"}):
        accepted(api, "wheel", op)
    accepted(api, "wheel", {"op": "velocity", "rpm": 200, "client": "teleop"})
    accepted(api, "la1", {"op": "claim", "client": "teleop"})
    assert api.follow("la1", b'{"position": 700, "client": "teleop"}') is None
    api.client_left("teleop")
    assert ("la1", {"client": "teleop", "reason": "client gone"}) in said(events, "released")
    assert said(events, "stopped") == [("wheel", {"client": "teleop", "reason": "client gone"})]
    wait_for(lambda: said(events, "stream_stopped"))
    assert said(events, "stream_stopped") == [("la1", {"reason": "client teleop gone"})]


def test_info_gives_each_devices_id_and_latest_state(wait_for, gateway):
    api, *_ = gateway
    runner = api.runners["uart0"]
    wait_for(lambda: "la1" in runner.states)
    devices = {d["name"]: d for bus in api.info()["buses"] for d in bus["devices"]}
    assert {name: d["id"] for name, d in devices.items()} == {"la1": 1, "la2": 2, "wheel": 5}
    assert devices["la1"]["state"]["device"] == "la1"
    assert api.info()["version"]


def test_a_payload_of_exactly_the_limit_is_read_and_one_byte_more_is_not(gateway):
    api, *_ = gateway
    pad = MAX_PAYLOAD - len(b'{"op":"status","x":""}')
    at_limit = b'{"op":"status","x":"' + b" " * pad + b'"}'
    assert len(at_limit) == MAX_PAYLOAD
    reply = api.command("la1", at_limit).result(10)
    assert reply["error"]["code"] == "bad_command", "read and judged as a command"
    over = api.command("la1", at_limit[:-2] + b' "}').result(10)
    assert over["error"]["code"] == "too_large"


def test_a_claim_with_a_bad_lifetime_is_refused_as_out_of_range(gateway):
    api, *_, events = gateway
    reply = api.command("la1", b'{"op":"claim","client":"alice","ttl_s":0}').result(10)
    assert reply["error"]["code"] == "out_of_range" and "ttl_s" in reply["error"]["message"]
    assert said(events, "claimed") == []


# -- replies: the envelope, and what each refusal says ---------------------------------------


def test_a_bug_is_answered_internal_with_its_message_or_its_type():
    assert error_reply(ValueError("boom")) == {
        "ok": False,
        "error": {"code": "internal", "message": "boom"},
    }
    assert error_reply(KeyError())["error"] == {"code": "internal", "message": "KeyError"}


HUGE = b'{"op":"' + b"x" * MAX_PAYLOAD + b'"}'


@pytest.mark.parametrize(
    ("payload", "code", "message"),
    [
        (HUGE, "too_large", f"payload of {len(HUGE)} bytes; at most {MAX_PAYLOAD}"),
        (b'{"op": "\xff"}', "not_utf8", "payload is not UTF-8: invalid start byte"),
        (
            b'{"a": 1, "op": "move", "op": "stop"}',
            "bad_command",
            "key 'op' appears twice: a command is never guessed",
        ),
        (b"[" * 30_000 + b"]" * 30_000, "bad_command", "payload is nested too deeply"),
        (b'{"position": NaN}', "not_json", "payload is not JSON: NaN is not a number JSON allows"),
        (
            b'{"position": 1e999}',
            "not_json",
            "payload is not JSON: 1e999 is too large for a double",
        ),
        (
            b"{op: move}",
            "not_json",
            "payload is not JSON: Expecting property name enclosed in "
            "double quotes: line 1 column 2 (char 1)",
        ),
        (b"[1]", "bad_command", "a command is a JSON object"),
        (
            b'{"position": ' + b"9" * 5000 + b"}",  # past the interpreter's own limit
            "not_json",
            "payload is not JSON: an integer of 5000 digits is too large for a double",
        ),
        (
            b'{"position": -1' + b"0" * 400 + b"}",  # was refused by each field in its words
            "not_json",
            "payload is not JSON: an integer of 401 digits is too large for a double",
        ),
        (
            b'{"position": ' + str(int(sys.float_info.max) + 1).encode() + b"}",
            "not_json",
            "payload is not JSON: an integer of 309 digits is too large for a double",
        ),
    ],
)
def test_a_payload_refused_before_it_is_a_command_says_why(payload, code, message):
    with pytest.raises(RefusedError) as refused:
        decode_object(payload)
    assert (refused.value.code, str(refused.value)) == (code, message)


class Ranges(BaseModel):
    """One field per pydantic error type that means "out of its range"."""

    lt: int = Field(lt=0)
    le: int = Field(le=0)
    gt: int = Field(gt=0)
    ge: int = Field(ge=0)
    step: int = Field(multiple_of=2)
    short: list[int] = Field(min_length=1)
    long: list[int] = Field(max_length=0)


def test_a_command_outside_every_kind_of_range_at_once_is_out_of_range():
    with pytest.raises(ValidationError) as invalid:
        Ranges(lt=1, le=1, gt=0, ge=-1, step=1, short=[], long=[1])
    assert len(invalid.value.errors()) == 7
    assert error_code(invalid.value) == "out_of_range"


def test_a_refused_command_keeps_its_code_and_its_message():
    refused = error_reply(CommandError("Inspire LA group moves have no move time; drop time_ms"))
    assert refused["error"] == {
        "code": "bad_command",
        "message": "Inspire LA group moves have no move time; drop time_ms",
    }


def test_an_unknown_device_is_named_with_the_gateway():
    reply = GatewayApi("gw", {}).command("la9", b'{"op":"status"}').result(0)
    assert reply["error"] == {"code": "unknown_device", "message": "no device 'la9' on gateway gw"}


def estop_bridge() -> tuple[ZenohBridge, BusRunner, deque[DeviceEvent]]:
    """A bridge with no session over one bus never started: its e-stops wait in its inbox."""
    config = parse_config({
        "gateway": {"name": "gw"},
        "buses": [{"name": "uart0", "transport": "serial", "port": "/dev/null", "baudrate": 921_600,
                   "devices": [{"name": "la1", "kind": "inspire_la", "id": 1}]}],
    })  # fmt: skip
    runner = build_bus(config.buses[0])
    events: deque[DeviceEvent] = deque()
    bridge = ZenohBridge(config, GatewayApi("gw", {"uart0": runner}), {"uart0": runner},
                         events, deque())  # fmt: skip
    return bridge, runner, events


def idle_bus_api() -> tuple[GatewayApi, BusRunner]:
    """The API over ``estop_bridge``'s bus, never started: what it hands over waits in the
    bus's inbox."""
    _, runner, _ = estop_bridge()
    return GatewayApi("gw", {"uart0": runner}), runner


def test_an_estop_is_handed_to_every_bus_before_its_payload_is_read(caplog, monkeypatch):
    """The payload only names the sender (for the log line and the event): a large one, up
    to 64 KiB of JSON to parse, would otherwise hold the e-stop up by milliseconds."""
    bridge, runner, events = estop_bridge()
    order: list[str] = []
    handed = runner.estop
    monkeypatch.setattr(runner, "estop", lambda: order.append("handed") or handed())

    class Payload:
        def __len__(self) -> int:
            order.append("measured")
            return len(b'{"client": "teleop"}')

        def to_bytes(self) -> bytes:
            order.append("read")
            return b'{"client": "teleop"}'

    sample = SimpleNamespace(payload=Payload(), key_expr="busgate/gw/estop")
    with caplog.at_level("WARNING"):
        bridge._on_estop(sample)
    assert order == ["handed", "measured", "read"]
    assert [r.getMessage() for r in caplog.records] == ["e-stop of every bus from teleop"]
    assert [(e.type, e.fields) for e in events] == [
        ("estop", {"key": "busgate/gw/estop", "client": "teleop"})
    ]


def test_an_estop_whose_payload_is_too_large_to_name_a_client_is_never_read():
    """Its payload only names its sender, at most 64 KiB of it: a larger one, copied out of
    zenoh on its receiving thread, held it by a copy of up to 2 MiB each (a flood of them)."""
    bridge, runner, events = estop_bridge()

    class Payload:
        def __len__(self) -> int:
            return MAX_PAYLOAD + 1

        def to_bytes(self) -> bytes:
            raise AssertionError("read")

    bridge._on_estop(SimpleNamespace(payload=Payload(), key_expr="busgate/gw/estop"))
    assert len(runner._inbox) == 1
    assert [(e.type, e.fields) for e in events] == [("estop", {"key": "busgate/gw/estop"})]


# -- the authority's refusals and its log ----------------------------------------------------


def test_ids_no_device_has_are_named_with_the_bus():
    with pytest.raises(RefusedError) as refused:
        authority_of_two().check([(frozenset({9, 7}), Effect.STOP)], "bob")
    assert str(refused.value) == "no device of bus uart0 is configured with id 7, 9"


def test_a_lapsed_claim_is_logged_with_its_device_and_client(caplog):
    claims = ClaimTable()
    claims.claim("la1", "alice", 10.0, now=100.0)
    with caplog.at_level("INFO", logger="busgate.gateway.scheduler.authority"):
        claims.check("la1", "bob", now=110.0)
    assert [r.getMessage() for r in caplog.records] == ["device la1: claim of alice lapsed"]


def test_a_claim_renewed_by_its_holder_is_not_logged_as_new(caplog):
    """The SDK renews a claim every half of its TTL: a journal line a second for each device
    a client holds, where a new holder (a lapsed claim taken again too) is what is news."""
    claims = ClaimTable()
    with caplog.at_level("INFO", logger="busgate.gateway.scheduler.authority"):
        claims.claim("la1", "alice", 2.0, now=100.0)
        claims.claim("la1", "alice", 2.0, now=101.0)  # renewed
        claims.claim("la1", "alice", 2.0, now=104.0)  # lapsed at 103: claimed again
    assert [r.getMessage() for r in caplog.records] == [
        "device la1 claimed by alice for 2.0 s",
        "device la1: claim of alice lapsed",
        "device la1 claimed by alice for 2.0 s",
    ]


def test_a_claim_renewed_by_its_holder_is_told_at_debug_level_naming_device_client_and_ttl(
    caplog,
):
    claims = ClaimTable()
    claims.claim("la1", "alice", 2.0, now=100.0)
    with caplog.at_level("DEBUG", logger="busgate.gateway.scheduler.authority"):
        claims.claim("la1", "alice", 1.5, now=101.0)
    assert [(r.levelname, r.getMessage()) for r in caplog.records] == [
        ("DEBUG", "device la1: the claim of alice renewed for 1.5 s")
    ]


# -- replies made from the bus's outcome ------------------------------------------------------


def test_a_reply_that_cannot_be_made_is_an_internal_error_not_silence(caplog):
    def broken(result):
        raise RuntimeError("no reply from this")

    submitted: Future = Future()
    answer = _chained(submitted, broken)
    submitted.set_result({})
    assert answer.result(0) == {
        "ok": False,
        "error": {"code": "internal", "message": "no reply from this"},
    }
    assert [r.getMessage() for r in caplog.records] == ["making a reply failed"]


def test_an_outcome_after_its_reply_was_cancelled_is_dropped_quietly(caplog):
    submitted: Future = Future()
    answer = _chained(submitted, lambda result: {"ok": True})
    assert submitted.set_running_or_notify_cancel()
    assert answer.cancel(), "the bridge answered without waiting"
    submitted.set_result({})  # the job had started: it finished all the same
    assert answer.cancelled()
    assert [r for r in caplog.records if r.levelno >= logging.WARNING] == []


def test_a_refusal_from_the_bus_is_answered_without_a_traceback(gateway, caplog):
    api, *_ = gateway
    accepted(api, "la1", {"op": "claim", "client": "alice"})
    with caplog.at_level("INFO"):
        reply = api.command("la1", b'{"op":"move","position":5,"client":"bob"}').result(10)
    assert reply["error"]["code"] == "claimed"
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == []


class BrokenFollow(Device):
    """A driver whose follow validation has a bug."""

    def follow_target(self, payload):
        raise RuntimeError("follow bug")


def test_a_bug_in_a_follow_is_answered_internal_and_logged_with_its_device(caplog):
    timing = link_timing("inspire_la", 921_600, margin_s=0.05)
    owner = SerialBusOwner("/nonexistent/tty", la, timing, BusCounters(now()))
    devices = BusDevices([BrokenFollow("arm", 1)])
    runner = BusRunner("b", owner, timing, devices, poll_hz={})  # not started
    reply = GatewayApi("gw", {"b": runner}).follow("arm", b'{"position": 1}')
    assert reply == {"ok": False, "error": {"code": "internal", "message": "follow bug"}}
    (record,) = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert record.getMessage() == "follow on arm failed" and record.exc_info


def test_a_group_move_to_a_device_of_no_bus_names_it(gateway):
    api, *_ = gateway
    move = {"op": "group_move", "targets": [{"device": "ghost", "position": 5}]}
    reply = api.bus_command("uart0", json.dumps(move).encode()).result(10)
    assert reply["error"] == {"code": "unknown_device", "message": "no device 'ghost' on this bus"}


def test_a_scan_tells_which_ids_answered_on_which_protocol(gateway):
    api, *_ = gateway
    found = api.bus_command("uart0", b'{"op":"scan","ids":[1,2,3]}').result(10)
    assert found == {
        "ok": True,
        "found": [
            {"id": 1, "protocol": "inspire_la", "reply": "StatusReply"},
            {"id": 2, "protocol": "inspire_la", "reply": "StatusReply"},
        ],
    }


# -- how long a scan may take -----------------------------------------------------------------


def idle_api(timing: LinkTiming) -> GatewayApi:
    """An API whose one bus is never started: what it accepts waits there, unanswered."""
    owner = SerialBusOwner("/nonexistent/tty", la, timing, BusCounters(now()))
    return GatewayApi("gw", {"b": BusRunner("b", owner, timing, BusDevices([]), poll_hz={})})


def planned(timing: LinkTiming, ids: list[int]) -> float:
    """What a scan of ``ids`` may take on a bus of ``timing``: each probe's worst case and
    the gap after it."""
    return sum(timing.worst_case(p) + timing.gap_s for p in scan_requests("inspire_la", ids))


def test_a_scan_too_long_for_its_bus_says_how_long_and_how_many_ids_fit():
    timing = link_timing("inspire_la", 921_600, margin_s=0.5, gap_s=0.1)
    ids = list(range(1, 11))
    planned_s = planned(timing, ids)
    most = int(len(ids) * SCAN_MAX_S / planned_s)
    assert planned_s > SCAN_MAX_S and 1 <= most < len(ids)
    reply = idle_api(timing).bus_command("b", json.dumps({"op": "scan", "ids": ids}).encode())
    assert reply.result(0)["error"] == {
        "code": "out_of_range",
        "message": f"a scan of 10 ids takes up to {planned_s:.1f} s on bus b; "
        f"ask for at most {most} ids at a time",
    }


def test_a_scan_that_just_fits_its_bus_goes_to_the_bus():
    margin = SCAN_MAX_S - link_timing("inspire_la", 921_600, margin_s=0.0).worst_case(
        scan_requests("inspire_la", [1])[0]
    )
    for _ in range(100):  # the margin that makes the plan exactly SCAN_MAX_S, to the last bit
        timing = link_timing("inspire_la", 921_600, margin_s=margin)
        if planned(timing, [1]) == SCAN_MAX_S:
            break
        margin = math.nextafter(margin, 0 if planned(timing, [1]) > SCAN_MAX_S else 10)
    assert planned(timing, [1]) == SCAN_MAX_S
    assert not idle_api(timing).bus_command("b", b'{"op":"scan","ids":[1]}').done()


def test_a_scan_whose_room_on_the_bus_has_passed_is_answered_busy(gateway, monkeypatch):
    """A scan's probes must all start within twice its plan and a second. With the API's
    clock set back past that room (but not past three times the plan), the bus finds the
    scan expired before its first probe."""
    api, simulator, *_ = gateway
    runner = api.runners["uart0"]
    ids = list(range(1, 61))
    planned_s = planned(runner.timing, ids)
    assert planned_s <= SCAN_MAX_S
    behind = 2.5 * planned_s + SCAN_SLACK_S
    monkeypatch.setattr(commands, "now", lambda: now() - behind)
    before = len(simulator.recorder.received())
    reply = api.bus_command("uart0", json.dumps({"op": "scan", "ids": ids}).encode()).result(10)
    assert reply["error"]["code"] == "busy"
    assert "last 60 ids (0 probed)" in reply["error"]["message"]
    monkeypatch.undo()
    accepted(api, "la1", {"op": "status"})
    probes = [r for r in simulator.recorder.received()[before:] if r.frame == "ControlCommand"]
    assert len(probes) == 1, "only the status asked after the scan"


def test_estops_put_in_a_loop_each_reach_the_bus_and_are_told_once_a_tenth_of_a_second(caplog):
    """A client putting e-stops in a loop: every put is handed to every bus, but one log
    line and one event are told every 0.1 s, the rest counted: the journal keeps the other
    lines, the events key the other events."""
    bridge, runner, events = estop_bridge()
    # The bridge's own reports and their teller, on a clock that stands still: the ten puts
    # come within 0.1 s however slow the host.
    bridge.put_reports = PutReports(bridge.api.devices, bridge._tell_put, clock=lambda: 0.0)
    payload = zenoh.ZBytes(b'{"client": "teleop"}')
    sample = SimpleNamespace(payload=payload, key_expr="busgate/gw/estop")
    with caplog.at_level("WARNING"):
        for _ in range(10):
            bridge._on_estop(sample)
        bridge.put_reports.flush(every=True)  # the gateway stops: the withheld are told
    assert len(runner._inbox) == 10
    assert [r.getMessage() for r in caplog.records] == [
        "e-stop of every bus from teleop",
        "e-stop of every bus from teleop (8 more since the last told)",
    ]
    assert [e.fields.get("suppressed") for e in events] == [None, 8]


def test_resets_put_in_a_loop_each_reach_the_bus_and_are_told_once_a_tenth_of_a_second(caplog):
    """As e-stops are: every reset put is handed to every bus, one log line and one event
    every 0.1 s; a put on another gateway's or a wildcard reset key does nothing."""
    bridge, runner, events = estop_bridge()
    bridge.put_reports = PutReports(bridge.api.devices, bridge._tell_put, clock=lambda: 0.0)
    payload = zenoh.ZBytes(b'{"client": "panel"}')
    with caplog.at_level("WARNING"):
        for key in ["busgate/gw/estop/reset"] * 5 + ["busgate/*/estop/reset", "busgate/gw/**"]:
            bridge._on_estop_reset(SimpleNamespace(payload=payload, key_expr=key))
        bridge.put_reports.flush(every=True)
    assert len(runner._inbox) == 5
    assert [r.getMessage() for r in caplog.records] == [
        "e-stop reset of every bus from panel",
        "e-stop reset of every bus from panel (3 more since the last told)",
    ]
    assert [(e.type, e.fields) for e in events] == [
        ("estop_reset", {"client": "panel"}),
        ("estop_reset", {"client": "panel", "suppressed": 3}),
    ]


@pytest.mark.parametrize(("payload", "code", "message"), [
    (b"\xff", "not_utf8", "payload is not UTF-8: invalid start byte"),
    (b"[]", "bad_command", "a command is a JSON object"),
    (b'{"client": "a b"}', "bad_command", "client 'a b' is no client id"),
    (b'{"client": 7}', "bad_command", "client 7 is no client id"),  # told as sent, not '7'
    (b'{"client": true}', "bad_command", "client true is no client id"),
    (b'{"client": ["a"]}', "bad_command", 'client ["a"] is no client id'),
    (b'{"op": "move", "position": 500}', "bad_command",  # a command on the wrong key
     'a reset of every device takes nothing but "client", not op, position: nothing was reset'),
    (b'{"client": "x", "extra": 1}', "bad_command",
     'a reset of every device takes nothing but "client", not extra: nothing was reset'),
    (b'{"client": "panel"' + b" " * 70_000 + b"}", "too_large",
     "payload of 70019 bytes; at most 65536"),
])
def test_a_reset_put_whose_payload_is_no_reset_resets_nothing_and_is_told(payload, code,
                                                                           message):
    """The e-stop takes any payload; its reset took any too (not UTF-8, 70 KB): a reset is
    carried out only on an empty payload or an object naming a valid client, else it is
    refused as any bad put is, by a ``command_refused`` event."""
    bridge, runner, events = estop_bridge()
    recorded: list = []
    bridge.on_command = lambda *command: recorded.append(command)  # as the flight recorder
    key = "busgate/gw/estop/reset"
    bridge._on_estop_reset(SimpleNamespace(payload=zenoh.ZBytes(payload), key_expr=key))
    assert len(runner._inbox) == 0, "nothing reset"
    [event] = events
    assert (event.device, event.type, event.fields) == (
        "*", "command_refused", {"code": code, "message": message})
    # kept among the commands with its refusal, as a refused command is (an audit: missing)
    [(recorded_key, recorded_payload, reply, _)] = recorded
    kept = b"" if code == "too_large" else payload  # one too large is never read (bridge's _taken)
    assert (recorded_key, recorded_payload) == (key, kept)
    assert reply["error"] == {"code": code, "message": message}
    for good in (b"", b" \n", b"{}", b'{"client": null}', b'{"client": "panel"}'):
        bridge._on_estop_reset(SimpleNamespace(payload=zenoh.ZBytes(good), key_expr=key))
    assert len(runner._inbox) == 5


def test_a_devices_reset_is_told_and_handed_over_unless_another_client_holds_it():
    _, runner, _ = estop_bridge()
    events: list[DeviceEvent] = []
    api = GatewayApi("gw", {"uart0": runner}, on_event=events.append)
    runner.authority.claims.claim("la1", "alice", 10.0, now=runner.authority.clock())
    refused = api.command("la1", b'{"op": "reset_estop", "client": "bob"}').result(0)
    assert refused["error"]["code"] == "claimed" and not runner._inbox and not events
    pending = api.command("la1", b'{"op": "reset_estop", "client": "alice"}')
    assert not pending.done() and len(runner._inbox) == 1
    assert [(e.device, e.type, e.fields) for e in events] == [
        ("la1", "estop_reset", {"client": "alice"})
    ]


def test_a_follow_target_to_a_device_playing_a_trajectory_is_refused_busy_saying_why():
    api, runner = idle_bus_api()
    runner.plays.start({"la1": lambda t_s: {"position": 900}}, now() + 1.0)  # the bus thread's
    assert runner.plays.playing("la1")
    assert api.follow("la1", b'{"position": 100}') == {"ok": False, "error": {
        "code": "busy",
        "message": "la1 is playing a trajectory: cancel it first (a follow stream and a "
                   "trajectory would fight over its target)",
    }}  # fmt: skip
    assert not runner._inbox  # nothing handed to the bus


def test_a_devices_reset_goes_to_that_device_alone():
    api, runner = idle_bus_api()
    asked: list[tuple[str | None, frozenset[str]]] = []
    reset = runner.reset_estop
    runner.reset_estop = lambda device=None, skip=frozenset(): (
        asked.append((device, skip)) or reset(device, skip))
    api.command("la1", b'{"op": "reset_estop"}')
    api.reset_every_bus()
    assert asked == [("la1", frozenset()), (None, frozenset())]


def test_a_kept_target_holds_its_device_for_its_client_and_ramps_it_there(gateway, wait_for):
    """``GatewayApi.ramp_to`` (the ROS face's commands): the first target claims the device
    for its client (told once), each renews it, another client is refused while it lasts, and
    the device gets to the target (a joint without a table here: its values are counts)."""
    api, _, _, clock, events = gateway
    assert api.ramp_to("la1", {"joint": 700}, "ros", 0.5) is None
    assert api.ramp_to("la1", {"joint": 800}, "ros", 0.5) is None
    assert said(events, "claimed") == [("la1", {"client": "ros", "ttl_s": 0.5})]
    refused = api.ramp_to("la1", {"joint": 900}, "teleop", 0.5)
    assert refused["error"]["code"] == "claimed" and "'ros'" in refused["error"]["message"]
    moved = api.command("la1", b'{"op": "move", "position": 900, "client": "teleop"}')
    assert moved.result(5)["error"]["code"] == "claimed"  # the hold is on the device itself
    wait_for(lambda: api.devices["la1"][1].telemetry(now()).get("target") == 800)
    assert api.ramp_to("la1", {"nope": 1}, "ros", 0.5)["error"]["code"] == "bad_command"
    clock.offset += 0.5  # the hold lapsed: another client may take over
    assert api.ramp_to("la1", {"joint": 600}, "teleop", 0.5) is None
    assert said(events, "claimed")[-1] == ("la1", {"client": "teleop", "ttl_s": 0.5})


def test_a_kept_target_is_refused_saying_why_while_a_trajectory_plays_or_the_bus_is_down():
    api, runner = idle_bus_api()  # never started: its bus is down
    assert api.ramp_to("la1", {"joint": 700}, "ros", 0.5)["error"] == {
        "code": "bus_unavailable",
        "message": "bus uart0 is down: la1 cannot move",
    }
    runner.plays.start({"la1": lambda t_s: {"position": 900}}, now() + 1.0)  # the bus thread's
    assert api.ramp_to("la1", {"joint": 700}, "ros", 0.5)["error"] == {
        "code": "busy",
        "message": "la1 is playing a trajectory: cancel it first (a target kept and a "
        "trajectory would fight over its target)",
    }
    assert not runner._inbox and runner.authority.claims.holder("la1", now()) is None


def test_a_bug_in_a_kept_target_is_answered_internal_and_logged_with_its_device(
    gateway, monkeypatch, caplog
):
    api, *_ = gateway
    runner, _ = api.devices["la1"]

    def broken(device: str, target: float, follows: str) -> None:
        raise RuntimeError("a bug")

    monkeypatch.setattr(runner, "ramp", broken)
    with caplog.at_level(logging.ERROR, logger="busgate.gateway.api.commands"):
        reply = api.ramp_to("la1", {"joint": 700}, "ros", 0.5)
    assert reply["error"] == {"code": "internal", "message": "a bug"}
    assert [r.getMessage() for r in caplog.records] == ["ramp on la1 failed"]


def test_an_end_and_a_target_numbered_one_without_the_other_are_ordered_by_the_fence():
    api, runner = idle_bus_api()
    api.command("la1", b'{"op": "end_follow", "client": "carol"}')  # no seq
    handed = len(runner._inbox)
    assert api.follow("la1", b'{"position": 700, "client": "carol", "seq": 9}') is None
    assert len(runner._inbox) == handed  # within the fence: dropped, not a new stream


def test_a_target_with_its_ends_own_number_starts_nothing_and_one_above_does():
    api, runner = idle_bus_api()
    api.command("la1", b'{"op": "end_follow", "client": "carol", "seq": 7}')
    handed = len(runner._inbox)
    assert api.follow("la1", b'{"position": 700, "client": "carol", "seq": 7}') is None
    assert len(runner._inbox) == handed  # numbered alike: cannot be ordered, nothing moves
    assert api.follow("la1", b'{"position": 700, "client": "carol", "seq": 8}') is None
    assert len(runner._inbox) == handed + 1


def test_the_ends_of_a_client_that_left_order_none_of_its_next_targets():
    api, runner = idle_bus_api()
    api.command("la1", b'{"op": "end_follow", "client": "carol"}')
    api.client_left("dave")  # another client: carol's end stands
    handed = len(runner._inbox)
    assert api.follow("la1", b'{"position": 700, "client": "carol"}') is None
    assert len(runner._inbox) == handed  # inside her end's fence: no new stream
    api.client_left("carol")
    assert api.follow("la1", b'{"position": 700, "client": "carol"}') is None
    assert len(runner._inbox) == handed + 1  # her end went with her: a new stream


def test_a_version_longer_than_a_client_takes_is_cut_to_the_longest_it_takes(monkeypatch):
    api, _ = idle_bus_api()
    monkeypatch.setattr(commands, "installed_version", lambda: "1.0+" + "g" * 500)
    version = api.info()["version"]
    assert len(version) == MAX_VERSION and version.startswith("1.0+g") and version[-1] == "…"
    monkeypatch.setattr(commands, "installed_version", lambda: "2" * (MAX_VERSION - 1))
    assert api.info()["version"] == "2" * (MAX_VERSION - 1)  # one shorter is whole
