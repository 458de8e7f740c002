"""``busgate send`` and ``busgate watch`` against a stand-in gateway, over real zenoh sessions.

The stand-in answers on the contract's keys the way a gateway does (ok and error envelopes)
and publishes device states and bus statistics; the tools run through ``busgate``'s ``main``
as a user would run them. Everything stays on 127.0.0.1 with multicast scouting off.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest
import zenoh

from busgate.codecs import inspire_la
from busgate.gateway import cli
from busgate.gateway.cli import client as client_cli
from busgate.gateway.cli import main
from busgate.gateway.cli.watch_table import WatchTable
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.zenoh_session import session_config
from tests.conftest import silent_listener
from tests.gateway_process import (
    BUSGATE,
    GatewayProcess,
    run_busgate,
    serial_bus,
    write_config,
)

PUBLISH_EVERY_S = 0.05


def la1_state() -> dict:
    return {"ts": time.monotonic(), "device": "la1", "kind": "inspire_la", "online": True,
            "last_reply_age_s": 0.01, "stale": False, "estopped": False, "enabled": True,
            "position": 1000, "target": 1500,
            "temperature_c": 31, "current_ma": 120, "force_g": 10, "faults": [],
            "joint": {"name": "la1", "unit": "m", "position": 0.005, "velocity": None,
                      "effort": 0.098}}


def wheel_state() -> dict:
    return {"ts": time.monotonic(), "device": "wheel", "kind": "zlac706", "online": True,
            "stale": True, "estopped": True, "enabled": False, "mode": "velocity",
            "speed_rpm": 12.5, "target_speed_rpm": 20.0,
            "current_ma": 800, "faults": ["overvoltage"],
            "joint": {"name": "wheel", "unit": "rad", "position": 3.2, "velocity": 1.309,
                      "effort": 0.8}}


def ds1_state() -> dict:
    return {"ts": time.monotonic(), "device": "ds1", "kind": "ds_servo", "online": False,
            "stale": False, "position": None, "target": 2048, "faults": []}


def uart0_stats(uptime_s: float) -> dict:
    return {"ts": time.time(), "bus": "uart0", "frames_out": int(100 * uptime_s),
            "frames_in": int(100 * uptime_s), "timeouts": 3, "checksum_errors": 4,
            "reconnects": 1, "utilisation": 0.25,
            "smallest_gap_s": 0.0005, "uptime_s": uptime_s}


@dataclass
class StandIn:
    """A zenoh peer playing gateways ``gwtest`` and ``gwtwo``."""

    endpoint: str
    session: zenoh.Session
    commands: list[bytes] = field(default_factory=list)
    puts: list[tuple[str, bytes]] = field(default_factory=list)
    held: list = field(default_factory=list)


def answer_la1(stand_in: StandIn, query: zenoh.Query) -> None:
    with query:
        raw = query.payload.to_bytes() if query.payload is not None else b""
        stand_in.commands.append(raw)
        try:
            command = json.loads(raw)
        except ValueError:
            reply = {"ok": False, "error": {"code": "not_json", "message": "not JSON"}}
        else:
            if command.get("op") == "move" and 0 <= command.get("position", -1) <= 2000:
                reply = {"ok": True, "state": {**la1_state(), "target": command["position"]}}
            else:
                reply = {"ok": False, "error": {"code": "out_of_range",
                                                "message": "position must be 0–2000"}}
        query.reply(query.key_expr, json.dumps(reply))


def answer_unknown(query: zenoh.Query) -> None:
    """What a gateway without the device says when a get names every gateway."""
    with query:
        device = str(query.key_expr).split("/")[-2]
        query.reply(query.key_expr, json.dumps({"ok": False, "error": {
            "code": "unknown_device", "message": f"no device {device!r} on gateway gwtwo"}}))


def answer_info(gateway: str, protocol: str, devices: dict[str, int]):
    """What gateway ``gateway`` answers ``info``: one bus of ``protocol`` with ``devices``
    (name: id), none read yet. ``send`` asks it first for a bare device name."""
    kind = {"inspire_la": "inspire_la", "ds_servo": "ds_servo"}[protocol]
    body = json.dumps({"ok": True, "gateway": gateway, "version": "9", "buses": [{
        "name": "bus0", "protocol": protocol, "devices": [
            {"name": name, "kind": kind, "id": device_id, "state": None}
            for name, device_id in devices.items()]}]})

    def answer(query: zenoh.Query) -> None:
        time.sleep(0.05)
        with query:
            query.reply(f"busgate/{gateway}/info", body)

    return answer


def answer_ok(query: zenoh.Query) -> None:
    with query:
        query.reply(query.key_expr, json.dumps({"ok": True, "data": {"ids": [1, 2]}}))


def publish_forever(session: zenoh.Session, stop: threading.Event) -> None:
    started = time.monotonic()
    while not stop.wait(PUBLISH_EVERY_S):
        session.put("busgate/gwtest/dev/la1/state", json.dumps(la1_state()))
        session.put("busgate/gwtest/dev/wheel/state", json.dumps(wheel_state()))
        session.put("busgate/gwtwo/dev/ds1/state", json.dumps(ds1_state()))
        session.put("busgate/gwtest/bus/uart0/stats",
                    json.dumps(uart0_stats(1.0 + time.monotonic() - started)))
        # Puts on wildcards reach every subscriber of states and stats: no row, no error.
        session.put("busgate/**/state", json.dumps(la1_state()))
        session.put("busgate/*/bus/*/stats", json.dumps(uart0_stats(1.0)))


@contextlib.contextmanager
def stand_in_peer(free_port, *, info: bool) -> Iterator[StandIn]:
    """A zenoh peer playing gateways ``gwtest`` and ``gwtwo``: their commands and states, and
    with ``info`` their ``info`` (answered 50 ms late, as a busy gateway's)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(session_config(mode="peer", listen=[endpoint]))
    stand_in = StandIn(endpoint, session)
    stop = threading.Event()
    publisher = threading.Thread(target=publish_forever, args=(session, stop), daemon=True)
    try:
        if info:
            stand_in.held += [
                session.declare_queryable("busgate/gwtest/info", answer_info(
                    "gwtest", "inspire_la", {"la1": 1, "both": 2, "mute": 3})),
                session.declare_queryable("busgate/gwtwo/info", answer_info(
                    "gwtwo", "ds_servo", {"both": 2, "ds1": 1})),
            ]
        stand_in.held += [
            *(session.liveliness().declare_token(f"busgate/{gateway}/alive")
              for gateway in ("gwtest", "gwtwo")),
            session.declare_queryable("busgate/gwtest/dev/la1/cmd",
                                      lambda query: answer_la1(stand_in, query)),
            session.declare_queryable("busgate/gwtest/bus/uart0/cmd", answer_ok),
            session.declare_queryable("busgate/gwtest/dev/both/cmd", answer_ok),
            session.declare_queryable("busgate/gwtwo/dev/both/cmd", answer_ok),
            session.declare_queryable("busgate/gwtest/dev/mute/cmd", stand_in.held.append),
            session.declare_queryable("busgate/gwtwo/dev/*/cmd", answer_unknown),
            *(session.declare_subscriber(key, lambda sample: stand_in.puts.append(
                (str(sample.key_expr), sample.payload.to_bytes())))
              for key in ("busgate/*/dev/*/cmd", "busgate/*/estop")),
        ]
        publisher.start()
        yield stand_in
    finally:
        stop.set()
        if publisher.is_alive():
            publisher.join()
        for held in stand_in.held:
            if isinstance(held, zenoh.Query):
                held.drop()
        session.close()


@pytest.fixture
def stand_in(free_port) -> Iterator[StandIn]:
    """The stand-in gateways, ``info`` and all: a bare name is looked up there first."""
    with stand_in_peer(free_port, info=True) as peer:
        yield peer


@pytest.fixture
def states_only(free_port) -> Iterator[StandIn]:
    """The stand-in gateways without ``info``: what ``watch`` shows of states alone."""
    with stand_in_peer(free_port, info=False) as peer:
        yield peer


@pytest.fixture
def gateway(free_port, tmp_path) -> Iterator[str]:
    """``busgate run``, gateway ``gw1`` with actuator ``la1`` on a simulator; its endpoint."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with SerialSimulator(inspire_la, [InspireLaDevice(1)], baudrate=921_600) as simulator:
        process = GatewayProcess(write_config(tmp_path / "gw.toml", endpoint,
                                              serial_bus("uart0", simulator.port, "la1")))
        try:
            process.wait_for(" serving ")
            yield endpoint
        finally:
            process.stop()


# -- send -----------------------------------------------------------------------------------


def test_send_prints_an_ok_reply_and_exits_0(stand_in, capsys):
    status = main(["send", "la1", '{"op":"move","position":1200}', "--connect", stand_in.endpoint])
    out, err = capsys.readouterr()
    assert status == 0, err
    reply = json.loads(out)
    assert reply["ok"] is True and reply["state"]["target"] == 1200
    assert stand_in.commands == [b'{"op":"move","position":1200}']
    assert "\n  " not in out.strip()  # one compact line without --pretty


def test_send_pretty_indents(stand_in, capsys):
    status = main(["send", "la1", '{"op":"move","position":5}', "--pretty",
                   "--connect", stand_in.endpoint])
    out, _ = capsys.readouterr()
    assert status == 0
    assert out.startswith('{\n  "ok": true')


def test_an_error_reply_exits_1_with_its_code_and_message_on_stderr(stand_in, capsys):
    status = main(["send", "la1", '{"op":"move","position":9999}', "--connect", stand_in.endpoint])
    out, err = capsys.readouterr()
    assert status == 1
    assert json.loads(out)["error"]["code"] == "out_of_range"
    assert err.strip() == "busgate send: out_of_range: position must be 0–2000"


def test_the_payload_goes_as_given_so_the_gateway_judges_bad_json(stand_in, capsys):
    status = main(["send", "la1", "{not json", "--connect", stand_in.endpoint])
    _, err = capsys.readouterr()
    assert status == 1
    assert "not_json" in err
    assert stand_in.commands == [b"{not json"]


def test_a_bare_name_goes_to_the_one_gateway_that_has_it_and_nowhere_when_none_does(
    stand_in, capsys
):
    # gwtwo answers unknown_device for every device, la1 included: it is never asked.
    assert main(["send", "la1", '{"op":"move","position":7}',
                 "--connect", stand_in.endpoint]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["ok"] is True and err == ""

    assert main(["send", "la9", "{}", "--connect", stand_in.endpoint]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err.strip() == ("busgate send: unknown_device: no device 'la9' on the gateways that "
                           "answered (gwtest, gwtwo; did you mean 'la1'?): nothing was sent")
    assert stand_in.commands == [b'{"op":"move","position":7}']

    # Named by key, a gateway's refusal counts like any other error.
    assert main(["send", "busgate/*/dev/la1/cmd", '{"op":"move","position":7}',
                 "--connect", stand_in.endpoint]) == 1
    out, _ = capsys.readouterr()
    assert len(out.splitlines()) == 2


def test_nobody_answering_exits_2_naming_the_selector_and_no_wait_it_did_not_do(stand_in,
                                                                                capsys):
    # No queryable matches: zenoh ends the get at once, so no wait may be claimed; and it
    # says what that may be, as the SDK says it (a viewer's command was "nobody answered").
    status = main(["send", "busgate/gwtest/dev/la9/cmd", '{"op":"stop"}', "--timeout", "5",
                   "--connect", stand_in.endpoint])
    out, err = capsys.readouterr()
    assert status == 2
    assert out == ""
    assert err.strip() == ("busgate send: nobody answered on busgate/gwtest/dev/la9/cmd: "
                           "nothing there took the query (no such gateway or device, or the "
                           "access rules keep this account from it), or its gateway went "
                           "before it answered (then it may have been carried out: see the "
                           "device's state)")


@pytest.mark.parametrize("key", ["busgate/gwtest/estop", "busgate/gwtest/estop/reset",
                                 "busgate/gwtest/dev/la1/follow"])
def test_a_get_on_a_key_that_takes_puts_says_nothing_was_done(stand_in, capsys, key):
    """A tired operator's e-stop without --put: the line says the key takes puts, so that
    "nobody answered" is not read as "the gateway is down" (nor as "stopped")."""
    assert main(["send", key, "{}", "--connect", stand_in.endpoint]) == 2
    _, err = capsys.readouterr()
    assert err.strip() == (f"busgate send: nobody answered on {key}: {key} takes puts, not gets:"
                           " nothing was done (send --put)")


def test_a_device_no_gateway_has_is_unknown_device_naming_the_gateways(gateway, capsys):
    # A real gateway leaves a fleet-wide command for a device it lacks unanswered; its info
    # reply tells it is there.
    status = main(["send", "la9", '{"op":"status"}', "--connect", gateway])
    out, err = capsys.readouterr()
    assert (status, out) == (1, "")
    assert err.strip() == ("busgate send: unknown_device: no device 'la9' on the gateways that "
                           "answered (gw1; did you mean 'la1'?): nothing was sent")
    assert main(["send", "la1", '{"op":"status"}', "--connect", gateway]) == 0


def test_a_device_the_named_gateway_lacks_is_unknown_device_from_that_gateway(module_demo,
                                                                              capsys):
    # <gateway>/<device>, as the SDK names a device on one gateway: that gateway answers.
    status = main(["send", "demo/la9", '{"op":"status"}', "--connect", module_demo.endpoint])
    out, err = capsys.readouterr()
    assert (status, json.loads(out)["error"]["code"]) == (1, "unknown_device")
    assert err == "busgate send: unknown_device: no device 'la9' on gateway demo\n"
    assert main(["send", "demo/la1", '{"op":"status"}', "--connect", module_demo.endpoint]) == 0


def test_a_misspelt_op_is_one_line_whether_got_or_put(module_demo, wait_for, capsys):
    line = "unknown op `mvoe` for inspire_la (did you mean `move`?)"
    send = ["send", "demo/la1", '{"op":"mvoe","position":5}', "--connect", module_demo.endpoint]
    assert main(send) == 1
    out, err = capsys.readouterr()
    assert json.loads(out)["error"] == {"code": "bad_command", "message": line}
    assert err == f"busgate send: bad_command: {line}\n"

    refused: list[dict] = []
    with zenoh.open(session_config(mode="client", connect=[module_demo.endpoint])) as session:
        session.declare_subscriber("busgate/demo/events", lambda sample: refused.append(
            json.loads(sample.payload.to_bytes())))

        def put_refused() -> bool:  # put until the subscription has reached the gateway
            assert main([*send, "--put"]) == 0
            return any(event["type"] == "command_refused" for event in refused)

        wait_for(put_refused, timeout=10)
    assert {(e["code"], e["message"]) for e in refused if e["type"] == "command_refused"} == {
        ("bad_command", line)}


def test_a_gateway_that_never_answers_in_time_counts_as_nobody(stand_in, capsys):
    started = time.monotonic()
    status = main(["send", "busgate/gwtest/dev/mute/cmd", '{"op":"stop"}', "--timeout", "0.3",
                   "--connect", stand_in.endpoint])
    _, err = capsys.readouterr()
    assert status == 2
    assert "nobody answered on busgate/gwtest/dev/mute/cmd within 0.3 s" in err
    assert time.monotonic() - started >= 0.3


def test_an_argument_with_a_slash_is_the_key_expression(stand_in, capsys):
    status = main(["send", "busgate/gwtest/bus/uart0/cmd", '{"op":"scan"}',
                   "--connect", stand_in.endpoint])
    out, _ = capsys.readouterr()
    assert status == 0
    assert json.loads(out) == {"ok": True, "data": {"ids": [1, 2]}}


def test_a_bare_name_two_gateways_have_is_refused_naming_them(stand_in, capsys):
    status = main(["send", "both", '{"op":"read"}', "--connect", stand_in.endpoint])
    out, err = capsys.readouterr()
    assert (status, out) == (2, "")
    assert err.strip() == ("busgate send: error: 2 gateways have a device 'both' (gwtest, "
                           "gwtwo): name one, e.g. gwtest/both; nothing was sent")


@pytest.mark.parametrize("target", ["*", "la*", "**", "", "la 1"])
def test_a_bare_target_that_is_no_device_name_is_refused_before_any_session(target, capsys):
    """A bare ``*`` was taken as a device's name and looked up in every gateway's info, to be
    answered ``unknown_device``: it is refused as no name, with where a key expression goes,
    before any session (the endpoint here has nobody listening)."""
    assert main(["send", target, "{}", "--connect", "tcp/127.0.0.1:9"]) == 2
    _, err = capsys.readouterr()
    assert err == (f"busgate send: error: not a device name: {target!r} (1-64 of A-Z a-z 0-9 _ -); "
                   "a target with a '/' is a key expression, taken as given (e.g. "
                   "busgate/*/dev/*/cmd)\n")


@pytest.mark.parametrize("selector", ["la 1", "gw.1", "x" * 65])
def test_a_watch_selector_that_is_no_gateway_name_is_refused_before_any_session(selector,
                                                                              capsys):
    """``watch --once 'la 1'`` watched a gateway no config can name, and said nothing was
    seen; a pattern of names (``robot*``) is still a selector."""
    assert main(["watch", "--once", selector, "--connect", "tcp/127.0.0.1:9"]) == 2
    assert capsys.readouterr().err == (
        f"busgate watch: error: not a gateway name: {selector[:80]!r} (1-64 of A-Z a-z 0-9 _ -); "
        "a selector with a '/' is a key expression, taken as given (e.g. "
        "busgate/*/dev/la1/state)\n")


@pytest.mark.parametrize("selector", ["$*", "robot*", "a**"])
def test_a_watch_pattern_zenoh_refuses_is_told_as_typed(selector, capsys):
    """``watch '$*'`` was refused naming ``busgate/$*/**``, a key the user never wrote (an
    audit); ``**`` is every gateway, as no selector is."""
    assert main(["watch", "--once", selector, "--connect", "tcp/127.0.0.1:9"]) == 2
    assert capsys.readouterr().err == (
        f"busgate watch: error: {selector} is no gateway name or pattern of names: * alone, or "
        "zenoh's $* within a name (robot$*)\n")


def test_a_watch_of_every_gateway_may_say_so_with_two_stars() -> None:
    assert client_cli.watch_keys("busgate", "**") == client_cli.watch_keys("busgate", None)


@pytest.mark.parametrize("argv", [["send", "la1", "\udcff"], ["send", "la\udcff", "{}"],
                                  ["watch", "--once", "\udcff"]])
def test_an_argument_that_is_no_utf8_is_one_line_and_exit_2(argv, capsys):
    """A byte that is no UTF-8 on the command line raised a UnicodeEncodeError traceback."""
    assert main(argv) == 2
    _, err = capsys.readouterr()
    assert err.endswith("is not UTF-8 text (the byte 0xff): nothing was done\n")
    assert len(err.splitlines()) == 1


def test_a_path_may_be_any_bytes(tmp_path):
    """Only names, keys and commands must be UTF-8: a config file's name is the system's
    (``gateway-\xe9.toml`` was refused as no UTF-8 text)."""
    path = write_config(tmp_path / "gateway-\udce9.toml", "tcp/127.0.0.1:7447",  # byte 0xe9
                        serial_bus("uart0", str(tmp_path / "ttyUSB0"), "la1"))  # missing here
    done = run_busgate("check-config", str(path), errors="backslashreplace")
    assert done.returncode == 0, done.stderr


def test_another_prefix_changes_the_selector(stand_in, capsys):
    status = main(["send", "la1", "{}", "--prefix", "other", "--timeout", "0.3",
                   "--connect", stand_in.endpoint])
    _, err = capsys.readouterr()
    assert status == 2
    assert err.strip() == ("busgate send: no gateway answered on other/*/info within 0.3 s: "
                           "nothing was sent to other/*/dev/la1/cmd")


