"""The SDK's pieces that need no network: the error classes made from the API's codes, names
and keys, finding a device among gateways' info replies, payloads, and the claims' timer.
(The SDK against a real gateway: tests/test_client_sdk.py and its neighbours.)"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
import types
from concurrent.futures import Future
from types import SimpleNamespace

import pytest

import busgate.client as bc
from busgate.client.base import (
    Found,
    Shared,
    as_body,
    gateway_infos,
    locate,
    name_hint,
    raw_payload,
    reenable_command,
)
from busgate.client.claims import Timers
from busgate.client.errors import MAX_CODE, NoAnswerError, raise_for
from busgate.client.feeds import MAX_WAITING, MAX_WAITING_BYTES, Inbox, Latest
from busgate.client.keys import Keys, check_key, check_name, split_name
from busgate.client.messages import Answer
from busgate.client.steps import Wait
from busgate.client.surface import ClientBase
from busgate.client.trajectories import Handle, Watch, result_wait_s
from busgate.errors import BusgateError, CommandError
from busgate.schemas import inspire_la
from busgate.schemas.api import ERROR_CODES, MAX_MESSAGE
from busgate.schemas.families import FAMILIES


@pytest.mark.parametrize("code", ERROR_CODES)
def test_every_error_code_has_its_class_under_the_one_root(code: str) -> None:
    cls = bc.error_for(code)
    assert issubclass(cls, bc.GatewayError) and issubclass(cls, BusgateError)
    assert cls is not bc.GatewayError and cls.code == code
    assert getattr(bc, cls.__name__) is cls  # reachable as bc.<Name>Error
    with pytest.raises(cls) as raised:
        raise_for({"code": code, "message": "why"}, gateway="gw1")
    assert (raised.value.code, raised.value.message, raised.value.gateway) == (code, "why", "gw1")


def test_a_claimed_error_names_its_holder() -> None:
    with pytest.raises(bc.ClaimedError) as raised:
        raise_for({"code": "claimed", "message": "la1 is claimed by 'teleop-2'"})
    assert raised.value.holder == "teleop-2"


def test_a_code_this_version_does_not_know_is_still_told_as_it_came() -> None:
    with pytest.raises(bc.GatewayError) as raised:
        raise_for({"code": "from_the_future", "message": "new"})
    assert type(raised.value) is bc.GatewayError and raised.value.code == "from_the_future"
    with pytest.raises(bc.GatewayError, match="no error"):
        raise_for("not an object")
    with pytest.raises(bc.GatewayError) as raised:  # a peer's megabyte of code: cut
        raise_for({"code": "x" * 2**20, "message": "new"})
    assert raised.value.code == "x" * (MAX_CODE - 1) + "…"


def test_an_error_message_is_cut_to_the_longest_a_gateway_sends() -> None:
    """A peer's error reply of megabytes became an exception whose message a traceback or a
    log printed whole: past ``MAX_MESSAGE`` it is cut (``…``), its code and class kept."""
    with pytest.raises(bc.BusyError) as raised:
        raise_for({"code": "busy", "message": "x" * 2**20})
    assert raised.value.message == "x" * (MAX_MESSAGE - 1) + "…"
    with pytest.raises(bc.BusyError) as raised:
        raise_for({"code": "busy", "message": "x" * (MAX_MESSAGE - 1)})
    assert raised.value.message == "x" * (MAX_MESSAGE - 1)


def test_client_side_failures_are_busgate_errors_too() -> None:
    for cls in (bc.ConnectError, bc.NoAnswerError, bc.AmbiguousError, bc.CommandError):
        assert issubclass(cls, bc.BusgateError) and not issubclass(cls, bc.GatewayError)
    assert bc.CommandError is CommandError  # as sdk.md names it: the arguments refused
    assert bc.error_for("not_claimed") is bc.ClaimLostError  # the SDK's and the gateway's


@pytest.mark.parametrize("name", ["la*", "gw/*", "a/b/c", "", "x" * 65, "la 1", "gw/"])
def test_a_name_that_would_address_others_is_refused(name: str) -> None:
    with pytest.raises(CommandError):
        split_name(name)


@pytest.mark.parametrize("options", [{"lease_s": 0}, {"lease_s": "1"}, {"timeout": float("nan")},
                                     {"timeout": -1}, {"client_id": "a*b"}, {"client_id": ""},
                                     {"mode": "router"}, {"mode": None}])
def test_settings_that_make_no_sense_are_refused_before_any_session(options) -> None:
    with pytest.raises(CommandError):
        bc.connect("tcp/127.0.0.1:9", **{"client_id": "ok", **options})


@pytest.mark.parametrize(("arguments", "options", "said"), [
    ((7447,), {}, "endpoints must be a zenoh endpoint ('tcp/host:port') or a list of them, not"),
    ((b"tcp/127.0.0.1:9",), {}, "or a list of them, not bytes"),
    ((["tcp/127.0.0.1:9", 9],), {}, "or a list of them, not int"),
    ((), {"config_file": 5}, "config_file must be a path, not int"),
    ((), {"ca": 1.5}, "ca must be a path, not float"),
    ((), {"username": 5, "password": "x"}, "username must be a string, not int"),
])
def test_arguments_of_the_wrong_type_are_a_command_error(arguments, options, said) -> None:
    """Under ``BusgateError`` as everything the SDK raises: a port number for the endpoint
    was Python's own ``TypeError`` ('int' object is not iterable), a user name that is no
    string zenoh's JSON5 error."""
    with pytest.raises(CommandError) as refused:
        bc.connect(*arguments, **{"client_id": "ok", **options})
    assert said in str(refused.value)


