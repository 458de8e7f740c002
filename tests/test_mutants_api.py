"""What mutation testing (``python mutation/run.py api``) found the API tests leaving open:
a claim over another client's claim is refused (and a claim lapses at its moment), what the
events of claims and of the deadman say, and what ``info`` tells of each device. The claim
table on a fake clock; the API on the LA simulator's pty and the ZLAC706 simulator on
python-can's virtual bus, as tests/test_api.py does."""

from __future__ import annotations

import json

import pytest

from busgate.codecs.errors import RefusedError
from busgate.gateway.api.commands import MAX_PAYLOAD, GatewayApi
from busgate.gateway.drivers.base import DeviceEvent, Driver, Effect
from busgate.gateway.scheduler.authority import Authority, ClaimTable
from tests import test_api

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


class Device(Driver):
    """The least driver the authority needs: a name and an id."""

    kind = protocol = "test"
    reenable_op = "enable"
    plan = poll = safe_stop = telemetry = frames_of = lambda self, *a: []
    apply = lambda self, *a: {}  # noqa: E731
    effect = lambda self, frame: Effect.MOTION  # noqa: E731


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