@pytest.mark.parametrize("put", [False, True])
def test_a_bare_name_no_gateway_answers_for_in_time_is_sent_nowhere(stand_in, capsys, put):
    """With a timeout too short for any gateway's info, the command went to every gateway's
    key, and each gateway with the device carried it out (two robots' la1 moved, while
    ``send`` said nobody answered)."""
    status = main(["send", "la1", '{"op":"move","position":1001}', "--timeout", "0.001",
                   *(["--put"] if put else []), "--connect", stand_in.endpoint])
    _, err = capsys.readouterr()
    assert status == 2
    assert err.strip() == ("busgate send: no gateway answered on busgate/*/info within 0.001 s:"
                           " nothing was sent to busgate/*/dev/la1/cmd")
    time.sleep(0.3)
    assert stand_in.commands == [] and stand_in.puts == []


def test_put_is_fire_and_forget(stand_in, capsys):
    status = main(["send", "la1", '{"op":"stop"}', "--put", "--connect", stand_in.endpoint])
    out, _ = capsys.readouterr()
    assert status == 0
    assert out == ""
    deadline = time.monotonic() + 2
    while not stand_in.puts and time.monotonic() < deadline:
        time.sleep(0.01)
    assert stand_in.puts == [("busgate/gwtest/dev/la1/cmd", b'{"op":"stop"}')]
    assert stand_in.commands == []  # no query reached the queryable