def test_an_endpoint_zenoh_cannot_use_is_a_connect_error() -> None:
    with pytest.raises(bc.ConnectError, match="cannot open a zenoh session to nonsense"):
        bc.connect("nonsense", client_id="ok")


@pytest.mark.parametrize(("endpoint", "reason"), [
    ("tcp/127.0.0.1:70000", "zenoh endpoint 'tcp/127.0.0.1:70000': port '70000' is no port: "
                            "from 1 to 65535"),
    ("tcp/127.0.0.1:0", "zenoh endpoint 'tcp/127.0.0.1:0': port '0' is no port: from 1 to 65535"),
    ("tcp/", "zenoh endpoint 'tcp/': it names no port: write host:port (tcp/127.0.0.1:7447)"),
    ("hello", "zenoh endpoint 'hello': Endpoints must be of the form <protocol>/<address>"),
])
def test_an_endpoint_that_cannot_be_is_refused_in_words_not_a_rust_debug_print(endpoint,
                                                                               reason) -> None:
    """A port over 65535 was taken, to fail as "unable to connect"; ``tcp/`` was refused
    with zenoh's ``Json5Err(Message { msg: … location: Some(Location {…}) })``."""
    with pytest.raises(bc.ConnectError) as refused:
        bc.connect(endpoint, client_id="ok")
    assert str(refused.value).startswith(f"cannot open a zenoh session to {endpoint}: {reason}")
    assert "Json5Err" not in str(refused.value) and "Location" not in str(refused.value)


def test_a_ca_certificate_that_cannot_be_one_or_has_no_tls_link_is_refused(tmp_path) -> None:
    """zenoh read ``--ca /dev/zero`` without end (1.9 GB in 3 s), and took a CA with a plain
    tcp/ endpoint, which then went in the clear while its user thought it was TLS."""
    big, ca = tmp_path / "big.pem", tmp_path / "ca.pem"
    big.write_bytes(b"x" * (1024 * 1024 + 1))
    ca.write_text("-----BEGIN CERTIFICATE-----\n")
    for path, reason in (
        ("/dev/zero", "the CA certificate /dev/zero: not a file"),
        (tmp_path / "none.pem", f"the CA certificate {tmp_path / 'none.pem'}: no such file"),
        (big, f"the CA certificate {big}: over 1 MiB: not a CA certificate"),
        (ca, "a CA certificate is for tls/ and quic/ endpoints; this session's are "
             "tcp/127.0.0.1:9: in the clear"),
    ):
        with pytest.raises(bc.ConnectError) as refused:
            bc.connect("tcp/127.0.0.1:9", client_id="ok", ca=path)
        assert str(refused.value) == f"cannot open a zenoh session to tcp/127.0.0.1:9: {reason}"


