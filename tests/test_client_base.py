"""The SDK's bases (``Client.base`` → ``Base``, ``DriveStream``, ``Odometry``) on both faces,
against a real gateway over real zenoh sessions: ``serve`` on a thread of this module (gateway
``gw``, zenoh on loopback only, multicast off) with a base of two simulated ZLAC706 on a
python-can ``virtual`` bus, the right wheel mirrored; and the pieces without a gateway (a base
several gateways have, an odometry message that is not one, both faces' classes as twins).

One daemon for the module; each test connects clients of its own. Waits are for conditions,
each with a deadline that only guards against a hang; the one bound on time is the drive
stream's stop, which must come well before the base's ``cmd_timeout_s`` would have stopped it.
"""

from __future__ import annotations

import asyncio
import inspect
import itertools
import json
import logging
import math
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from itertools import pairwise

import can
import pytest
import zenoh

import busgate.client as bc
from busgate.client.base import Found
from busgate.client.bases import located
from busgate.client.keys import Keys
from busgate.client.messages import Answer, Answers
from busgate.codecs import zlac706_can as zcan
from busgate.codecs.zlac706_common import rpm_from_speed_raw
from busgate.errors import CommandError
from busgate.gateway.sim.can_server import CanSimulator
from busgate.gateway.sim.zlac706 import Zlac706CanDevice
from busgate.schemas.zenoh_session import session_config
from tests.conftest import unused_loopback_port
from tests.sdk_helpers import patiently, patiently_async, the_client_id
from tests.test_client_faces import TWINS, function_of, kind, public
from tests.test_zenoh_api import Daemon
from tests.wire_frames import received, written_speed

TURN = 2 * math.pi
#: Each wheel: 10000 pulses a turn, the right one mirrored; at most 3 turns a second.
LEFT = {"name": "left_wheel", "unit": "rad", "scale": TURN / 10_000, "max_velocity": 3 * TURN}
RIGHT = LEFT | {"name": "right_wheel", "scale": -TURN / 10_000}
#: A twist holds this long: long enough that a stop within it is the drive stream's, not the
#: deadman's.
CMD_TIMEOUT_S = 3.0
BASE = {"name": "base", "left": "wl", "right": "wr", "wheel_radius_m": 0.0825, "track_m": 0.4,
        "max_linear_mps": 1.0, "max_angular_radps": 2.0, "max_linear_accel": 2.0,
        "max_angular_accel": 6.0, "cmd_timeout_s": CMD_TIMEOUT_S}
#: Hang guards, not speed requirements.
DEADLINE_S = 10.0
_channels = itertools.count()


@dataclass(frozen=True)
class Gateway:
    endpoint: str
    sim: CanSimulator

    def speeds(self, since: int) -> dict[int, list[float]]:
        """The rpm of each speed write since the ``since``-th frame, by node."""
        by_node: dict[int, list[float]] = {1: [], 2: []}
        for _, frame in received(self.sim, since, zcan):
            speed = written_speed(frame)
            if speed is not None:
                by_node[frame.device_id].append(rpm_from_speed_raw(speed))
        return by_node


@pytest.fixture(scope="module")
def gw() -> Iterator[Gateway]:
    """``serve`` as gateway ``gw`` with the base ``base`` (``wl`` and ``wr``), its wheels
    online."""
    endpoint = f"tcp/127.0.0.1:{unused_loopback_port()}"
    channel = f"test-client-base-{os.getpid()}-{next(_channels)}"
    sim = CanSimulator(zcan, [Zlac706CanDevice(1, heartbeat_ms=20),
                              Zlac706CanDevice(2, heartbeat_ms=20)],
                       bus=can.Bus(interface="virtual", channel=channel))
    sim.start()
    daemon = Daemon({
        "gateway": {"name": "gw"},
        "zenoh": {"listen": [endpoint]},
        "buses": [{"name": "can0", "transport": "can", "interface": "virtual",
                   "channel": channel, "reply_margin_ms": 50, "devices": [
                       {"name": "wl", "kind": "zlac706", "id": 1, "heartbeat_ms": 20,
                        "joint": LEFT},
                       {"name": "wr", "kind": "zlac706", "id": 2, "heartbeat_ms": 20,
                        "joint": RIGHT}]}],
        "bases": [BASE],
    })
    try:
        with bc.connect(endpoint, client_id="base-fixture") as client:
            client.base("gw/base").odometry(timeout=DEADLINE_S)  # both wheels read: online
        yield Gateway(endpoint, sim)
    finally:
        daemon.shutdown()
        sim.stop()