@pytest.mark.parametrize(("command", "why"), [
    ("{op:stop}", "payload is not JSON: Expecting property name enclosed in double quotes"),
    ("[" * 100_000, "payload of 100000 bytes; at most 65536"),
    ("[" * 3000 + "]" * 3000, "payload is nested too deeply"),
    # What plain JSON takes and the gateway does not: sent, it was refused as an event.
    ('{"op":"move","position":NaN}', "payload is not JSON: NaN is not a number JSON allows"),
    ('{"op":"move","op":"stop"}', "key 'op' appears twice: a command is never guessed"),
    ("[1]", "a command is a JSON object"),
])
def test_a_put_that_is_not_json_is_refused_here_and_nothing_is_sent(stand_in, capsys, command,
                                                                    why):
    status = main(["send", "la1", command, "--put", "--connect", stand_in.endpoint])
    _, err = capsys.readouterr()
    assert status == 2
    assert err.startswith(f"busgate send: the command is not JSON the gateway takes ({why}")
    assert err.endswith("): nothing was sent\n")
    assert main(["send", "la1", "", "--put", "--connect", stand_in.endpoint]) == 0  # as an e-stop
    deadline = time.monotonic() + 2
    while not stand_in.puts and time.monotonic() < deadline:
        time.sleep(0.01)
    assert stand_in.puts == [("busgate/gwtest/dev/la1/cmd", b"")]  # the empty one, not the other