def test_a_zenoh_config_file_zenoh_cannot_parse_is_refused_saying_where(tmp_path) -> None:
    zenoh_file = tmp_path / "bad.json5"
    zenoh_file.write_text("{ not json5")
    with pytest.raises(bc.ConnectError) as refused:
        bc.connect("tcp/127.0.0.1:9", client_id="ok", config_file=zenoh_file)
    assert str(refused.value).startswith(
        f"cannot open a zenoh session to tcp/127.0.0.1:9: the zenoh config file {zenoh_file}: "
        "line 1, column 1: expected array, boolean, null, number, object, or string")


def test_a_key_zenoh_refuses_is_one_line() -> None:
    with pytest.raises(CommandError, match="not a key expression: 'busgate//x'"):
        check_key("busgate//x")
    with pytest.raises(CommandError, match="at most"):
        check_key("k/" + "x" * 70_000)


def _info(gateway: str, *devices: tuple[str, str]) -> dict:
    return {"ok": True, "gateway": gateway, "buses": [
        {"name": "uart0", "protocol": "inspire_la",
         "devices": [{"name": name, "kind": kind} for name, kind in devices]}]}


def test_a_bare_name_finds_the_one_gateway_that_has_it() -> None:
    infos = {"gw1": _info("gw1", ("la1", "inspire_la")), "gw2": _info("gw2", ("s1", "ds_servo"))}
    found = locate(infos, "s1", "device", "busgate/*/info")
    assert (found.gateway, found.name, found.kind) == ("gw2", "s1", "ds_servo")
    assert locate(infos, "gw1/uart0", "bus", "k").kind == "inspire_la"


def test_several_gateways_with_the_name_are_named() -> None:
    infos = {g: _info(g, ("la1", "inspire_la")) for g in ("gw2", "gw1")}
    with pytest.raises(bc.AmbiguousError, match=r"gw1, gw2.*gw1/la1") as raised:
        locate(infos, "la1", "device", "k")
    assert raised.value.gateways == ["gw1", "gw2"]
    assert locate(infos, "gw2/la1", "device", "k").gateway == "gw2"


def test_no_gateway_with_it_names_those_that_answered_and_nobody_is_no_answer() -> None:
    infos = {"gw1": _info("gw1", ("la1", "inspire_la"))}
    with pytest.raises(bc.UnknownDeviceError, match=r"'la9'.*\(gw1; did you mean 'la1'\?\)"):
        locate(infos, "la9", "device", "k")
    with pytest.raises(bc.UnknownBusError):
        locate(infos, "can7", "bus", "k")
    with pytest.raises(bc.NoAnswerError, match="busgate/gw3/info"):
        locate({}, "gw3/la1", "device", "busgate/gw3/info")


@pytest.mark.parametrize(("name", "said"), [
    ("la11", "(gw1, gw2; did you mean 'la1'?)"),  # the name closest to one they have
    ("lfit", "(gw1, gw2; did you mean 'lift'?)"),  # a joint's name is a device's name too
    ("gw1/xyz", "(gw1, gw2; they have la1, lift)"),  # none close: the named gateway's names
    ("gw9/la1", "(gw1, gw2; no gateway 'gw9': did you mean gw1/la1?)"),  # the one with it
    ("gw9/servo", "(gw1, gw2; no gateway 'gw9': did you mean gw2/servo?)"),
    ("other/xyz", "(gw1, gw2; no gateway 'other')"),  # and no device of that name
    ("gw1/servo", "(gw1, gw2; did you mean gw2/servo?)"),  # another gateway's, not gw1's la1
])
def test_an_unknown_name_says_what_it_likely_meant(name: str, said: str) -> None:
    """A newcomer's typo, told as an op's is (``did you mean``), where it said only who
    answered."""
    infos = {"gw1": _info("gw1", ("la1", "inspire_la")), "gw2": _info("gw2", ("servo", "ds_servo"))}
    infos["gw1"]["buses"][0]["devices"][0]["joint"] = {"name": "lift"}
    with pytest.raises(bc.UnknownDeviceError) as refused:
        locate(infos, name, "device", "k")
    assert str(refused.value).endswith(said), refused.value


@pytest.mark.parametrize(("leaf", "names", "said"), [
    ("lal", ["la1", "la2", "la3", "servo1"], "; did you mean 'la1', 'la2' or 'la3'?"),
    ("la", ["la1", "la2", "la3", "la4"], "; did you mean 'la1', 'la2' or 'la3'?"),  # 3 at most
    ("la11", ["la1", "la2"], "; did you mean 'la1'?"),  # the one closer
])
def test_a_name_as_close_to_several_names_them(leaf, names, said) -> None:
    """``lal`` was told ``did you mean 'la3'?``: the last of several alike, a guess."""
    assert name_hint(leaf, names) == said


