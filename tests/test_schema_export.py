"""The exported JSON Schemas: the committed files are what ``busgate schema`` writes, and each
one accepts what the gateway really produces (states built by the drivers from codec-decoded
replies, the API's own replies and events, bus counters, the example configs) and refuses
malformed commands.

Examples are checked twice: against the pydantic model, and against the committed JSON file
with a small validator of the JSON Schema keywords pydantic emits (it refuses any keyword it
does not know, so a schema it cannot judge fails loudly instead of passing).
"""

from __future__ import annotations

import json
import math
import operator
import re
import time
import tomllib
from dataclasses import asdict, fields
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from pydantic import ValidationError

from busgate.codecs import ds_servo as ds
from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as can_codec
from busgate.codecs import zlac706_rs232 as rs_codec
from busgate.codecs.can_frame import CanFrame
from busgate.errors import RefusedError
from busgate.gateway.api import commands
from busgate.gateway.api.commands import GatewayApi, ok_reply
from busgate.gateway.api.group import scan_requests, scan_result
from busgate.gateway.bus.stats import BusCounters, BusStats
from busgate.gateway.cli import main
from busgate.gateway.cli import schema as schema_cli
from busgate.gateway.drivers.base import OFFLINE_AFTER, DeviceEvent, Driver
from busgate.gateway.drivers.ds_servo import DsServoDriver
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.drivers.zlac706_rs232 import Zlac706Rs232Driver
from busgate.gateway.scheduler.authority import Authority
from busgate.schemas import api, exported, trajectory
from busgate.schemas.config import Config
from busgate.schemas.events import EVENT_ADAPTER
from busgate.schemas.payload import MAX_PAYLOAD
from busgate.schemas.replies import error_reply
from tests.published_state import published

ROOT = Path(__file__).resolve().parent.parent
SCHEMA_DIR = ROOT / "schemas" / "json"
MANUAL_MONITOR = "80000181 e1001cfd e20011f3 e4010ef3 e60000e6 e727101e e80000e8 e9271020"


# --- a validator for the keywords pydantic emits ----------------------------------------------

ANNOTATIONS = {"$schema", "$defs", "title", "description", "default", "discriminator"}
TYPES = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "number": lambda v: isinstance(v, int | float) and not isinstance(v, bool),
}


def errors(value: Any, schema: dict, root: dict, path: str = "$") -> list[str]:
    """Why ``value`` does not match ``schema`` (empty: it does)."""
    found: list[str] = []
    for key, rule in schema.items():
        check = CHECKS.get(key)
        if check is None:
            if key not in ANNOTATIONS and key not in OBJECT_KEYWORDS:
                raise AssertionError(f"the test validator does not know keyword {key!r}")
            continue
        found += check(value, rule, schema, root, path)
    if isinstance(value, dict) and schema.get("type") == "object":
        found += object_errors(value, schema, root, path)
    return found


OBJECT_KEYWORDS = {"properties", "required", "additionalProperties"}


def object_errors(value: dict, schema: dict, root: dict, path: str) -> list[str]:
    properties = schema.get("properties", {})
    found = [f"{path}: missing {name}" for name in schema.get("required", []) if name not in value]
    extra = schema.get("additionalProperties", True)
    for name, item in value.items():
        if name in properties:
            found += errors(item, properties[name], root, f"{path}.{name}")
        elif extra is False:
            found.append(f"{path}: unexpected {name}")
        elif isinstance(extra, dict):
            found += errors(item, extra, root, f"{path}.{name}")
    return found


def _ref(value, rule, schema, root, path):
    assert rule.startswith("#/$defs/"), rule
    return errors(value, root["$defs"][rule.removeprefix("#/$defs/")], root, path)


def _any_of(value, rule, schema, root, path):
    results = [errors(value, option, root, path) for option in rule]
    return [] if any(not r for r in results) else [f"{path}: no option matches: {results}"]


def _one_of(value, rule, schema, root, path):
    matching = sum(not errors(value, option, root, path) for option in rule)
    return [] if matching == 1 else [f"{path}: {matching} options match, not exactly one"]


def _items(value, rule, schema, root, path):
    if not isinstance(value, list):
        return []
    return [e for i, item in enumerate(value) for e in errors(item, rule, root, f"{path}[{i}]")]