def test_an_estop_put_goes_whatever_it_carries(stand_in, capsys):
    """The gateway's e-stop takes any payload: the tool never holds one back as no JSON, on
    any key that reaches an e-stop; a reset's is judged."""
    for key in ("busgate/gwtest/estop", "busgate/gwtest/estop/**"):
        assert main(["send", key, "stop!", "--put", "--connect", stand_in.endpoint]) == 0
    assert main(["send", "busgate/gwtest/estop/reset", "stop!", "--put",
                 "--connect", stand_in.endpoint]) == 2
    deadline = time.monotonic() + 2
    while len(stand_in.puts) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert sorted(stand_in.puts) == [("busgate/gwtest/estop", b"stop!"),
                                     ("busgate/gwtest/estop/**", b"stop!")]


def test_ctrl_c_while_the_command_loads_is_one_line_too(monkeypatch, capsys):
    """The command's module (zenoh, pydantic) takes some 0.5 s to load: a Ctrl-C then was a
    traceback."""
    def loading(command):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "build_parser", loading)
    assert main(["send", "la1", "{}"]) == 130
    assert capsys.readouterr().err == "busgate send: stopped (Ctrl-C)\n"


def test_a_put_that_reaches_no_gateway_says_so_and_exits_2(stand_in, capsys):
    """An e-stop put on a misspelt gateway went, reached nobody, and ended with exit 0 and no
    word, as one carried out does."""
    status = main(["send", "--put", "busgate/gwtset/estop", "", "--timeout", "0.5",
                   "--connect", stand_in.endpoint])
    _, err = capsys.readouterr()
    assert (status, err) == (2, "busgate send: no gateway under busgate/gwtset/estop is up "
                                "(none seen within 0.5 s): the put reached nobody\n")
    assert main(["send", "--put", "busgate/*/estop", "", "--connect", stand_in.endpoint]) == 0