def test_commands_go_as_dicts_or_models_and_payloads_as_given() -> None:
    assert as_body(inspire_la.Move(op="move", position=5)) == {"op": "move", "position": 5}
    assert as_body({"op": "status"}) == {"op": "status"}
    with pytest.raises(CommandError):
        as_body(["move"])
    assert raw_payload(b"\xff") == b"\xff" and raw_payload("{}") == b"{}"
    assert raw_payload({"a": 1}) == b'{"a":1}' and raw_payload(None) is None


@pytest.mark.parametrize("kind", sorted(FAMILIES))
def test_every_kind_names_a_reenable_command_its_schema_takes(kind: str) -> None:
    command = reenable_command(kind)
    FAMILIES[kind].schema.COMMAND_ADAPTER.validate_python(command)


def test_timers_call_in_time_order_on_their_own_thread_and_stop_on_close() -> None:
    timers, called, done = Timers(), [], threading.Event()
    start = time.monotonic()
    timers.at(start + 0.05, lambda: called.append(("late", threading.current_thread().name)))
    timers.at(start, lambda: called.append(("first", threading.current_thread().name)))
    timers.at(start + 0.06, done.set)
    assert done.wait(5.0)
    assert [what for what, _ in called] == ["first", "late"]
    assert {thread for _, thread in called} == {"busgate-client-timers"}
    timers.close()
    timers.at(time.monotonic(), lambda: called.append(("after close", "")))
    time.sleep(0.05)
    assert len(called) == 2


def test_a_wait_raises_what_its_future_raised_not_a_timeout_of_its_own() -> None:
    """A ``NoAnswerError`` is a ``TimeoutError`` too: the one a lookup raised at once ("no
    gateway answered on busgate/ghost/info") was told as the wait's own timeout ("finding
    ghost/la1: no answer within 5 s", in 1.6 ms), sync and asyncio alike."""
    failed: Future = Future()
    failed.set_exception(NoAnswerError("no gateway answered on busgate/ghost/info"))
    with pytest.raises(NoAnswerError, match="no gateway answered on busgate/ghost/info"):
        Wait(failed, 5.0, "finding ghost/la1").wait()
    with pytest.raises(NoAnswerError, match="no gateway answered on busgate/ghost/info"):
        asyncio.run(Wait(failed, 5.0, "finding ghost/la1").awaited())
    with pytest.raises(NoAnswerError, match=r"finding ghost/la1: no answer within 0\.01 s"):
        Wait(Future(), 0.01, "finding ghost/la1", margin_s=0.0).wait()  # nothing came


def test_a_trajectorys_result_is_waited_for_without_a_querys_margin() -> None:
    """``t.wait(0.1)`` waited 1.1 s: the margin zenoh may take to settle a query was added to
    a result that comes on a subscription (an audit)."""
    handle = SimpleNamespace(_watch=SimpleNamespace(finished=Future()), end_at=0.0, id="t1")
    step = next(Handle.__dict__["wait"].steps(handle, 0.1))
    assert isinstance(step, Wait) and (step.timeout_s, step.margin_s) == (0.1, 0.0)


def test_a_name_that_is_not_a_string_is_said_to_be_none() -> None:
    """``{"gateway": 123}`` was refused as "not a gateway name: '123'", a name that looks
    valid."""
    with pytest.raises(CommandError, match="not a gateway name: 123 is a int, not a string"):
        check_name("gateway", 123)