def _bound(test: Any, sized: bool = False) -> Any:
    """A check of a number (or, ``sized``, of a string's or array's length) against a bound."""

    def check(value, rule, schema, root, path):
        applies = isinstance(value, str | list) if sized else TYPES["number"](value)
        if applies and not test(len(value) if sized else value, rule):
            return [f"{path}: {value!r} is out of bounds ({rule})"]
        return []

    return check


CHECKS = {
    "$ref": _ref,
    "anyOf": _any_of,
    "oneOf": _one_of,
    "items": _items,
    "type": lambda v, rule, s, root, p: [] if TYPES[rule](v) else [f"{p}: {v!r} is not {rule}"],
    "const": lambda v, rule, s, root, p: [] if v == rule and type(v) is type(rule)
    else [f"{p}: {v!r} is not {rule!r}"],
    "enum": lambda v, rule, s, root, p: [] if v in rule else [f"{p}: {v!r} not in {rule}"],
    "pattern": lambda v, rule, s, root, p: [] if not isinstance(v, str) or re.search(rule, v)
    else [f"{p}: {v!r} does not match {rule}"],
    "minimum": _bound(operator.ge),
    "maximum": _bound(operator.le),
    "exclusiveMinimum": _bound(operator.gt),
    "exclusiveMaximum": _bound(operator.lt),
    "multipleOf": _bound(lambda v, r: math.isclose(v / r, round(v / r))),
    "minItems": _bound(operator.ge, sized=True),
    "maxItems": _bound(operator.le, sized=True),
    "minLength": _bound(operator.ge, sized=True),
    "maxLength": _bound(operator.le, sized=True),
}


def committed(name: str) -> dict:
    return json.loads((SCHEMA_DIR / name).read_text(encoding="utf-8"))


def assert_valid(name: str, value: Any) -> None:
    """``value`` (as JSON would carry it) matches the committed schema ``name``."""
    value = json.loads(json.dumps(value))
    schema = committed(name)
    assert errors(value, schema, schema) == []


def assert_invalid(name: str, value: Any) -> None:
    schema = committed(name)
    assert errors(value, schema, schema) != []


# --- the committed files -----------------------------------------------------------------------


def test_the_committed_schemas_are_up_to_date():
    stale = schema_cli.stale_files(SCHEMA_DIR)
    assert stale == [], f"out of date: {stale}; regenerate with `busgate schema`"


def test_the_schema_folder_holds_data_only():
    assert {p.suffix for p in SCHEMA_DIR.iterdir()} == {".json"}
    assert sorted(p.name for p in SCHEMA_DIR.iterdir()) == sorted(exported.SCHEMAS)


def test_output_is_deterministic_and_ends_with_one_newline():
    first, second = exported.generated(), exported.generated()
    assert first == second
    for text in first.values():
        assert text.endswith("}\n") and not text.endswith("\n\n")
        assert json.loads(text)["$schema"] == exported.DRAFT


def test_check_names_the_stale_files_and_writing_fixes_them(tmp_path, capsys):
    out = tmp_path / "json"
    assert main(["schema", "--out", str(out)]) == 0
    assert main(["schema", "--out", str(out), "--check"]) == 0
    (out / "info.json").write_text("{}\n")
    (out / "config.json").unlink()
    (out / "package.json").write_text('{"mine": 1}\n')  # not ours: never named, never removed
    capsys.readouterr()
    assert main(["schema", "--out", str(out), "--check"]) == 1
    err = capsys.readouterr().err
    assert all(name in err for name in ("info.json", "config.json"))
    assert "telemetry.zlac706.json" not in err and "package.json" not in err
    assert main(["schema", "--out", str(out)]) == 0
    assert schema_cli.stale_files(out) == []
    assert (out / "package.json").read_text() == '{"mine": 1}\n'


def test_a_schema_no_longer_generated_is_named_and_removed_in_the_repository_only(
        tmp_path, monkeypatch):
    out = tmp_path / "json"
    monkeypatch.setattr(schema_cli, "DEFAULT_OUT", out.resolve())
    assert main(["schema", "--out", str(out)]) == 0
    (out / "old.json").write_text("{}\n")
    assert schema_cli.stale_files(out) == ["old.json"]
    assert main(["schema", "--out", str(out)]) == 0
    assert not (out / "old.json").exists()


def test_an_out_that_cannot_be_written_is_one_line(tmp_path, capsys):
    (tmp_path / "a-file").write_text("")
    assert main(["schema", "--out", str(tmp_path / "a-file")]) == 2
    assert capsys.readouterr().err.strip() == (
        f"busgate schema: error: --out: {tmp_path / 'a-file'} is a file, not a folder")


