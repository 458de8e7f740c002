"""Two gateways of one name on one zenoh network (``gateway.api.bridge`` rule 7): both would
carry out every command sent to that name, each replying ok. The second is refused before it
declares anything (``busgate run`` exits 2 with one line), and one that comes later is logged
as an ERROR, once a session. Real gateways (``busgate run``, or the bridge on a real session)
and real zenoh sessions, on loopback ports, no multicast."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import socket
import subprocess
from collections import deque
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from busgate.codecs import inspire_la
from busgate.errors import ConfigError
from busgate.gateway.api.bridge import ZenohBridge
from busgate.gateway.api.commands import GatewayApi
from busgate.gateway.service.assembly import build_bus
from busgate.gateway.sim.inspire_la import InspireLaDevice
from busgate.gateway.sim.serial_server import SerialSimulator
from busgate.schemas.config import parse_config
from busgate.schemas.zenoh_session import session_config
from tests.gateway_process import TIMEOUT_S, GatewayProcess, run_busgate, serial_bus
from tests.test_zenoh_api import config_for

#: What a gateway logs when one of its name comes later.
LATER = "another gateway named aud1 is live under prefix busgate"


def gateway_config(path: Path, *buses: str, listen: str | None = None,
                   connect: str | None = None, mode: str = "peer") -> Path:
    """A config of gateway ``aud1`` (``tests.gateway_process.write_config``'s, with ``connect``
    and ``mode`` besides)."""
    zenoh_table = f'mode = "{mode}"\n'
    zenoh_table += "" if listen is None else f'listen = ["{listen}"]\n'
    zenoh_table += "" if connect is None else f'connect = ["{connect}"]\n'
    path.write_text(f'[gateway]\nname = "aud1"\n[zenoh]\n{zenoh_table}' + "".join(buses))
    return path


def ended(process: GatewayProcess) -> int:
    """``process``'s exit status; fails, stopping it, when it is still serving after
    ``TIMEOUT_S``."""
    try:
        return process.process.wait(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        process.stop()
        pytest.fail(f"the second gateway aud1 kept serving: {process.logged}")


@contextlib.contextmanager
def serving(config: Path) -> Iterator[GatewayProcess]:
    gateway = GatewayProcess(config)
    try:
        gateway.wait_for(" serving ")
        yield gateway
    finally:
        gateway.stop()


def test_a_second_gateway_of_a_name_is_refused_and_commands_reach_the_first_alone(
        free_port, tmp_path) -> None:
    """The outside audit's case: aud1 on one port, a second aud1 on another port connecting to
    it, each with an la1. The second exits 2 with one line naming the name, the prefix and
    what to do, before it opened its bus; the first heard nothing of it, and a move sent to
    aud1/la1 (or la1 alone) gets one reply."""
    first_endpoint = f"tcp/127.0.0.1:{free_port()}"
    with (SerialSimulator(inspire_la, [InspireLaDevice(1)], baudrate=921_600) as first_sim,
          SerialSimulator(inspire_la, [InspireLaDevice(1)], baudrate=921_600) as second_sim,
          serving(gateway_config(tmp_path / "first.toml",
                                 serial_bus("uart0", first_sim.port, "la1"),
                                 listen=first_endpoint)) as first):
        second = GatewayProcess(gateway_config(
            tmp_path / "second.toml", serial_bus("uart1", second_sim.port, "la1"),
            listen=f"tcp/127.0.0.1:{free_port()}", connect=first_endpoint))
        assert ended(second) == 2, second.logged
        errors = [line for line in second.logged if "error" in line.lower()]
        assert len(errors) == 1, second.logged
        assert errors[0].startswith("busgate run: error: gateway aud1 is already live under "
                                    "prefix busgate (zenoh session ")
        assert "give each gateway its own [gateway] name" in errors[0]
        assert second_sim.recorder.received() == []  # its bus never opened
        for device in ("aud1/la1", "la1"):
            sent = run_busgate("send", "--connect", first_endpoint, device,
                               '{"op":"move","position":1500}')
            assert sent.returncode == 0, sent.stderr
            replies = sent.stdout.strip().splitlines()
            assert len(replies) == 1 and json.loads(replies[0])["ok"] is True, sent.stdout
        assert not [line for line in first.logged if "ERROR" in line], first.logged


@contextlib.contextmanager
def bridge_opened_beside(other_endpoint: str, endpoint: str) -> Iterator[ZenohBridge]:
    """The bridge of gateway ``gw1`` (its bus never started) on a session listening on
    ``endpoint`` and connected to ``other_endpoint``; closed after."""
    raw = config_for("/dev/null", endpoint)
    raw["zenoh"]["connect"] = [other_endpoint]
    config = parse_config(raw)
    runners = {bus.name: build_bus(bus) for bus in config.buses}
    bridge = ZenohBridge(config, GatewayApi("gw1", runners), runners, deque(), deque())
    loop = asyncio.new_event_loop()
    try:
        bridge.open(loop)
        yield bridge
    finally:
        bridge.close()
        loop.close()


@pytest.mark.parametrize("held", ["info", "token and info"])
def test_a_bridge_opens_beside_another_name_and_is_refused_beside_its_own(free_port,
                                                                          held) -> None:
    """Beside a session holding gateway gw2's token and info the bridge of gw1 opens; beside
    one answering gw1's info it is refused with nothing declared: no answer of its own on
    gw1's keys, its listen port free again."""
    other_endpoint = f"tcp/127.0.0.1:{free_port()}"
    other = zenoh.open(session_config(mode="peer", listen=[other_endpoint]))
    try:
        kept = [other.liveliness().declare_token("busgate/gw2/alive"),
                other.declare_queryable("busgate/gw2/info",
                                        lambda query: query.reply(query.key_expr, b"{}"))]
        with bridge_opened_beside(other_endpoint, f"tcp/127.0.0.1:{free_port()}"):
            pass  # gw2 is no namesake of gw1
        if held == "token and info":
            kept.append(other.liveliness().declare_token("busgate/gw1/alive"))
        kept.append(other.declare_queryable(
            "busgate/gw1/info", lambda query: query.reply(query.key_expr, b"{}")))
        port = free_port()
        with (pytest.raises(ConfigError) as refused,
              bridge_opened_beside(other_endpoint, f"tcp/127.0.0.1:{port}")):
            pytest.fail("the bridge of gw1 opened beside a gw1")
        said = str(refused.value)
        assert said.startswith("gateway gw1 is already live under prefix busgate (")
        assert refused.value.path == "gateway.name"
        assert f"zenoh session {other.info.zid()} at {other_endpoint}" in said
        answers = [r for r in other.get("busgate/gw1/**", timeout=2.0) if r.ok is not None]
        assert len(answers) == 1  # its own: none of the bridge's
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", port))  # the refused session's listener is closed
        del kept
    finally:
        other.close()