def test_a_peer_whose_info_is_malformed_never_breaks_finding_the_others() -> None:
    """The lookup walks each gateway's info as it came (a newer gateway's may say more): a
    bus that is no object, a device list that is a string, a device named with a wildcard or
    of a kind this SDK does not know are passed over; an answer naming no gateway (``*``) or
    another than it answered as is left out. Before: AttributeError, a Device of kind
    'nonexistent' that failed later with KeyError, and a Device on gateway '*'."""
    good = _info("gw1", ("la1", "inspire_la"))
    answers = [Answer(f"busgate/{gw}/info", body, True) for gw, body in (
        ("evil", {"gateway": "evil", "buses": "not a list"}),
        ("evil2", {"gateway": "evil2", "buses": [5, {"name": "uart0", "devices": "x"}]}),
        ("evil3", _info("evil3", ("la1", "nonexistent"), ("*", "inspire_la"))),
        ("star", _info("*", ("la1", "inspire_la"))),  # claims every gateway's name
        ("liar", _info("gw1", ("la2", "inspire_la"))),  # answers as another
        ("gw1", good),
    )]
    infos = gateway_infos(answers)
    assert sorted(infos) == ["evil", "evil2", "evil3", "gw1"] and infos["gw1"] is good
    found = locate(infos, "la1", "device", "busgate/*/info")
    assert (found.gateway, found.name, found.kind) == ("gw1", "la1", "inspire_la")
    with pytest.raises(bc.UnknownDeviceError):
        locate(infos, "evil3/la1", "device", "k")
    with pytest.raises(bc.UnknownDeviceError):
        locate(infos, "la2", "device", "k")


def test_a_state_that_is_not_one_is_left_out_not_raised_as_pydantics(caplog) -> None:
    """``states()`` ended at the first malformed message with a raw ValidationError (no
    BusgateError); now such a message reads as none, and the gateway is named once."""
    found = Found("gwbad", "la1", "inspire_la")
    for payload in (b'{"position": "far"}', b"[" * 5000, b"not json"):
        assert Shared.telemetry(None, found, payload) is None  # type: ignore[arg-type]
    assert caplog.text.count("states of gateway 'gwbad' left out") == 1


def test_a_reader_far_behind_loses_the_oldest_and_is_told_once(caplog) -> None:
    """A feed's items waited without end for a reader that had fallen behind (memory, as
    long as the feed ran): past ``MAX_WAITING`` the oldest go, and a warning says so once."""
    inbox: Inbox[int] = Inbox()
    with caplog.at_level(logging.WARNING, logger="busgate.client.feeds"):
        for n in range(MAX_WAITING + 5):
            inbox.put(n)
    assert inbox.dropped == 5
    assert caplog.text.count("the oldest are dropped unread") == 1
    taken = [inbox.next().result(timeout=0) for _ in range(MAX_WAITING)]
    assert taken == list(range(5, MAX_WAITING + 5))
    waiting = inbox.next()
    assert not waiting.done()
    inbox.put(-1)
    assert waiting.result(timeout=0) == -1


def test_a_reader_behind_holds_at_most_max_waiting_bytes_of_payloads() -> None:
    """A thousand of a peer's 2 MiB payloads waited for a reader that had stopped reading (an
    audit: 1.2 GB): past ``MAX_WAITING_BYTES`` the oldest go as well."""
    inbox: Inbox[bytes] = Inbox()
    big = MAX_WAITING_BYTES // 4 + 1
    for n in range(6):
        inbox.put(bytes([n]) * big)
    assert inbox.dropped == 3  # four would be one byte past the budget
    assert [inbox.next().result(timeout=0)[0] for _ in range(3)] == [3, 4, 5]
    inbox.put(b"x" * MAX_WAITING_BYTES)  # the budget free again: one as large as it waits
    assert inbox.dropped == 3 and inbox.next().result(timeout=0) == b"x" * MAX_WAITING_BYTES



def test_an_ended_inbox_hands_what_waits_then_its_end_and_wakes_a_reader_waiting() -> None:
    inbox: Inbox[int] = Inbox()
    waiting = inbox.next()
    inbox.end(CommandError("closed"))
    assert isinstance(waiting.exception(timeout=0), CommandError)  # woken, not left to time out
    ended: Inbox[int] = Inbox()
    ended.put(1)
    ended.end(CommandError("closed"))
    assert ended.next().result(timeout=0) == 1
    assert isinstance(ended.next().exception(timeout=0), CommandError)



class _Shared:
    """What a trajectory's ``Watch`` asks of the client: its keys, the gateways' going and one
    subscription, whose end (and a gateway's going) the test calls."""

    def __init__(self) -> None:
        self.gone: list = []
        self.core = types.SimpleNamespace(keys=Keys("busgate"), on_gateway_gone=self.listen)

    def listen(self, listener):
        self.gone.append(listener)
        return lambda: listener in self.gone and self.gone.remove(listener)  # again: no-op

    def subscribe(self, key, on_message, ended):
        self.ended, self.feed = ended, on_message
        return lambda: None


