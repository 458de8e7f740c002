"""What the SDK does when things go wrong, against real gateways as child processes: a client
frozen by SIGSTOP loses its claim within its short lease, a claim taken over after a lapse is
reported lost, a gateway restarted under a live client is used again by the same ``Client``
(and the claim held across the restart is reported lost), and the deploy config's accounts
(TLS, user names and passwords, ACL: tests/secured_gateway.py) decide who may command.

The figures the contract names are printed (run with ``-s`` to see them): how long after its
SIGSTOP another client could move the frozen client's device, and how long after the restart
the same client's commands and telemetry worked again.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

import busgate.client as bc
from tests.gateway_process import DemoProcess
from tests.sdk_helpers import fresh_positions, patiently, the_client_id
from tests.secured_gateway import ACCOUNTS

POSITIONS = fresh_positions(102)
#: Hang guards, not speed requirements.
DEADLINE_S = 10.0
CHILD_TIMEOUT_S = 30.0
#: The contract's bounds: a frozen client's claim is gone this soon (its lease is 1 s), and a
#: restarted gateway serves the same client again this soon after it is back.
LEASE_BOUND_S = 2.0
RECOVERY_BOUND_S = 10.0
SESSIONS = itertools.count(1)


@pytest.fixture
def connect(request):
    """``connect(endpoint, suffix, **options)``: a client named after the test, closed after
    it."""
    clients: list[bc.Client] = []

    def open_client(endpoint: str, suffix: str = "", **options) -> bc.Client:
        name = f"{request.node.name}-{suffix}" if suffix else request.node.name
        clients.append(bc.connect(endpoint, client_id=the_client_id(name), **options))
        return clients[-1]

    yield open_client
    for client in clients:
        client.close()


def until_it_works(attempt, deadline_s: float):
    """``attempt()``'s result once it stops raising ``NoAnswerError``, and when."""
    deadline = time.monotonic() + deadline_s
    while True:
        try:
            return attempt(), time.monotonic()
        except bc.NoAnswerError:
            assert time.monotonic() < deadline, "it never worked again"
            time.sleep(0.05)


# -- the short lease: a frozen client's claim ------------------------------------------------

#: A client that claims la2 for far longer than the test (only its lease can end the claim),
#: says so, and waits to be frozen.
FROZEN_CLIENT = """
import sys
import busgate.client as bc
with bc.connect(sys.argv[1], client_id=sys.argv[2]) as client:
    with client.device("la2").claim(ttl_s=600.0):
        print("claimed", flush=True)
        sys.stdin.readline()
"""


