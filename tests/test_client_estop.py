"""E-stops and their resets as the SDK sends them, with both faces, against a bare zenoh
session posing as gateways: it listens on a loopback port (multicast scouting off), holds the
liveliness tokens of ``gwx`` and ``gwy`` and answers their ``info``, records every put under
``busgate/`` on zenoh's thread as it comes, and answers the commands to ``gwx/la1``.

``estop()`` is the fleet; a name must be one gateway's (``""`` is refused before anything is
put); the put goes first, and a name no gateway is up under is ``UnknownGatewayError`` after
it (known at once from the tokens the client has seen, else from the gateways' ``info``).
``reset_estop(gw)`` puts the client's id on ``<prefix>/<gw>/estop/reset`` and
``Device.reset_estop()`` sends ``{"op": "reset_estop"}`` on the device's ``cmd`` key. (The
gateway's side of a reset: its own tests.)
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import zenoh

import busgate.client as bc
from busgate.schemas.zenoh_session import session_config
from tests.conftest import unused_loopback_port
from tests.sdk_helpers import the_client_id

#: The gateways the fake session poses as.
UP = ["gwx", "gwy"]
BUSES = [{"name": "uart0", "protocol": "inspire_la", "devices": [
    {"name": "la1", "kind": "inspire_la"}]}]  # fmt: skip
#: Liveliness tokens the fake session holds whose gateway chunk is no name.
NO_GATEWAYS = ["*", "**", "a$*", "gwx/la1"]
#: A hang guard for what is waited for, not a speed requirement.
DEADLINE_S = 5.0


class FakeGateways:
    """The zenoh session posing as ``gwx`` and ``gwy``, until ``close``."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{unused_loopback_port()}"
        self.session = zenoh.open(session_config(mode="peer", listen=[self.endpoint]))
        self._lock = threading.Lock()
        self.puts: list[tuple[float, str, Any]] = []
        self.commands: list[tuple[str, Any]] = []
        #: When each ``info`` query came.
        self.asked: list[float] = []
        liveliness = self.session.liveliness()
        self._held = [
            *(liveliness.declare_token(f"busgate/{gateway}/alive") for gateway in UP),
            # a peer's tokens that name no gateway: none of them is one (nor every one)
            *(liveliness.declare_token(f"busgate/{key}/alive") for key in NO_GATEWAYS),
            self.session.declare_subscriber("busgate/**", self._direct(self._on_put)),
            *(
                self.session.declare_queryable(f"busgate/{gateway}/info", self._info(gateway))
                for gateway in UP
            ),
            self.session.declare_queryable(
                "busgate/gwx/dev/la1/cmd", self._direct(self._on_command)
            ),
        ]

    @staticmethod
    def _direct(callback: Callable[[Any], None]) -> zenoh.handlers.Callback:
        return zenoh.handlers.Callback(callback, indirect=False)

    def _on_put(self, sample: zenoh.Sample) -> None:
        with self._lock:
            body = json.loads(sample.payload.to_bytes())
            self.puts.append((time.monotonic(), str(sample.key_expr), body))

    def _info(self, gateway: str) -> zenoh.handlers.Callback:
        info = json.dumps({"ok": True, "gateway": gateway, "buses": BUSES})

        def answer(query: zenoh.Query) -> None:
            with self._lock:
                self.asked.append(time.monotonic())
            query.reply(f"busgate/{gateway}/info", info)

        return self._direct(answer)

    def _on_command(self, query: zenoh.Query) -> None:
        assert query.payload is not None
        command = json.loads(query.payload.to_bytes())
        with self._lock:
            self.commands.append((str(query.key_expr), command))
        query.reply(query.key_expr, json.dumps({"ok": True, "state": {"estopped": False}}))

    def put_on(self, key: str) -> tuple[float, Any]:
        """When the first put on ``key`` came, and its body; fails after ``DEADLINE_S``."""
        deadline = time.monotonic() + DEADLINE_S
        while time.monotonic() < deadline:
            with self._lock:
                for came, put_key, body in self.puts:
                    if put_key == key:
                        return came, body
            time.sleep(0.005)
        raise AssertionError(f"no put on {key}: {self.puts}")

    def clear(self) -> None:
        with self._lock:
            self.puts.clear()
            self.commands.clear()
            self.asked.clear()

    def close(self) -> None:
        self._held.clear()
        self.session.close()


@pytest.fixture(scope="module")
def gateways() -> Iterator[FakeGateways]:
    fake = FakeGateways()
    try:
        yield fake
    finally:
        fake.close()


