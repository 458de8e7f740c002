"""What a client of either face is and does, each method written once: a method that waits is
a generator of the steps it waits for (``steps.py``), which the blocking face (``sync.py``)
runs waiting and the asyncio face (``aio.py``) awaiting (``faces.py`` makes it each face's
method); the devices, buses, claims and follow streams it hands out are in ``devices.py``,
trajectories in ``trajectories.py``, bases in ``bases.py``.

A face's module only names its classes (``faces.Blocking`` or ``faces.Awaiting``, and the
classes it hands out) and the ways into and out of a block (``with`` or ``async with``). Here
``Device``, ``Bus``, ``Trajectory``, ``Joint`` and ``Base`` are type variables that each face
binds to its own classes, so that a type checker knows ``bc.connect(…).device(…)`` for a
``bc.Device`` and ``await c.device(…)`` of an asyncio client for a ``bc.aio.Device``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from busgate.client import trajectories
from busgate.client.base import FleetDevice, Found, Shared, raw_payload
from busgate.client.bases import find_base
from busgate.client.core import LEFT_OPEN_WAIT_S, Core
from busgate.client.devices import DeviceBase
from busgate.client.errors import NoAnswerError
from busgate.client.faces import Face, feeding, taking, waiting
from busgate.client.feeds import latest_parsed, parsed_feed
from busgate.client.keys import check_name
from busgate.client.messages import Answers, JointsMessage, joints_message
from busgate.client.steps import Call, Items, Steps, Wait
from busgate.client.trajectories import Watch, one_gateway, play_body
from busgate.errors import CommandError
from busgate.schemas.api import InfoReply

Device = TypeVar("Device", bound=DeviceBase[Any, Any, Any])
Bus = TypeVar("Bus")
Trajectory = TypeVar("Trajectory")
Joint = TypeVar("Joint")
Base = TypeVar("Base")
C = TypeVar("C", bound=Callable[..., Any])


@taking(Core)
def connecting(*args: Any, **options: Any) -> Steps[Shared]:
    """A client of every gateway reachable through ``endpoints`` (a zenoh router, or a
    gateway's own listen endpoint), as ``client_id``; use it as a context manager, or
    ``close`` it. ``lease_s``: how soon gateways give up on this client when it freezes or
    is cut off (its claims and streams go with it). ``timeout``: the default wait of every
    command. ``ConnectError`` when no session can be opened."""
    core = yield Call(
        functools.partial(Core, *args, **options),
        unwanted=Core.close,
        left_wait_s=LEFT_OPEN_WAIT_S,
    )
    return Shared(core)


class ClientBase(Face, Generic[Device, Bus, Trajectory, Joint, Base]):
    """One program's connection to a fleet of gateways, of either face."""

    _Device: Callable[[Shared, Found], Device]
    _Bus: Callable[[Shared, Found], Bus]
    _Trajectory: Callable[[Shared, Watch, dict[str, Any]], Trajectory]
    _Base: Callable[[Shared, Found, dict[str, Any]], Base]

    def __init__(self, shared: Shared) -> None:
        self._shared = shared
        self.client_id = shared.core.client_id
        self.timeout = shared.core.timeout_s

    @waiting
    def close(self) -> Steps[None]:
        """Release nothing explicitly (claims and streams end with the liveliness token the
        session holds) and close the session."""
        yield Call(self._shared.close)

    @waiting
    def gateways(self, timeout: float = 1.0) -> Steps[dict[str, InfoReply]]:
        """Every gateway that answers ``info`` within ``timeout``: its info, by name, as the
        model ``busgate.schemas.api.InfoReply`` (``info.buses[0].devices``; ``info["buses"]``
        too, as scripts written against the earlier release read it). A gateway whose reply
        does not validate is left out, with a warning naming it."""
        return (yield Wait(self._shared.gateways(timeout), timeout, "info of the gateways"))

    @waiting
    def devices(self, timeout: float = 1.0) -> Steps[list[FleetDevice]]:
        """Every device of the gateways ``gateways(timeout)`` gives, one ``FleetDevice`` each
        (gateway, bus, name, kind, id and last state), by gateway then name."""
        return (yield Wait(self._shared.devices(timeout), timeout, "devices of the gateways"))

    def _found(self, name: str, what: str, timeout: float | None, asked: str) -> Steps[Found]:
        waited = self.timeout if timeout is None else timeout
        return (yield Wait(self._shared.find(name, what, waited), waited, asked))

    @waiting
    def device(self, name: str, *, timeout: float | None = None) -> Steps[Device]:
        """The device ``name``: ``"gw/la1"``, or a bare ``"la1"`` that one gateway has; a
        joint's name finds its device."""
        found = yield from self._found(name, "device", timeout, f"finding {name}")
        return self._Device(self._shared, found)

    @waiting
    def joint(self, name: str, *, timeout: float | None = None) -> Steps[Joint]:
        """The joint ``name`` (``"gw/lift"``, or a bare ``"lift"`` that one gateway has), or
        the joint of the device ``name``: ``device(name).joint``."""
        found = yield from self._found(name, "device", timeout, f"finding {name}")
        joint: Joint = self._Device(self._shared, found).joint
        return joint

    @waiting
    def joints(
        self, gateway: str, timeout: float = 2.0, *, max_age: float = 1.0
    ) -> Steps[JointsMessage]:
        """The latest joints message of ``gateway`` (every joint of it in SI, published when
        any was read again): one received in the last ``max_age`` seconds, else the next
        within ``timeout``."""
        latest = self._shared.latest(self._joints_key(gateway), gateway, timeout, max_age)
        parse = functools.partial(joints_message, gateway=gateway)
        message = yield from latest_parsed(latest, parse, timeout, max_age)
        if message is None:
            raise NoAnswerError(f"no joints message of {gateway} within {timeout:g} s")
        return message

    @feeding
    def joints_feed(self, gateway: str, timeout: float = 5.0) -> Items[JointsMessage]:
        """Each new joints message of ``gateway``, as it comes, until ``timeout`` seconds."""
        parse = functools.partial(joints_message, gateway=gateway)
        yield from parsed_feed(self._shared.core, self._joints_key(gateway), parse, timeout)

    def _joints_key(self, gateway: str) -> str:
        return self._shared.core.keys.joints(check_name("gateway", gateway))

    @waiting
    def bus(self, name: str, *, timeout: float | None = None) -> Steps[Bus]:
        """The bus ``name``: ``"gw/uart0"``, or a bare ``"uart0"`` that one gateway has."""
        found = yield from self._found(name, "bus", timeout, f"finding bus {name}")
        return self._Bus(self._shared, found)

    @waiting
    def base(self, name: str, *, timeout: float | None = None) -> Steps[Base]:
        """The base ``name`` (a gateway's ``[[bases]]``: two wheels driven as one): ``"gw/base"``,
        or a bare ``"base"`` that one gateway has (asked of every gateway: ``info`` lists no
        bases). ``UnknownDeviceError`` when there is none of that name."""
        waited = self.timeout if timeout is None else timeout
        finding = find_base(self._shared, name, waited)
        found, status = yield Wait(finding, waited, f"finding base {name}")
        return self._Base(self._shared, found, status)

    def on_gateways(self, callback: Callable[[str, bool], None]) -> Callable[[], None]:
        """``callback(gateway, alive)`` as each gateway comes (``True``: first for each one up
        now) and goes (``False``: its liveliness token went, as when its process ended), on
        zenoh's thread (it must not block; ``loop.call_soon_threadsafe`` brings it to an
        asyncio loop); returns what stops it."""
        return self._shared.core.on_gateways(_callable(callback))

    @waiting
    def estop(self, gateway: str | None = None) -> Steps[None]:
        """Stop every device of ``gateway``, or of every gateway (``None``, or ``"*"``); no gateway
        refuses it. Devices stay e-stopped until each is reset (``reset_estop``) or enabled
        again (``Device.enable``). The put goes first, never slowed by a check; then
        ``UnknownGatewayError`` when no gateway of that name is up (known at once for one
        this client has seen). Not a gateway's name (``""``): ``ValueError``, nothing sent."""
        checked = self._shared.estop(gateway)
        yield Wait(checked, self.timeout, f"whether {gateway} is up (e-stop put)")

    @waiting
    def reset_estop(self, gateway: str) -> Steps[None]:
        """Every device of ``gateway`` (a name: never the fleet) out of its e-stop, as
        ``Device.reset_estop``: a put of this client's id on ``<prefix>/<gateway>/estop/reset``
        (the gateway answers nothing), checked as ``estop`` checks."""
        checked = self._shared.reset_estop(gateway)
        yield Wait(checked, self.timeout, f"whether {gateway} is up (reset put)")

    @waiting
    def play(
        self,
        devices: list[str],
        points: list[dict[str, Any]],
        *,
        id: str | None = None,  # noqa: A002 - the contract's field name
        timeout: float | None = None,
        **options: Any,
    ) -> Steps[Trajectory]:
        """Have the devices' gateway play a trajectory (``points`` as the trajectory key
        takes them; ``options``: ``start_at``, ``interpolation``, ``path_tolerance``,
        ``goal_tolerance``, ``goal_time_s``); the devices must be on one gateway. Returns
        once it is accepted, with its ``start_at`` and ``end_at``."""
        if isinstance(devices, str) or not devices:  # a str's letters were each a name
            raise CommandError(
                f"devices is a list of their names (['la1', 'la2']), not {devices!r}"
            )
        waited = self.timeout if timeout is None else timeout
        finding = self._shared.find_all(devices, "device", waited)
        found = yield Wait(finding, waited, "finding the devices")
        gateway = one_gateway(found)
        body = play_body(self.client_id, id, [f.name for f in found], points, options)
        started = trajectories.start(self._shared, gateway, body, waited)
        watch, accepted = yield Wait(started, waited, f"play of {body['id']} on {gateway}")
        return self._Trajectory(self._shared, watch, accepted)

    # -- raw keys (the command-line tools', and anything the typed surface lacks) ---------------

    @waiting
    def query(
        self, key: str, payload: Any = None, *, timeout: float | None = None
    ) -> Steps[Answers]:
        """Every answer to a get on the key expression ``key``, as it came (nothing added to
        the payload, no error raised for an error reply; one past ``MAX_REPLY`` unread:
        ``core.answer_of``): bytes or text as given, a dict as JSON. ``.timed_out`` says zenoh
        stopped waiting for a queryable."""
        waited = self.timeout if timeout is None else timeout
        return (yield Wait(self._shared.query(key, payload, waited), waited, f"query on {key}"))

    def put(self, key: str, payload: Any) -> None:
        """A put on ``key`` (bytes or text as given, a dict as JSON)."""
        self._shared.core.put(key, raw_payload(payload) or b"")

    def subscribe_raw(
        self, key: str, callback: Callable[[str, bytes, int], None]
    ) -> Callable[[], None]:
        """``callback(key, payload, ns)`` for every sample on ``key``: its bytes as they came
        and its time (ns since the epoch: zenoh's timestamp where it has one, else its
        arrival), on zenoh's thread; returns what ends the subscription (``busgate record``)."""
        return self._shared.core.subscribe_timed(key, _callable(callback))

    def subscribe(self, key: str, callback: Callable[[str, Any], None]) -> Callable[[], None]:
        """``callback(key, body)`` for every sample on ``key``, on zenoh's thread (it must not
        block: hand over and return; ``loop.call_soon_threadsafe`` hands over to an asyncio
        loop); returns what ends the subscription."""
        return self._shared.subscribe(key, _callable(callback))


def _callable(callback: C) -> C:
    """``callback`` when it can be called; ``CommandError`` at once, not a traceback logged
    for each sample later (an audit's ``subscribe(key, None)``)."""
    if not callable(callback):
        raise CommandError(f"a callback is a function, not {type(callback).__name__}")
    return callback