def test_a_frozen_clients_claim_is_lost_within_2_s(module_demo, connect) -> None:
    other = connect(module_demo.endpoint, "other")
    la2 = other.device("la2")
    patiently(la2.enable)
    frozen_id = the_client_id("frozen-claimant")
    child = subprocess.Popen([sys.executable, "-c", FROZEN_CLIENT, module_demo.endpoint, frozen_id],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline() == "claimed\n"
        with pytest.raises(bc.ClaimedError) as refused:
            la2.move(next(POSITIONS))
        assert refused.value.holder == frozen_id
        child.send_signal(signal.SIGSTOP)
        frozen = time.monotonic()
        while True:
            try:
                assert patiently(lambda: la2.move(next(POSITIONS)))["ok"] is True
                break
            except bc.ClaimedError:
                assert time.monotonic() - frozen < CHILD_TIMEOUT_S, "the claim never went"
                time.sleep(0.02)
        lost_after = time.monotonic() - frozen
        print(f"\nSIGSTOP -> another client's move succeeds: {lost_after:.2f} s")
        assert lost_after < LEASE_BOUND_S
    finally:
        child.send_signal(signal.SIGCONT)
        child.kill()
        child.wait(timeout=CHILD_TIMEOUT_S)


# -- a claim lost to another client ----------------------------------------------------------


def _take_over(endpoint: str, connect, holder: bc.Client, device: str) -> bc.Client:
    """Release ``holder``'s claim on ``device`` as its own id would (client ids are
    self-chosen), and claim it as another client whose block the caller enters: the holder's
    next renewal is refused ``claimed``."""
    twin = bc.connect(endpoint, client_id=holder.client_id)
    try:
        assert patiently(lambda: twin.device(device).send({"op": "release"}))["ok"] is True
    finally:
        twin.close()
    return connect(endpoint, "thief")


def test_a_claim_whose_renewal_is_refused_is_lost_and_refuses_motion(
        module_demo, connect, wait_for) -> None:
    holder = connect(module_demo.endpoint, "holder")
    la3 = holder.device("la3")
    patiently(la3.enable)
    with pytest.raises(bc.ClaimLostError), la3.claim(ttl_s=1.0) as claim:
        thief = _take_over(module_demo.endpoint, connect, holder, "la3")
        with thief.device("la3").claim(ttl_s=5.0):
            wait_for(lambda: claim.lost is not None, timeout=DEADLINE_S)
            assert "claimed" in claim.lost
            with pytest.raises(bc.ClaimLostError):
                la3.move(next(POSITIONS))
            with pytest.raises(bc.ClaimLostError), la3.follow() as stream:
                stream.set(position=next(POSITIONS))
        time.sleep(0.5)  # past the holder's renewal period (TTL / 3): it must not renew
        third = connect(module_demo.endpoint, "third").device("la3")
        assert patiently(lambda: third.move(next(POSITIONS)))["ok"]
    assert patiently(lambda: la3.move(next(POSITIONS)))["ok"] is True


def test_a_lost_claim_still_lets_an_estop_and_a_read_through(module_demo, connect) -> None:
    holder = connect(module_demo.endpoint, "holder")
    la3 = holder.device("la3")
    patiently(la3.enable)
    try:
        with pytest.raises(bc.ClaimLostError), la3.claim(ttl_s=1.0) as claim:
            thief = _take_over(module_demo.endpoint, connect, holder, "la3")
            with thief.device("la3").claim(ttl_s=5.0):
                deadline = time.monotonic() + DEADLINE_S
                while claim.lost is None:
                    assert time.monotonic() < deadline
                    time.sleep(0.01)
                for op in ("status", "estop"):  # what the gateway never refuses
                    try:
                        reply = patiently(la3.send, {"op": op})
                    except bc.ClaimLostError as exc:
                        pytest.fail(f"{op} refused by the SDK: {exc}")
                    assert reply["ok"] is True, reply
    finally:
        patiently(la3.enable)


# -- a gateway restarted under a live client -------------------------------------------------


def test_a_gateway_restart_under_a_live_client(free_port, connect, wait_for) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    gateway = DemoProcess(endpoint)
    try:
        client = connect(endpoint)
        la1 = client.device("la1")
        assert patiently(la1.enable)["ok"] is True and la1.state().device == "la1"
        # a TTL far past the test: only the gateway's going can tell the claim is lost
        with pytest.raises(bc.ClaimLostError), la1.claim(ttl_s=600.0) as claim:
            assert patiently(lambda: la1.move(next(POSITIONS)))["ok"] is True
            playing = client.play(["la1"], [{"t_s": 10.0, "positions": [1000]}])
            stopped, stopped_wall = time.monotonic(), time.time()
            assert gateway.terminate(signal.SIGINT) == 0
            # Its result never comes: told at once, not as "no answer" after 40 s (an audit).
            with pytest.raises(bc.NoAnswerError, match=f"trajectory {playing.id}: gateway "
                                                       "demo went away"):
                playing.wait()
            assert time.monotonic() - stopped < DEADLINE_S
            wait_for(lambda: claim.lost is not None, timeout=DEADLINE_S)
            with pytest.raises(bc.ClaimLostError):
                la1.move(next(POSITIONS))
            gateway = DemoProcess(endpoint)  # the same endpoint
            served = time.monotonic()
            with pytest.raises(bc.ClaimLostError):
                la1.move(next(POSITIONS))  # still lost: never silently re-taken
        # the same Client and Device, once its session found the gateway again
        reply, answered = until_it_works(
            lambda: patiently(lambda: la1.send({"op": "status"}, timeout=1.0)), RECOVERY_BOUND_S)
        assert reply["ok"] is True
        state, read = until_it_works(lambda: la1.state(timeout=1.0), RECOVERY_BOUND_S)
        assert state.device == "la1" and state.ts > stopped_wall, "not read by the new gateway"
        print(f"\nrestart: back in {served - stopped:.2f} s; then send answered after "
              f"{answered - served:.2f} s, state after {read - served:.2f} s")
        assert read - served < RECOVERY_BOUND_S and answered - served < RECOVERY_BOUND_S
        other = connect(endpoint, "other")
        with la1.claim(ttl_s=2.0):  # a claim the new gateway holds for this client
            with pytest.raises(bc.ClaimedError) as refused:
                other.device("la1").move(next(POSITIONS))
            assert refused.value.holder == client.client_id
            assert patiently(lambda: la1.move(next(POSITIONS)))["ok"] is True
    finally:
        assert gateway.terminate() == 0


# -- a session's opening left by a signal ----------------------------------------------------


class Left(Exception):
    """What the test's signal raises in the thread waiting for the session's opening."""


def _held_link(target_port: int, hold_s: float, client_gone: threading.Event) -> int:
    """A loopback port whose first connection reaches ``target_port`` only ``hold_s`` after
    it came (a slow handshake), then is carried both ways; ``client_gone`` is set when the
    connecting side closes it."""
    listener = socket.create_server(("127.0.0.1", 0))

    def carry(source: socket.socket, sink: socket.socket, gone: threading.Event | None) -> None:
        with contextlib.suppress(OSError):
            while data := source.recv(65536):
                sink.sendall(data)
        if gone is not None:
            gone.set()
        with contextlib.suppress(OSError):
            sink.shutdown(socket.SHUT_WR)

    def serve() -> None:
        with listener:
            near, _ = listener.accept()
        time.sleep(hold_s)
        far = socket.create_connection(("127.0.0.1", target_port))
        threading.Thread(target=carry, args=(far, near, None), daemon=True).start()
        carry(near, far, client_gone)

    threading.Thread(target=serve, daemon=True).start()
    return listener.getsockname()[1]


def test_a_session_that_opens_after_its_caller_left_is_closed(module_demo) -> None:
    """Ctrl-C (here SIGUSR1, raising) ends ``bc.connect``'s wait for zenoh's opening at once
    (core rule 7); the session that opens after all is closed, not left open in the program,
    even while the exception is kept (as an interactive Python keeps the last one, its frames
    with it)."""
    client_gone = threading.Event()
    demo_port = int(module_demo.endpoint.rsplit(":", 1)[1])
    port = _held_link(demo_port, hold_s=1.0, client_gone=client_gone)

    def leave(signum, frame):
        raise Left

    previous = signal.signal(signal.SIGUSR1, leave)
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGUSR1))
    try:
        timer.start()
        with pytest.raises(Left) as left:
            bc.connect(f"tcp/127.0.0.1:{port}", client_id=the_client_id("left"))
    finally:
        timer.cancel()
        timer.join()
        signal.signal(signal.SIGUSR1, previous)
    assert client_gone.wait(DEADLINE_S), "the session that opened late is still open"
    assert left.tb is not None  # kept until here