class Face:
    """A client of one face: ``done(x)`` is ``x`` from the sync face, and ``x`` awaited from
    the asyncio one (each on one event loop, kept for the test)."""

    def __init__(self, face: str, endpoint: str, client_id: str) -> None:
        self.face = face
        self._runner = asyncio.Runner() if face == "asyncio" else None
        opened = bc.connect if face == "sync" else bc.aio.connect
        self.client = self.done(opened(endpoint, client_id=client_id))
        self.client_id = client_id

    def done(self, result: Any) -> Any:
        if self._runner is None:
            return result
        return self._runner.run(asyncio.wait_for(_awaited(result), DEADLINE_S * 2))

    def close(self) -> None:
        self.done(self.client.close())
        if self._runner is not None:
            self._runner.close()


async def _awaited(awaitable: Any) -> Any:
    return await awaitable


@pytest.fixture(params=["sync", "asyncio"])
def face(request, gateways) -> Iterator[Face]:
    gateways.clear()
    client = Face(request.param, gateways.endpoint, the_client_id(request.node.name))
    try:
        yield client
    finally:
        client.close()


@pytest.mark.parametrize(
    ("method", "name"),
    [("estop", ""), ("estop", "gwx/la1"), ("estop", "gw*"), ("reset_estop", ""),
     ("reset_estop", None), ("reset_estop", "*")],
)  # fmt: skip
def test_what_names_no_gateway_is_refused_with_nothing_put_and_no_name_is_the_fleet(
    face, gateways, method, name
) -> None:
    """``estop()`` (and ``estop("*")``, as earlier releases took it) is the fleet; a reset
    always names one gateway."""
    with pytest.raises(ValueError, match="gateway"):
        face.done(getattr(face.client, method)(name))
    assert face.done(face.client.estop()) is None  # after the refused one, in order
    assert face.done(face.client.estop("*")) is None
    assert gateways.put_on("busgate/*/estop")[1] == {"client": face.client_id}
    deadline = time.monotonic() + DEADLINE_S
    while len(gateways.puts) < 2 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert [key for _, key, _ in gateways.puts] == ["busgate/*/estop"] * 2


@pytest.mark.parametrize("method", ["estop", "reset_estop"])
@pytest.mark.parametrize("seen", [True, False], ids=["token seen", "token not seen yet"])
def test_a_gateway_up_is_put_to_and_one_nobody_runs_is_put_to_then_unknown_gateway(
    face, gateways, method, seen
) -> None:
    """Whether or not this client has heard the gateway's token yet (as just after a
    connect), a gateway that is up is found; the put to one that is not goes before the
    error that says so."""
    core = face.client._shared.core
    if seen:
        deadline = time.monotonic() + DEADLINE_S
        while "gwx" not in core.gateways_up and time.monotonic() < deadline:
            time.sleep(0.005)
    else:
        core.gateways_up.clear()
    leaf = "estop" if method == "estop" else "estop/reset"
    assert face.done(getattr(face.client, method)("gwx")) is None
    assert gateways.put_on(f"busgate/gwx/{leaf}")[1] == {"client": face.client_id}
    asking = time.monotonic()
    with pytest.raises(bc.UnknownGatewayError) as unknown:
        face.done(getattr(face.client, method)("gw-typo"))
    assert unknown.value.gateway == "gw-typo" and unknown.value.gateways == UP
    assert unknown.value.code == "unknown_gateway"
    assert "'gw-typo'" in str(unknown.value) and "gwx, gwy" in str(unknown.value)
    came, body = gateways.put_on(f"busgate/gw-typo/{leaf}")
    assert body == {"client": face.client_id}
    assert came < min(t for t in gateways.asked if t > asking), "the lookup went first"


def test_a_token_whose_gateway_is_no_name_is_no_gateway_up(face) -> None:
    """A peer's token on ``busgate/*/alive`` stood for a gateway named ``*`` (the dashboard
    showed it, filled by every gateway's info, a wildcard query)."""
    core = face.client._shared.core
    deadline = time.monotonic() + DEADLINE_S
    while set(UP) - core.gateways_up and time.monotonic() < deadline:
        time.sleep(0.005)
    time.sleep(0.1)  # the other tokens came with them, in the same declarations
    assert sorted(core.gateways_up) == UP


def test_unknown_gateway_is_the_sdks_code_in_the_unknown_device_family() -> None:
    assert bc.error_for("unknown_gateway") is bc.UnknownGatewayError
    assert issubclass(bc.UnknownGatewayError, bc.GatewayError)


def test_a_devices_reset_estop_is_its_op_on_its_cmd_key(face, gateways) -> None:
    la1 = face.done(face.client.device("gwx/la1"))
    reply = face.done(la1.reset_estop())
    assert reply == {"ok": True, "state": {"estopped": False}}
    assert gateways.commands == [
        ("busgate/gwx/dev/la1/cmd", {"op": "reset_estop", "client": face.client_id})
    ]