# --- telemetry: states built by the drivers from decoded replies --------------------------------


def answered(driver: Driver, request, reply: tuple[object, ...], now: float) -> None:
    """As the runner does: the device answered, then its answer is applied."""
    driver.heard(now)
    driver.apply(request, reply, now)


def inspire_la_state() -> dict[str, Any]:
    driver = InspireLaDriver("la1", 3)
    [poll] = driver.poll()
    decoder = la.ReplyDecoder()
    decoder.feed(la.encode(la.StatusReply(3, target_raw=1003, position_raw=990, temperature_c=41,
                                          current_ma=120, force_g=-500, faults=la.Fault.STALL)))
    answered(driver, poll, tuple(decoder.events()), 1.0)
    return published(driver, 1.25)


def ds_reply(device_id: int, status: ds.ServoStatus, data: bytes = b"") -> tuple[object, ...]:
    decoder = ds.ReplyDecoder()
    decoder.feed(ds.encode(ds.StatusReply(device_id, status, data)))
    return tuple(decoder.events())


def ds_servo_driver() -> DsServoDriver:
    driver = DsServoDriver("arm", 1)
    first = bytearray(14)
    first[0:2] = (250).to_bytes(2, "big")
    first[0x38 - 0x2E : 0x3A - 0x2E] = (2047).to_bytes(2, "big")
    for request, data in zip(driver.poll(), [bytes(first), bytes([31])], strict=True):
        answered(driver, request, ds_reply(1, ds.ServoStatus.TEMPERATURE, data), 1.0)
    return driver


def rs232_state() -> dict[str, Any]:
    driver = Zlac706Rs232Driver("wheel", 1)
    for text in ('{"op":"set_mode","mode":"velocity"}',
                 '{"op":"set_velocity_ramp","accel_ms":500,"decel_ms":300}',
                 '{"op":"velocity","rpm":120.5}'):
        for request in driver.plan(driver.parse(text)):
            decoder = rs_codec.ReplyDecoder()
            decoder.feed(rs_codec.encode(rs_codec.Ack(request.frame.register)))
            answered(driver, request, tuple(decoder.events()), 0.5)
    [monitor] = driver.poll()
    decoder = rs_codec.ReplyDecoder()
    decoder.feed(bytes.fromhex(MANUAL_MONITOR))
    answered(driver, monitor, tuple(decoder.events()), 1.0)
    return published(driver, 1.0)


def can_state(heartbeats: bool) -> dict[str, Any]:
    driver = Zlac706CanDriver("wheel", 1, heartbeat_ms=100 if heartbeats else 0)
    if heartbeats:
        for data in ("00fe00200001e1e2", "00fe0021001e043f"):  # manual: position, current+speed
            decoder = can_codec.ReplyDecoder()
            decoder.feed(CanFrame(1, bytes.fromhex(data)))
            driver.unsolicited(next(iter(decoder.events())), 1.0)
    return published(driver, 1.0)


def telemetry_examples() -> list[dict[str, Any]]:
    return [inspire_la_state(), published(InspireLaDriver("la2", 4), 0.0),
            published(ds_servo_driver(), 2.0), published(DsServoDriver("arm2", 2), 0.0),
            rs232_state(), can_state(heartbeats=True), can_state(heartbeats=False)]


@pytest.mark.parametrize("state", telemetry_examples(), ids=lambda s: f"{s['kind']}-{s['device']}")
def test_real_states_match_their_kinds_telemetry_schema(state):
    assert_valid(f"telemetry.{state['kind']}.json", state)
    api.TELEMETRY_ADAPTER.validate_python(state)
    api.TELEMETRY_MODELS[state["kind"]].model_validate(state)


def test_the_examples_carry_measured_values_not_only_nulls():
    la_state, rs_state = inspire_la_state(), rs232_state()
    assert la_state["position"] == 990 and la_state["faults"] == ["stall"]
    assert rs_state["voltage_v"] == 28 and rs_state["velocity_ramp"] == {"accel_ms": 500,
                                                                         "decel_ms": 300}
    assert published(ds_servo_driver(), 2.0)["faults"] == ["temperature"]


def test_an_undocumented_or_missing_telemetry_key_is_refused():
    state = inspire_la_state()
    assert_invalid("telemetry.inspire_la.json", state | {"speed_rpm": 3.0})
    assert_invalid("telemetry.inspire_la.json", {k: v for k, v in state.items() if k != "stale"})
    assert_invalid("telemetry.inspire_la.json", state | {"faults": ["stalled"]})