def test_an_asyncio_connect_given_up_while_it_opens_closes_its_session(module_demo) -> None:
    """``asyncio.wait_for`` (a dashboard's stop, a program's deadline) cancelling
    ``bc.aio.connect``: the session that opened after all stayed open, its token held."""
    client_gone = threading.Event()
    demo_port = int(module_demo.endpoint.rsplit(":", 1)[1])
    port = _held_link(demo_port, hold_s=1.0, client_gone=client_gone)

    async def given_up() -> None:
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(bc.aio.connect(f"tcp/127.0.0.1:{port}",
                                                  client_id=the_client_id("given-up")), 0.3)

    asyncio.run(given_up())
    assert client_gone.wait(DEADLINE_S), "the session that opened late is still open"


# -- accounts: the deploy config's TLS, passwords and ACL -------------------------------------


def _secured(daemon, account: str | None, password: str | None = None, *,
             scheme: str = "tls", ca: bool = True, **options) -> bc.Client:
    """A client of the secured daemon as ``account`` (a client id of its own each time)."""
    return bc.connect(f"{scheme}/127.0.0.1:{daemon.port}",
                      client_id=the_client_id(f"{account}-{scheme}-{next(SESSIONS)}"),
                      username=account, password=password,
                      ca=daemon.etc / "tls/ca.pem" if ca else None, **options)


def test_an_operator_over_tls_can_move(secured_daemon, wait_for) -> None:
    with _secured(secured_daemon, "operator", ACCOUNTS["operator"]) as operator:
        assert set(operator.gateways()) == {"gw1"}
        la1 = operator.device("la1")
        patiently(la1.enable)
        target = next(POSITIONS)
        assert patiently(lambda: la1.move(target))["state"]["target"] == target
        wait_for(lambda: la1.state().position == target, timeout=DEADLINE_S)
        with la1.claim(ttl_s=1.0):  # its liveliness token is allowed: claims work
            assert patiently(lambda: la1.move(next(POSITIONS)))["ok"] is True