@pytest.fixture
def connect(request) -> Iterator[Callable[..., bc.Client]]:
    """``connect(endpoint, suffix)``: a client (id from the test's name), closed after it."""
    clients: list[bc.Client] = []

    def open_client(endpoint: str, suffix: str = "") -> bc.Client:
        name = f"{request.node.name}-{suffix}" if suffix else request.node.name
        clients.append(bc.connect(endpoint, client_id=the_client_id(name)))
        return clients[-1]

    yield open_client
    for client in clients:
        client.close()


def until(condition: Callable[[], object], timeout: float = DEADLINE_S) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.02)


@contextmanager
def at_rest(base: bc.Base) -> Iterator[None]:
    """The block, then the base stopped and its play over."""
    try:
        yield
    finally:
        base.stop()
        until(lambda: not base.status()["driving"])


# -- the blocking face -------------------------------------------------------------------------


def test_a_base_is_found_by_name_and_a_missing_one_is_told(gw, connect) -> None:
    client = connect(gw.endpoint)
    base = client.base("base")
    assert isinstance(base, bc.Base)
    assert (base.gateway, base.name, base.wheels) == ("gw", "base", ("wl", "wr"))
    assert repr(base) == "<Base gw/base (wl, wr)>"
    assert client.base("gw/base").wheels == ("wl", "wr")
    with pytest.raises(bc.UnknownDeviceError, match="no base 'nothing' on gateway gw"):
        client.base("gw/nothing")
    with pytest.raises(bc.UnknownDeviceError, match=r"no base 'nothing' on the gateways up \(gw"):
        client.base("nothing")
    with pytest.raises(bc.NoAnswerError):
        client.base("gw9/base", timeout=1.0)
    with pytest.raises(CommandError, match="not a base name"):
        client.base("gw/ba*se")


def test_enable_drive_odometry_feed_and_stop_on_the_blocking_face(gw, connect) -> None:
    client = connect(gw.endpoint)
    base = client.base("gw/base")
    status = patiently(base.enable)
    assert status["name"] == "base" and status["wheels"] == ["wl", "wr"]
    start = base.odometry(max_age=0.0)
    assert isinstance(start, bc.Odometry) and start.base == "base"
    with at_rest(base):
        status = base.drive(0.3, duration_s=2.0)
        assert status["target"] == {"linear": 0.3, "angular": 0.0}
        assert status["client"] == client.client_id
        xs = []
        for odometry in base.odometry_feed(timeout=DEADLINE_S):
            xs.append(odometry.x)
            if odometry.x > start.x + 0.1:
                break
        assert xs[-1] > start.x + 0.1, "the base did not go forward"
        assert all(b >= a - 1e-6 for a, b in pairwise(xs)), xs  # x grows, step by step
        assert abs(base.odometry().theta - start.theta) < 0.02  # straight ahead
        assert base.status()["driving"] is True
        stopped = base.stop()
        assert stopped["name"] == "base"
        until(lambda: abs(base.odometry(max_age=0.0).linear) < 1e-3)
    assert base.status()["odometry"]["x"] > start.x + 0.1
    base.reset_odometry()
    until(lambda: abs(base.odometry(max_age=0.0).x) < 1e-9)
    assert base.status()["odometry"] == {"x": 0.0, "y": 0.0, "theta": 0.0}


def test_a_drive_is_refused_claimed_while_another_client_holds_the_base(gw, connect) -> None:
    nav, teleop = connect(gw.endpoint, "nav"), connect(gw.endpoint, "teleop")
    mine, theirs = nav.base("base"), teleop.base("gw/base")
    patiently(mine.enable)
    with at_rest(mine):
        with theirs.claim(ttl_s=5.0) as claim:
            assert isinstance(claim, bc.Claim) and claim.lost is None
            with pytest.raises(bc.ClaimedError) as refused:
                mine.drive(0.2)
            assert refused.value.holder == teleop.client_id
            with pytest.raises(bc.ClaimedError), mine.claim(ttl_s=5.0):
                pass
            status = theirs.drive(0.1, duration_s=0.5)  # the holder drives (require_claim)
            assert status["client"] == teleop.client_id
            mine.stop()  # a stop is never refused
        assert mine.drive(0.1, duration_s=0.5)["client"] == nav.client_id  # released on exit
        with theirs.claim(ttl_s=5.0):
            with pytest.raises(bc.ClaimedError):
                mine.drive(0.1)
            assert theirs.release()["name"] == "base"  # given back before the block ends
            assert mine.drive(0.1, duration_s=0.5)["client"] == nav.client_id
        with mine.claim(ttl_s=5.0):  # the block's exit gave nothing back twice
            assert mine.drive(0.1, duration_s=0.5)["client"] == nav.client_id