# --- replies, events, info: from the gateway's own API -------------------------------------------


def gateway() -> tuple[GatewayApi, list[Any], DsServoDriver]:
    """The API over one DS bus whose runner is a stand-in holding real drivers and states."""
    arm, spare = ds_servo_driver(), DsServoDriver("arm2", 2)
    drivers = {"arm": arm, "arm2": spare}
    runner = SimpleNamespace(drivers=drivers, authority=Authority("uart0", drivers),
                             timing=SimpleNamespace(protocol="ds_servo"),
                             states={"arm": published(arm, 2.0)},
                             stop_stream=lambda device, reason: None)
    events: list[Any] = []
    return (GatewayApi("gw1", {"uart0": runner}, on_event=events.append),
            events, arm)


def reply(future) -> dict[str, Any]:
    return future.result(timeout=1)


def test_the_apis_replies_match_the_reply_schema():
    gw, _, arm = gateway()
    [read] = arm.plan(arm.parse('{"op":"read","address":56,"length":2}'))
    data = arm.apply(read, ds_reply(1, ds.ServoStatus(0), b"\x07\xff"), 2.0)
    found = scan_result("ds_servo", [
        (probe, ds_reply(1, ds.ServoStatus(0)) if i == 0 else None)
        for i, probe in enumerate(scan_requests("ds_servo", [1, 2]))
    ])
    replies = [
        ok_reply(**data, state=published(arm, 2.0)),
        reply(gw.command("arm", b'{"op":"claim","client":"ui-1","ttl_s":5}')),
        error_reply(RefusedError("claimed", "arm is claimed by 'ui-1'")),
        reply(gw.command("arm", b'{"op":"release","client":"ui-1"}')),
        reply(gw.command("arm", b'{"op":"end_follow","client":"ui-1"}')),
        reply(gw.command("nope", b"{}")),
        reply(gw.command("arm", b"\xff")),
        reply(gw.command("arm", b'{"op":"move"')),
        reply(gw.command("arm", b'{"op":"move","position":99999}')),
        reply(gw.command("arm", b'{"op":"fly"}')),
        reply(gw.command("arm", b" " * (70 * 1024))),
        ok_reply(found=found),
    ]
    assert [r.get("error", {}).get("code") for r in replies] == [
        None, None, "claimed", None, None, "unknown_device", "not_utf8", "not_json", "out_of_range",
        "bad_command", "too_large", None]
    assert found == [{"id": 1, "protocol": "ds_servo", "reply": "StatusReply"}]
    for answer in replies:
        assert_valid("reply.json", answer)
        api.REPLY_ADAPTER.validate_python(answer)


def test_an_unknown_error_code_is_refused():
    answer = error_reply(RuntimeError("boom"))
    assert_valid("reply.json", answer)
    assert_invalid("reply.json", answer | {"error": {"code": "oops", "message": "boom"}})


def test_an_error_message_is_cut_to_what_a_client_takes():
    """A 59 KB command of 6,000 unknown fields was refused with a message of 263 KB (every
    problem named): a message is cut to ``MAX_MESSAGE`` (``…``), which the reply schema holds
    every peer to."""
    gw, _, _ = gateway()
    extra = {f"x{i}": 1 for i in range(6000)}
    payload = json.dumps({"op": "move", "position": 1, **extra}, separators=(",", ":")).encode()
    answer = reply(gw.command("arm", payload))
    message = answer["error"]["message"]
    assert len(payload) < MAX_PAYLOAD and answer["error"]["code"] == "bad_command"
    assert len(message) == api.MAX_MESSAGE and message.endswith("x97: Extr…")
    assert_valid("reply.json", answer)
    api.REPLY_ADAPTER.validate_python(answer)
    longer = {"ok": False, "error": {"code": "busy", "message": "x" * (api.MAX_MESSAGE + 1)}}
    assert_invalid("reply.json", longer)
    with pytest.raises(ValidationError, match=f"at most {api.MAX_MESSAGE} characters"):
        api.REPLY_ADAPTER.validate_python(longer)


def test_info_matches_the_info_schema():
    gw, _, _ = gateway()
    info = gw.info()
    assert [d["state"] is None for d in info["buses"][0]["devices"]] == [False, True]
    assert_valid("info.json", info)
    api.InfoReply.model_validate(info)