def test_a_token_held_with_no_info_answering_is_a_stale_one_warned_of(free_port,
                                                                        caplog) -> None:
    """A gateway whose host went away keeps its token at the others until its lease runs
    out, and answers nothing: one of its name restarted meanwhile serves, with a warning."""
    other_endpoint = f"tcp/127.0.0.1:{free_port()}"
    other = zenoh.open(session_config(mode="peer", listen=[other_endpoint]))
    try:
        kept = other.liveliness().declare_token("busgate/gw1/alive")
        opened = False
        with caplog.at_level(logging.WARNING), \
                bridge_opened_beside(other_endpoint, f"tcp/127.0.0.1:{free_port()}"):
            opened = True
        assert opened and "no gateway of name gw1 answers its info" in caplog.text
        del kept
    finally:
        other.close()


class Namesake:
    """A zenoh session posing as gateway aud1: its liveliness token and an ``info``."""

    def __init__(self, config: zenoh.Config) -> None:
        self.session = zenoh.open(config)
        self.zid = str(self.session.info.zid())
        self.declared: list = []
        self.declare()

    def declare(self) -> None:
        """Its ``info`` first, then its token, as a gateway declares them (``bridge.open``):
        a token that came first sent the look for its ``info`` before it was served."""
        self.declared = [
            self.session.declare_queryable(
                "busgate/aud1/info", lambda query: query.reply(query.key_expr, b'{"ok":true}')),
            self.session.liveliness().declare_token("busgate/aud1/alive"),
        ]

    def undeclare(self) -> None:
        for entity in self.declared:
            entity.undeclare()


@pytest.mark.parametrize("through", ["peer", "router"])
def test_a_gateway_of_its_name_that_comes_later_is_logged_once_a_session(free_port, tmp_path,
                                                                         through) -> None:
    """aud1 serving; a session posing as another aud1 comes (linked to it, or through a
    router both are clients of): an ERROR naming that session and what to do. The same
    session leaving and coming back is not told again; another session after it is. (Through
    a router, zenoh told the first coming only as this ``info`` served elsewhere, the next
    only as the token: the test fails without either watch.)"""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = None
    if through == "router":
        router = zenoh.open(session_config(mode="router", listen=[endpoint]))
        config = gateway_config(tmp_path / "gw.toml", serial_bus("uart0", str(tmp_path / "no"),
                                                                 "la1"),
                                connect=endpoint, mode="client")
        namesake_config = {"mode": "client", "connect": [endpoint]}
    else:
        config = gateway_config(tmp_path / "gw.toml", serial_bus("uart0", str(tmp_path / "no"),
                                                                 "la1"), listen=endpoint)
        namesake_config = {"mode": "peer", "connect": [endpoint]}
    try:
        with serving(config) as gateway:
            first = Namesake(session_config(**namesake_config))
            told = gateway.wait_for(LATER)
            assert told.startswith("ERROR ") and f"zenoh session {first.zid}" in told
            assert "give one of them its own [gateway] name" in told
            first.undeclare()
            first.declare()  # the same session again: told already
            first.session.close()
            second = Namesake(session_config(**namesake_config))
            assert second.zid in gateway.wait_for(LATER)
            second.session.close()
            errors = [line for line in gateway.logged if line.startswith("ERROR")]
            assert len(errors) == 2 and second.zid in errors[1], errors
            assert gateway.stop() == 0
    finally:
        if router is not None:
            router.close()