def test_nothing_listening_is_one_line_and_exit_2(free_port, capsys):
    status = main(["send", "la1", "{}", "--connect", f"tcp/127.0.0.1:{free_port()}"])
    out, err = capsys.readouterr()
    assert status == 2
    assert out == ""
    assert err.startswith("busgate send: error: cannot open a zenoh session to tcp/127.0.0.1:")
    assert "(is a gateway listening there? `busgate demo` listens on tcp/127.0.0.1:7447" in err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("endpoint", ["foo/bar", " tcp/127.0.0.1:7447"])
def test_an_endpoint_that_is_none_says_so_not_that_nobody_listens(endpoint, capsys):
    """A protocol busgate knows no link of, a space before it: the line asked "is a gateway
    listening there?", as for a gateway not started."""
    assert main(["send", "la1", "{}", "--connect", endpoint]) == 2
    err = capsys.readouterr().err
    assert f"({endpoint!r} is no endpoint: protocol/address, its protocol one of tcp," in err
    assert "listening there" not in err and len(err.splitlines()) == 1


def test_ctrl_c_while_the_session_opens_ends_the_tool_at_once_in_one_line():
    """An endpoint that takes the connection and never answers holds zenoh's opening for its
    connect timeout (some 10 s): a Ctrl-C then waited all of it and printed a traceback."""
    with silent_listener() as (mute, endpoint):
        send = subprocess.Popen([*BUSGATE, "send", "la1", "{}", "--connect", endpoint],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            held, _ = mute.accept()  # the tool is in the opening now
            with held:
                send.send_signal(signal.SIGINT)
                out, err = send.communicate(timeout=5.0)  # not zenoh's 10 s
        finally:
            send.kill()
            send.wait()
    assert (send.returncode, out, err) == (130, "", "busgate send: stopped (Ctrl-C)\n")


@pytest.mark.parametrize(("options", "hint"), [
    (["--ca", "CA"], "(nobody listening there, or a gateway that takes accounts refusing a "
                     "session without one: username=, --user)"),
    (["--user", "op"], "(a tls/ endpoint needs the CA that signed the gateway's certificate: "
                       "ca=, --ca)"),
])
def test_a_tls_session_that_cannot_open_says_what_it_lacks_not_that_nobody_listens(
        options, hint, tmp_path, free_port, capsys, monkeypatch):
    """With a CA and no user the tool said "is a gateway listening there?", and with a user
    and no CA it blamed the password."""
    ca = tmp_path / "ca.pem"
    ca.write_text("-----BEGIN CERTIFICATE-----\nMIIB\n-----END CERTIFICATE-----\n")
    monkeypatch.setenv("BUSGATE_PASSWORD", "secret")
    options = [str(ca) if option == "CA" else option for option in options]
    endpoint = f"tls/127.0.0.1:{free_port()}"
    assert main(["send", "la1", "{}", "--connect", endpoint, *options]) == 2
    _, err = capsys.readouterr()
    assert err.startswith(f"busgate send: error: cannot open a zenoh session to {endpoint}: ")
    assert err.endswith(f"{hint}\n") and "listening there?" not in err


def test_a_password_file_that_cannot_be_one_is_one_line_and_exit_2(tmp_path, free_port,
                                                                   capsys):
    """``/dev/zero`` was read without end (5.5 GB in 4 s), a byte that is no UTF-8 raised a
    UnicodeDecodeError traceback."""
    binary, big = tmp_path / "binary", tmp_path / "big"
    binary.write_bytes(b"pw\xff\n")
    big.write_text("x" * 4097)
    for path, reason in (("/dev/zero", "/dev/zero is over 4 KiB: not a password file"),
                         (binary, f"{binary} is not UTF-8 text (line 1 has the byte 0xff): save "
                                  "it as UTF-8"),
                         (big, f"{big} is over 4 KiB: not a password file"),
                         (tmp_path, f"cannot read {tmp_path}: Is a directory")):
        status = main(["send", "la1", "{}", "--user", "operator", "--password-file", str(path),
                       "--connect", f"tcp/127.0.0.1:{free_port()}"])
        _, err = capsys.readouterr()
        assert (status, err) == (2, f"busgate send: error: --password-file: {reason}\n")
    # a file without a user, an empty user or an empty file failed as nobody answering
    empty = tmp_path / "empty"
    empty.write_text(" \n")
    for options, reason in (
            (["--password-file", str(big)], "--password-file needs --user: the account it is "
                                            "the password of"),
            (["--user", " "], "--user names an account, not an empty string"),
            (["--user", "operator", "--password-file", str(empty)],
             f"--password-file: {empty} holds no password")):
        status = main(["send", "la1", "{}", *options, "--connect",
                       f"tcp/127.0.0.1:{free_port()}"])
        _, err = capsys.readouterr()
        assert (status, err) == (2, f"busgate send: error: {reason}\n")


@pytest.mark.parametrize(("command", "message"), [
    (["send", "busgate/gw1//cmd", "{}"], "not a key expression: 'busgate/gw1//cmd' (Invalid"),
    (["send", "busgate/gw1/dev/" + "x" * 70_000 + "/cmd", "{}"], "a key expression of 70020"),
    (["watch", "busgate/#", "--once"], "not a key expression: 'busgate/#'"),
])
def test_a_key_zenoh_would_refuse_is_one_line_and_exit_2(command, message, free_port, capsys):
    """Refused before any session opens (zenoh would raise, or panic past 64 KiB), with
    zenoh's reason and without its Rust source path."""
    status = main([*command, "--connect", f"tcp/127.0.0.1:{free_port()}"])
    _, err = capsys.readouterr()
    assert status == 2
    assert err.startswith(f"busgate {command[0]}: error: {message}"), err[:300]
    assert len(err.strip().splitlines()) == 1 and ".rs:" not in err


# -- watch ----------------------------------------------------------------------------------


def test_watch_once_shows_every_device_and_bus(states_only, capsys, caplog):
    status = main(["watch", "--once", "--seconds", "0.8", "--connect", states_only.endpoint])
    out, _ = capsys.readouterr()
    assert status == 0
    assert not [r for r in caplog.records if "failed its subscriber" in r.getMessage()]
    lines = out.splitlines()
    assert lines[0].split() == ["GATEWAY", "DEVICE", "KIND", "ONLINE", "STALE", "POWER",
                                "JOINT", "MOTION", "TEMP_C", "CURRENT_MA", "FAULTS", "AGE"]
    rows = {line.split()[1]: line.split() for line in lines[1:4]}
    assert rows["la1"][:12] == ["gwtest", "la1", "inspire_la", "yes", "-", "enabled", "0.005",
                                "m", "1000", "->", "1500", "31"]
    assert rows["wheel"][:14] == ["gwtest", "wheel", "zlac706", "yes", "STALE", "e-stopped",
                                  "1.309", "rad/s", "12.5", "rpm", "->", "20.0", "-", "800"]
    assert "overvoltage" in rows["wheel"]
    assert rows["ds1"][:7] == ["gwtwo", "ds1", "ds_servo", "NO", "-", "-", "-"]
    assert lines[5].split() == ["GATEWAY", "BUS", "UTILISATION", "FRAMES_S", "TIMEOUTS",
                                "CHECKSUM_ERRORS", "RECONNECTS", "SMALLEST_GAP", "AGE"]
    bus = next(line for line in lines if line.startswith("gwtest") and "uart0" in line).split()
    assert bus[:3] == ["gwtest", "uart0", "25%"]
    assert bus[4:9] == ["3", "4", "1", "0.50", "ms"]
    assert 150 < float(bus[3]) < 250  # frames/s between samples: 2 × 100 per second of uptime


def test_watch_narrows_to_one_gateway(states_only, capsys):
    status = main(["watch", "gwtwo", "--once", "--seconds", "0.5",
                   "--connect", states_only.endpoint])
    out, _ = capsys.readouterr()
    assert status == 0
    assert "ds1" in out and "la1" not in out and "uart0" not in out
    assert "(no bus seen)" in out
    assert not out.startswith("GATEWAY")  # one gateway: no gateway column


def test_watch_narrows_to_a_key_expression(states_only, capsys):
    status = main(["watch", "busgate/gwtest/dev/la1/**", "--once", "--seconds", "0.5",
                   "--connect", states_only.endpoint])
    out, _ = capsys.readouterr()
    assert status == 0
    device_rows = [line for line in out.splitlines()[1:] if line and not line.startswith("(")]
    assert [row.split()[0] for row in device_rows] == ["la1"]


def test_watch_once_with_nothing_seen_exits_1(states_only, capsys):
    status = main(["watch", "nobody", "--once", "--seconds", "0.3",
                   "--connect", states_only.endpoint])
    out, err = capsys.readouterr()
    assert status == 1
    assert "(no device seen)" in out
    assert "nothing seen on busgate/nobody/**" in err


def test_watch_once_of_a_misspelt_gateway_names_the_gateways_that_answer(stand_in, capsys):
    assert main(["watch", "gwtset", "--once", "--seconds", "0.3",
                 "--connect", stand_in.endpoint]) == 1
    assert capsys.readouterr().err == ("busgate watch: nothing seen on busgate/gwtset/** in 0.3 s "
                                       "(the gateways that answer: gwtest, gwtwo)\n")


def test_watch_without_a_tty_prints_one_line_per_updated_row(states_only, capsys):
    status = main(["watch", "gwtest", "--seconds", "0.7", "--connect", states_only.endpoint])
    out, _ = capsys.readouterr()
    assert status == 0
    lines = out.splitlines()
    assert "\x1b" not in out
    la1 = [line for line in lines if "device=la1 " in line]
    assert len(la1) >= 2  # once per refresh while it keeps publishing, not once per sample
    assert len(la1) <= 0.7 * client_cli.REDRAW_HZ + 1
    assert ("gateway=gwtest device=la1 kind=inspire_la online=yes stale=- power=enabled "
            "joint=0.005m motion=1000->1500") in la1[0]
    assert any("bus=uart0 utilisation=25%" in line for line in lines)


def test_watch_on_a_tty_redraws_in_place(states_only):
    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    table = WatchTable()
    table.update_state("busgate/gwtest/dev/la1/state", la1_state(), time.monotonic())
    terminal = Terminal()
    client_cli._wait_showing_live(table, terminal, 0.5)
    screens = terminal.getvalue().split("\x1b[H")[1:]
    assert 1 <= len(screens) <= 0.5 * client_cli.REDRAW_HZ + 1
    assert all(screen.endswith("\x1b[J") and "la1" in screen for screen in screens)


def test_ctrl_c_ends_a_live_watch_with_status_0(states_only):
    watch = subprocess.Popen(
        [sys.executable, "-m", "busgate.gateway.cli", "watch", "--connect", states_only.endpoint],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        first = watch.stdout.readline()
        assert "gateway=gw" in first
        watch.send_signal(signal.SIGINT)
        assert watch.wait(timeout=30) == 0, watch.stderr.read()  # a hang guard only
        assert "Traceback" not in watch.stderr.read()
    finally:
        if watch.poll() is None:
            watch.kill()
            watch.wait()


# -- the pieces -----------------------------------------------------------------------------


def test_frames_per_second_come_from_consecutive_statistics():
    table = WatchTable()
    table.update_stats("p/gw/bus/can0/stats", uart0_stats(2.0), 10.0)
    table.update_stats("p/gw/bus/can0/stats", uart0_stats(4.0), 12.0)
    line = table.render(12.5)[-1].split()
    assert line[:3] == ["can0", "25%", "200.0"]
    assert line[-1] == "0.5s"


def test_age_is_of_the_reading_and_power_says_e_stopped_first():
    """AGE: the device's last reply as of the state's arrival, plus the time since; a state
    that repeats a reading does not make it young."""
    table = WatchTable()
    state = {**la1_state(), "last_reply_age_s": 2.0, "estopped": True, "enabled": True}
    table.update_state("p/gw/dev/la1/state", state, 10.0)
    cells = table.render(10.5)[1].split()
    assert cells[4] == "e-stopped" and cells[-1] == "2.5s"


def test_info_seeds_rows_for_devices_not_heard_from_yet():
    table = WatchTable()
    info = {"ok": True, "gateway": "gw1", "version": "0.1.0", "buses": [
        {"name": "uart0", "protocol": "inspire_la", "devices": [
            {"name": "la1", "kind": "inspire_la", "id": 1, "state": {"online": False}},
            {"name": "la2", "kind": "inspire_la", "id": 2, "state": None}]}]}
    table.seed(info, lambda key: "la2" not in key)
    lines = table.render(0.0)
    assert lines[1].split() == ["la1", "inspire_la", "NO", "-", "-", "-", "-", "-", "-", "-",
                                "-"]
    assert lines[2] == ""
    assert lines[4].split() == ["uart0", "-", "-", "-", "-", "-", "-", "-"]


def test_session_config_lays_busgate_settings_over_a_zenoh_file(tmp_path):
    zenoh_file = tmp_path / "zenoh.json5"
    zenoh_file.write_text('{ listen: { endpoints: ["tcp/127.0.0.1:7001"] }, scouting: '
                          '{ multicast: { enabled: true } }, queries_default_timeout: 1234, '
                          'transport: { shared_memory: { enabled: true } } }')
    config = session_config(mode="client", connect=["tcp/127.0.0.1:7002"], config_file=zenoh_file)
    assert json.loads(config.get_json("mode")) == "client"
    assert json.loads(config.get_json("scouting/multicast/enabled")) is False
    assert json.loads(config.get_json("transport/shared_memory/enabled")) is False
    assert json.loads(config.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7002"]
    assert json.loads(config.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7001"]  # kept
    assert json.loads(config.get_json("queries_default_timeout")) == 1234
    with pytest.raises(ValueError, match="mode"):
        session_config(mode="gateway")


@pytest.mark.parametrize("seconds", ["1e309", "1e300", "nan", "0", "-1"])
def test_watch_and_send_take_seconds_a_timer_can_be_set_for(seconds, capsys):
    """1e309 and 1e300 passed, then a timer could not be set (an OverflowError traceback).
    Each refused naming its flag; ``send --timeout`` in the SDK's range (below)."""
    with pytest.raises(SystemExit) as exited:
        main(["watch", "--once", f"--seconds={seconds}"])
    assert exited.value.code == 2
    assert "argument --seconds: must be a number of seconds above 0 and at most 31536000" in (
        capsys.readouterr().err)


@pytest.mark.parametrize("seconds", ["1e309", "5000", "nan", "0", "-1"])
def test_send_takes_a_timeout_the_sdk_waits(seconds, capsys):
    """``send --timeout`` took up to a year, then the SDK refused past an hour in its own
    words."""
    with pytest.raises(SystemExit) as exited:
        main(["send", "la1", "{}", f"--timeout={seconds}"])
    assert exited.value.code == 2
    assert capsys.readouterr().err.endswith(
        f"argument --timeout: must be a number of seconds from 0.001 to 3600, not {seconds}\n")


@pytest.fixture
def hostile_peer(free_port) -> Iterator[tuple[str, zenoh.Session]]:
    """A peer that says what it likes: a state whose values carry a terminal's escapes (and a
    number where a list goes), and an error reply whose code and message do too."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    escapes = "\x1b[2J\x1b]0;pwned\x07\u202e\n"
    session = zenoh.open(session_config(mode="peer", listen=[endpoint]))

    def answer(query: zenoh.Query) -> None:
        body = {"ok": False, "error": {"code": f"bad{escapes}", "message": escapes * 1000}}
        query.reply(query.key_expr, json.dumps(body))

    held = session.declare_queryable("busgate/gwx/dev/bad/cmd", answer)
    stop = threading.Event()

    def publish() -> None:
        while not stop.wait(0.05):
            session.put("busgate/gwx/dev/bad/state", json.dumps(
                {"kind": escapes, "online": True, "faults": 5, "temperature_c": escapes,
                 "joint": {"name": escapes, "unit": escapes, "position": 1e308}}))
            session.put("busgate/gwx/dev/huge/state", json.dumps(  # over 64 KiB: left out
                {"kind": "inspire_la", "online": True, "faults": ["x" * 70_000]}))

    publisher = threading.Thread(target=publish, daemon=True)
    publisher.start()
    try:
        yield endpoint, session
    finally:
        stop.set()
        publisher.join(5)
        held.undeclare()
        session.close()


def test_what_a_peer_sends_is_printed_without_its_escapes(hostile_peer, capsys):
    """A gateway's values and errors are printed, and could clear the operator's screen,
    retitle the terminal or forge lines: every control character is shown escaped."""
    endpoint, _ = hostile_peer
    assert main(["watch", "--once", "--seconds", "0.8", "--connect", endpoint]) == 0
    assert main(["send", "gwx/bad", '{"op":"status"}', "--connect", endpoint]) == 1
    out, err = capsys.readouterr()
    for text in (out, err):
        assert not set(text) & {"\x1b", "\x07", "\u202e"}, text[:300]
    assert "\\u001b[2J" in out
    assert [line for line in out.splitlines() if line.startswith("bad ")]  # one row, one line
    assert not [line for line in out.splitlines() if line.startswith("huge ")]
    [line] = err.splitlines()
    assert line.startswith("busgate send: bad\\u001b[2J") and line.endswith("…")  # cut