def test_an_info_whose_state_names_another_device_is_refused():
    """A client took the state listed under ``la1`` as ``la1``'s whatever device it named; a
    gateway lists each device with its own."""
    gw, _, _ = gateway()
    info = gw.info()
    entry = info["buses"][0]["devices"][0]
    entry["state"]["device"] = "la2"
    with pytest.raises(ValidationError, match=f"the state of {entry['name']} .* names la2"):
        api.InfoReply.model_validate(info)


def test_a_version_past_what_a_client_takes_is_cut(monkeypatch):
    """A build's version is a few dozen characters; one past ``MAX_VERSION`` would make every
    client leave the gateway out: its info carries it cut (``…``)."""
    monkeypatch.setattr(commands, "installed_version", lambda: "1.0.0+" + "g" * 200)
    info = gateway()[0].info()
    assert info["version"] == ("1.0.0+" + "g" * 200)[: api.MAX_VERSION - 1] + "…"
    assert_valid("info.json", info)
    api.InfoReply.model_validate(info)


def event_body(event) -> dict[str, Any]:
    """An event as the bridge publishes it."""
    return {"ts": time.time(), "device": event.device, "type": event.type, **event.fields}


def test_events_from_drivers_and_the_api_match_the_event_schema():
    arm = ds_servo_driver()  # online, then a temperature fault
    for _ in range(OFFLINE_AFTER):
        arm.missed(3.0)
    [set_id] = arm.plan(arm.parse('{"op":"set_id","new_id":7}'))
    answered(arm, set_id, ds_reply(1, ds.ServoStatus(0)), 4.0)
    arm.rebooted("torque on again, its power-up value")
    events = arm.drain_events()
    gw, api_events, _ = gateway()
    reply(gw.command("arm", b'{"op":"claim","client":"ui-1"}'))
    reply(gw.command("arm", b'{"op":"release","client":"ui-1"}'))
    refused = reply(gw.command("arm", b'{"op":"move","position":-1}'))
    events += [*api_events, DeviceEvent("arm", "command_refused", refused["error"]),
               DeviceEvent("*", "estop", {"key": "busgate/gw1/estop"})]
    types = [event.type for event in events]
    assert types == ["online", "fault", "offline", "online", "fault", "id_changed", "rebooted",
                     "claimed", "released", "command_refused", "estop"]
    for event in events:
        assert_valid("event.json", event_body(event))
        EVENT_ADAPTER.validate_python(event_body(event))


# --- bus statistics, config ---------------------------------------------------------------------


def test_bus_stats_match_the_bus_stats_schema_and_name_every_counter():
    counters = BusCounters(started=0.0)
    counters.frames_out, counters.timeouts, counters.busy_s = 120, 2, 0.5
    counters.gap(0.0011)
    for interval in (0.0201, 0.0199, 0.0202):
        counters.follow_interval(interval, 0.02)
    for snapshot in (counters.snapshot(2.0), BusCounters(started=0.0).snapshot(1.0)):
        stats = {"ts": time.time(), "bus": "uart0", "up": True, **asdict(snapshot)}
        assert_valid("bus_stats.json", stats)
        api.BusStatistics.model_validate(stats)
    assert set(api.BusStatistics.model_fields) == (
        {f.name for f in fields(BusStats)} | {"ts", "bus", "up"})


@pytest.mark.parametrize("number", [math.nan, math.inf, -math.inf], ids=["nan", "inf", "-inf"])
def test_a_state_or_a_bus_statistic_that_is_not_finite_is_refused(number: float) -> None:
    """A gateway never publishes NaN or an infinity (its encoder would write one null): a
    peer's, in a state's values or a bus's statistics, is refused by the models a client reads
    them with, as in a joint."""
    counters = BusCounters(started=0.0)
    counters.gap(0.0011)
    stats = {"ts": time.time(), "bus": "uart0", "up": True, **asdict(counters.snapshot(2.0))}
    published = [(api.TELEMETRY_MODELS[state["kind"]], state)
                 for state in (inspire_la_state(), rs232_state(), can_state(heartbeats=True))]
    for model, valid in [*published, (api.BusStatistics, stats)]:
        model.model_validate(valid)
        floats = [name for name, value in valid.items() if type(value) is float]
        assert floats, model
        for name in floats:
            with pytest.raises(ValidationError, match="finite number"):
                model.model_validate_json(json.dumps({**valid, name: number}))


@pytest.mark.parametrize("path", sorted((ROOT / "deploy" / "config").glob("*.toml")),
                         ids=lambda p: p.name)