class Interrupted(Exception):
    """What ends a claim's block here: a Ctrl-C, or the program's own error."""


def test_a_claim_block_an_exception_ends_stops_its_base(gw, connect) -> None:
    """A one-shot drive for 8 s under a claim: a Ctrl-C ending the block released the claim
    and left the base driving out its duration."""
    base = connect(gw.endpoint).base("base")
    patiently(base.enable)
    with at_rest(base):
        with pytest.raises(Interrupted), base.claim(ttl_s=5.0):
            assert base.drive(0.1, duration_s=8.0)["driving"] is True
            raise Interrupted
        until(lambda: not base.status()["driving"], timeout=4.0)  # its ramp down, not 8 s


def test_a_drive_stream_puts_twists_and_stops_the_base_when_it_ends(gw, connect) -> None:
    base = connect(gw.endpoint).base("base")
    patiently(base.enable)
    since = len(gw.sim.recorder.received())
    with base.drive_stream() as stream:
        assert isinstance(stream, bc.DriveStream)
        with pytest.raises(bc.BadCommandError, match="invalid twist for base gw/base"):
            stream.send("fast")  # type: ignore[arg-type]
        deadline = time.monotonic() + DEADLINE_S
        while not all(any(rpm != 0 for rpm in rpms) for rpms in gw.speeds(since).values()):
            assert time.monotonic() < deadline, "the wheels did not turn"
            stream.send(0.4, 0.5)
            time.sleep(0.05)
        assert stream.sent >= 1
    ended = time.monotonic()
    # both wheels at 0 rpm long before the last twist would have timed out (CMD_TIMEOUT_S)
    until(lambda: all(rpms and rpms[-1] == 0 for rpms in gw.speeds(since).values()),
          timeout=CMD_TIMEOUT_S - 0.5)
    assert time.monotonic() - ended < CMD_TIMEOUT_S - 0.5
    with pytest.raises(bc.CommandError, match=r"send\(\) outside the drive stream's with block"):
        stream.send(0.1)
    with pytest.raises(RuntimeError):  # what it was before: caught as that too
        stream.send(0.1)


def test_a_put_on_the_base_cmd_key_runs_and_a_refused_one_is_an_event_naming_it(
    gw, connect
) -> None:
    """A put (``busgate send --put``) is carried out as a device's is: a ``stop`` stops a
    driving base long before its twist's 5 s; a refused one is a ``command_refused`` event
    naming the base, in a slot of its own (``put_reports`` rule 2)."""
    base = connect(gw.endpoint).base("gw/base")
    patiently(base.enable)
    events: list[dict] = []
    session = zenoh.open(session_config(connect=[gw.endpoint]))
    try:
        subscriber = session.declare_subscriber(
            "busgate/gw/events", lambda sample: events.append(json.loads(sample.payload.to_bytes()))
        )
        with at_rest(base):
            base.drive(0.3, duration_s=5.0)
            session.put("busgate/gw/base/base/cmd", b'{"op":"stop"}')
            until(lambda: not base.status()["driving"], timeout=2.0)

        def refused() -> list[dict]:  # put again until the subscriber hears one
            session.put("busgate/gw/base/base/cmd", b'{"op":"fly"}')
            return [e for e in events if e.get("type") == "command_refused"]

        until(refused)
        told = refused()[0]
        assert (told["device"], told["code"]) == ("base", "bad_command"), told
        # The base's slot is its own: bad names put around its refusal do not bury it.
        time.sleep(0.2)  # past the slots' interval (0.1 s): the next of each is told at once
        events.clear()
        for key in ("nosuch", "base", "nosuch", "nosuch", "nosuch"):
            session.put(f"busgate/gw/base/{key}/cmd", b'{"op":"fly"}')
        until(lambda: any(e.get("device") == "base" for e in events))
        subscriber.undeclare()
    finally:
        session.close()


# -- the asyncio face --------------------------------------------------------------------------