@pytest.mark.parametrize(("closed_first", "why"), [
    (False, "cannot read 'busgate/gw/trajectory/t1/feedback': session closed"),
    (True, "trajectory t1 is no longer listened to: closed"),
])
def test_a_trajectorys_result_and_feedback_waited_for_end_with_its_subscription(
        closed_first, why) -> None:
    """A wait for a trajectory's result, or its feedback, under way when the client closed
    waited out its timeout (by default 30 s past the trajectory's end)."""
    shared = _Shared()
    watch = Watch(shared, "gw", "t1")
    inbox: Inbox[dict] = Inbox()
    watch.add_inbox(inbox)
    feedback = inbox.next()
    if closed_first:
        watch.close()
    shared.ended()
    later: Inbox[dict] = Inbox()
    watch.add_inbox(later)  # a feed started after the end: it ends at once too
    for future in (watch.finished, feedback, later.next()):
        assert str(future.exception(timeout=0)) == why


def test_a_trajectorys_waits_end_when_its_gateway_goes_and_only_its_own() -> None:
    shared = _Shared()
    watch, done = Watch(shared, "gw", "t1"), Watch(shared, "gw", "t2")
    shared.feed("busgate/gw/trajectory/t2/feedback", {"id": "t2", "result": "succeeded"})
    assert len(shared.gone) == 1  # a finished one no longer listens
    inbox: Inbox[dict] = Inbox()
    watch.add_inbox(inbox)
    feedback = inbox.next()
    shared.gone[0]("other")
    assert not watch.finished.done()
    shared.gone[0]("gw")
    why = "trajectory t1: gateway gw went away (restarted or cut off) before its result came"
    for future in (watch.finished, feedback):
        assert isinstance(future.exception(timeout=0), bc.NoAnswerError)
        assert str(future.exception(timeout=0)) == why
    assert done.finished.result(timeout=0)["result"] == "succeeded"


def test_a_latest_ended_fails_its_readers_and_those_that_come_after() -> None:
    core = _Core()
    latest = Latest(core, "busgate/gw/joints", "gw")
    waiting = latest.next()
    core.ended()
    for future in (waiting, latest.next()):
        assert "session closed" in str(future.exception(timeout=0))


class _Core:
    """What ``Latest`` asks of a client's core: its subscription, kept here to be fed."""

    def subscribe(self, key, on_message, ended):
        self.feed, self.ended = on_message, ended

    def on_gateway_gone(self, callback):
        self.gone = callback


def test_a_latest_payload_newer_than_one_taken_is_found_without_waiting() -> None:
    """``Client.joints`` found a junk message and then waited for the next one: a good one
    that came while it looked was passed over, and a peer's junk sent just before each good
    message hid every one of them (a test saw no joints message within 2 s on a busy host)."""
    core = _Core()
    latest = Latest(core, "busgate/gw/joints", "gw")
    waited = latest.next()
    core.feed("busgate/gw/joints", b"junk")
    junk = waited.result(0)
    assert latest.newer_than(junk) is None  # nothing came after it
    core.feed("busgate/gw/joints", b'{"good": 1}')
    assert latest.newer_than(junk) == b'{"good": 1}'
    core.gone("gw")
    assert latest.newer_than(junk) is None  # the gateway went: nothing is its latest


@pytest.mark.parametrize("timeout", [float("inf"), 1e12, "x", -1, float("nan"), True])
def test_a_trajectory_wait_that_is_no_number_of_seconds_is_a_command_error(timeout) -> None:
    """``t.wait(float("inf"))`` raised OverflowError, ``"x"`` TypeError: both outside the
    SDK's errors (an audit)."""
    with pytest.raises(CommandError, match="timeout must be a number of seconds from 0 to"):
        result_wait_s(0.0, timeout)
    assert result_wait_s(0.0, 5) == 5 and result_wait_s(time.time(), None) >= 29


@pytest.mark.parametrize("devices", ["la1", []])
def test_a_play_of_devices_that_are_no_list_of_names_is_refused(devices) -> None:
    """``c.play("la1", …)`` looked up 'l', 'a' and '1'; ``c.play([], …)`` was refused in a
    garbled line ("…not of : play one trajectory…")."""
    face = SimpleNamespace(timeout=1.0)
    with pytest.raises(CommandError, match=r"devices is a list of their names \(\['la1'"):
        next(ClientBase.__dict__["play"].steps(face, devices, []))