def test_the_example_configs_match_the_config_schema(path):
    data = tomllib.loads(path.read_text())
    assert_valid("config.json", data)
    Config.model_validate(data)


def test_a_config_with_an_unknown_key_is_refused():
    data = tomllib.loads((ROOT / "deploy" / "config" / "inspire_la.toml").read_text())
    assert_invalid("config.json", data | {"gatway": {"name": "x"}})


# --- commands ------------------------------------------------------------------------------------


GOOD_COMMANDS = {
    "inspire_la": ['{"op":"move","position":1000}', '{"op":"set_overtemp","temp_c":70.5}',
                   '{"op":"write","index":55,"data":"e803"}', '{"op":"claim","client":"ui-1"}'],
    "ds_servo": ['{"op":"move","position":2048,"time_ms":1000,"client":"c_2"}',
                 '{"op":"torque","on":false}', '{"op":"release","client":"ui-1"}',
                 '{"op":"end_follow"}'],
    "zlac706": ['{"op":"set_mode","mode":"velocity"}', '{"op":"velocity","rpm":-120.5}',
                '{"op":"write","register":25,"value":1}',
                '{"op":"claim","client":"ui-1","ttl_s":2.5}',
                '{"op":"end_follow","client":"ui-1"}'],
    "bus": ['{"op":"group_move","targets":[{"device":"s1","position":100,"time_ms":500}]}',
            '{"op":"scan"}', '{"op":"scan","ids":[1,2,3]}'],
    "trajectory": ['{"op":"play","id":"pick-1","devices":["la1","s1"],"start_at":1796150000.25,'
                   '"points":[{"t_s":0,"positions":[500,2048]},{"t_s":0.8,"positions":[1500,'
                   '3000],"velocities":[0,0]}],"path_tolerance":[100,200],"goal_time_s":0.5}',
                   '{"op":"play","id":"w","devices":["wheel"],"interpolation":"quintic",'
                   '"points":[{"t_s":1,"rpms":[-120.5],"accelerations":[10]}]}',
                   '{"op":"cancel","id":"pick-1","client":"arm-ctl"}', '{"op":"status"}'],
}
BAD_COMMANDS = {
    "inspire_la": ['{"op":"move","position":2001}', '{"op":"move","position":"5"}',
                   '{"op":"move","position":5,"speed":3}', '{"op":"claim"}'],
    "ds_servo": ['{"op":"torque","on":1}', '{"op":"move","position":1,"client":"a b"}',
                 '{"op":"end_follow","position":1}'],
    "zlac706": ['{"op":"set_mode","mode":"fast"}', '{"op":"write","value":1}',
                '{"op":"set_velocity_ramp","accel_ms":150,"decel_ms":0}',
                '{"op":"claim","client":"ui-1","ttl_s":0}'],
    "bus": ['{"op":"group_move","targets":[]}', '{"op":"scan","ids":[256]}', '{"op":"estop"}'],
    "trajectory": ['{"op":"play","id":"p","devices":["la1"],"points":[]}',
                   '{"op":"play","id":"p","devices":["la1"],"points":[{"t_s":-1,"positions":[1]}]}',
                   '{"op":"play","id":"p","devices":["la1"],"points":[{"t_s":0,"positions":[1.5]}]}',
                   '{"op":"play","id":"p","devices":["la1"],"points":[{"t_s":0,"positions":[1]}],'
                   '"interpolation":"spline"}',
                   '{"op":"cancel"}', '{"op":"status","id":"p"}'],
}
ADAPTERS = {**api.DEVICE_COMMAND_ADAPTERS, "bus": api.BUS_COMMAND_ADAPTER,
            "trajectory": trajectory.TRAJECTORY_COMMAND_ADAPTER}


@pytest.mark.parametrize(("kind", "text"),
                         [(k, t) for k, texts in GOOD_COMMANDS.items() for t in texts])
def test_good_commands_match_their_schema(kind, text):
    assert_valid(f"command.{kind}.json", json.loads(text))
    ADAPTERS[kind].validate_json(text)


@pytest.mark.parametrize(("kind", "text"),
                         [(k, t) for k, texts in BAD_COMMANDS.items() for t in texts])
def test_malformed_commands_are_refused_by_schema_and_model(kind, text):
    assert_invalid(f"command.{kind}.json", json.loads(text))
    with pytest.raises(ValueError):
        ADAPTERS[kind].validate_json(text)