def test_the_asyncio_face_drives_and_reads_odometry(gw) -> None:
    async def main() -> None:
        async with bc.aio.connect(gw.endpoint, client_id="base-aio") as client:
            base = await client.base("gw/base")
            assert isinstance(base, bc.aio.Base) and repr(base) == "<aio.Base gw/base (wl, wr)>"
            await patiently_async(base.enable)
            start = await base.odometry(max_age=0.0)
            status = await base.drive(0.0, 1.0, duration_s=2.0)  # on the spot, anticlockwise
            assert status["target"] == {"linear": 0.0, "angular": 1.0}
            turned = None
            async for odometry in base.odometry_feed(timeout=DEADLINE_S):
                if odometry.theta > start.theta + 0.2:
                    turned = odometry
                    break
            assert turned is not None, "the base did not turn"
            assert math.hypot(turned.x - start.x, turned.y - start.y) < 0.02  # on the spot
            assert (await base.stop())["name"] == "base"
            since = len(gw.sim.recorder.received())
            async with base.drive_stream() as stream:
                assert isinstance(stream, bc.aio.DriveStream)
                stream.send(0.2)
                await asyncio.sleep(0.1)
            deadline = time.monotonic() + CMD_TIMEOUT_S - 0.5  # stopped by the block's exit
            while not all(rpms and rpms[-1] == 0 for rpms in gw.speeds(since).values()):
                assert time.monotonic() < deadline, "the wheels did not stop"
                await asyncio.sleep(0.02)
            assert any(rpm != 0 for rpm in gw.speeds(since)[1]), "the stream did not drive"

    asyncio.run(main())


# -- without a gateway -------------------------------------------------------------------------


def test_a_bare_base_name_several_gateways_have_is_ambiguous() -> None:
    status = {"ok": True, "base": {"name": "base", "wheels": ["wl", "wr"]}}
    answers = Answers([Answer(f"busgate/{gw}/base/base/cmd", status, True) for gw in ("g2", "g1")])
    with pytest.raises(bc.AmbiguousError, match="2 gateways have a base 'base'") as refused:
        located(answers, None, "base", "busgate/*/base/base/cmd", 1.0, Keys(), {"g1", "g2"})
    assert refused.value.gateways == ["g1", "g2"]
    found, seen = located(Answers(answers[:1]), None, "base", "…", 1.0, Keys(), set())
    assert (found.gateway, found.name, found.room, seen["wheels"]) == ("g2", "base", "base",
                                                                      ["wl", "wr"])
    with pytest.raises(bc.NoAnswerError):  # nobody answered, and no gateway is known up
        located(Answers(), None, "base", "busgate/*/base/base/cmd", 1.0, Keys(), set())


def test_an_odometry_message_that_is_not_one_is_left_out_with_a_warning(caplog) -> None:
    base = bc.Base(None, Found("gwx", "base", "diff_drive", room="base"), {})  # type: ignore[arg-type]
    good = (b'{"base":"base","ts":1.5,"x":1,"y":0.0,"theta":0.0,"linear":0.0,"angular":0.0,'
            b'"commanded":{"linear":0.1,"angular":0.0}}')
    assert base._message(good) == bc.Odometry(
        base="base", ts=1.5, x=1.0, y=0.0, theta=0.0, linear=0.0, angular=0.0,
        commanded={"linear": 0.1, "angular": 0.0})
    with caplog.at_level(logging.WARNING):
        assert base._message(good.replace(b'"x":1', b'"x":"far"')) is None
        assert base._message(b"not json") is None
    assert caplog.text.count("odometry messages of base 'base' of gateway 'gwx' left out") == 1
    assert base.wheels == ()


@pytest.mark.parametrize(("blocking", "awaiting"), [(bc.Base, bc.aio.Base),
                                                    (bc.DriveStream, bc.aio.DriveStream)],
                         ids=lambda cls: cls.__qualname__)
def test_both_faces_bases_are_twins(blocking, awaiting) -> None:
    assert public(blocking) == public(awaiting)
    for name in sorted(public(blocking)):
        mine = inspect.getattr_static(blocking, name)
        twin = inspect.getattr_static(awaiting, name)
        assert kind(twin) in TWINS[kind(mine)], f"{awaiting.__qualname__}.{name}"
        assert (inspect.signature(function_of(twin)).parameters
                == inspect.signature(function_of(mine)).parameters), name
        assert inspect.getdoc(function_of(twin)), name
    assert inspect.signature(bc.aio.DriveStream.__aexit__) == inspect.signature(
        bc.DriveStream.__exit__)