def test_a_viewer_reads_state_but_gets_no_answer_to_a_command(secured_daemon) -> None:
    """The ACL hides the command keys from a viewer: its commands are not refused with a
    code, nobody answers them (at once: zenoh knows no queryable for them), and its e-stop
    put is dropped."""
    with _secured(secured_daemon, "operator", ACCOUNTS["operator"]) as operator, \
            _secured(secured_daemon, "viewer", ACCOUNTS["viewer"], timeout=3.0) as viewer:
        assert set(viewer.gateways()) == {"gw1"}
        la1 = viewer.device("la1")
        assert la1.state(timeout=5.0).device == "la1"
        assert len(list(la1.states(timeout=1.0))) >= 2
        mine = operator.device("la1")
        patiently(mine.enable)
        target = next(POSITIONS)
        for attempt in (lambda: la1.move(target), lambda: la1.send({"op": "status"}),
                        lambda: la1.claim(ttl_s=1.0).__enter__(),
                        lambda: viewer.bus("uart0").scan([1])):
            asked = time.monotonic()
            with pytest.raises(bc.NoAnswerError):
                attempt()
            assert time.monotonic() - asked < 3.0, "it waited for the timeout"
        viewer.estop()  # no error: a put is not answered
        assert set(viewer.gateways()) == {"gw1"}  # so the gateway has had the e-stop put
        moved = patiently(mine.move, next(POSITIONS))
        assert moved["ok"] is True, "the viewer's e-stop got through"


WRONG_ACCOUNT = "(a wrong user name or password, or a gateway that takes none, is refused so too)"
NO_CA = "(a tls/ endpoint needs the CA that signed the gateway's certificate: ca=, --ca"
#: Each way in, and the hint its refusal ends with: what it lacks, not what it has.
TURNED_AWAY = {
    "wrong password": ("operator", "guess", {}, WRONG_ACCOUNT),
    "unknown user": ("intruder", "op-secret", {}, WRONG_ACCOUNT),
    "no credentials": (None, None, {}, "(nobody listening there, or a gateway that takes "
                                       "accounts refusing a session without one: username=, "
                                       "--user)"),
    "no credentials and no CA": (None, None, {"ca": False},
                                 f"{NO_CA}; and an account if it takes them: --user)"),
    "plain tcp": ("operator", ACCOUNTS["operator"], {"scheme": "tcp", "ca": False},
                  WRONG_ACCOUNT),
    "no CA": ("operator", ACCOUNTS["operator"], {"ca": False}, f"{NO_CA})"),
}


@pytest.mark.parametrize("way", TURNED_AWAY.values(), ids=TURNED_AWAY)
def test_a_client_turned_away_raises_connect_error_saying_what_it_may_lack(secured_daemon,
                                                                           way) -> None:
    """With a user but no CA, the refusal blamed the password; with a CA but no user it said
    nothing of an account, and the command-line tools added "is a gateway listening there?"."""
    account, password, options, hint = way
    with pytest.raises(bc.ConnectError) as refused:
        _secured(secured_daemon, account, password, **options).close()
    assert isinstance(refused.value, bc.BusgateError) and isinstance(refused.value,
                                                                      ConnectionError)
    assert f"127.0.0.1:{secured_daemon.port}" in str(refused.value)
    assert str(refused.value).endswith(hint), refused.value
    assert not refused.value.unreached  # so no command-line tool adds its own guess


def test_a_local_clients_shared_memory_is_never_mapped_into_the_gateway(module_demo) -> None:
    """A client of zenoh's defaults on the gateway's host sends a large payload through a
    shared-memory segment of its own (16 MB), which a gateway with shared memory on maps and
    keeps: a few local sessions grew a demo by hundreds of MB. busgate's sessions have it off,
    so the payload comes over the socket (refused as too large, as ever) and nothing is mapped."""
    config = zenoh.Config()  # shared memory on, as zenoh has it by default
    config.insert_json5("mode", json.dumps("client"))
    config.insert_json5("connect/endpoints", json.dumps([module_demo.endpoint]))
    config.insert_json5("scouting/multicast/enabled", "false")
    assert json.loads(config.get_json("transport/shared_memory/enabled")) is True
    with zenoh.open(config) as session:
        for _ in range(3):
            replies = list(session.get("busgate/demo/dev/la1/cmd", payload=b" " * 200_000,
                                       timeout=5))
            assert [json.loads(r.ok.payload.to_bytes())["error"]["code"] for r in replies] == [
                "too_large"]
    maps = Path(f"/proc/{module_demo.process.pid}/maps").read_text().splitlines()
    assert [line for line in maps if "/dev/shm/" in line] == []
