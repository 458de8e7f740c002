"""What the sync and asyncio faces of the SDK share below their methods (``surface.py``):
finding a device or bus by name, the commands the typed helpers send, telemetry as models,
follow payloads, and the claims a client holds. Everything here returns values or
``concurrent.futures.Future``s, which the shared methods wait for (``steps.py``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ValidationError

from busgate.client.claims import ClaimLease, Timers
from busgate.client.core import Core
from busgate.client.errors import (
    AmbiguousError,
    ClaimLostError,
    NoAnswerError,
    UnknownGatewayError,
    error_for,
)
from busgate.client.feeds import Latest
from busgate.client.follow import FollowSender
from busgate.client.keys import Keys, check_name, is_name, split_name
from busgate.client.messages import (
    MAX_WAIT_S,
    UNPARSED,
    Answer,
    JointInfo,
    dumps,
    published_naming,
    seconds,
    then,
)
from busgate.errors import CommandError
from busgate.schemas.api import FOLLOW_MODELS, TELEMETRY_MODELS, InfoReply
from busgate.schemas.families import FAMILIES
from busgate.schemas.payload import largest_published
from busgate.schemas.telemetry import TelemetryEnvelope
from busgate.schemas.validation import closest, likeliest

log = logging.getLogger(__name__)

#: The most names an unknown one's refusal lists when none is close to it (a fleet's dozens
#: would bury the message).
SUGGESTED_NAMES_MAX = 12
#: The most names a misspelling is told it may mean, when several are as close.
TIED_SHOWN = 3


@dataclass(frozen=True)
class Found:
    """A device, bus or base of one gateway: its name, and its kind (device, base) or
    protocol (bus); a device's joint as its gateway's ``info`` describes it (``None``: it
    describes none); the room of its keys (``dev``; ``base`` for a base, ``bases.py``)."""

    gateway: str
    name: str
    kind: str
    joint: JointInfo | None = None
    room: str = "dev"


@dataclass(frozen=True)
class FleetDevice:
    """One device of the fleet as its gateway's ``info`` lists it (``Client.devices``): its
    gateway, bus, name, kind and id, its last state (its kind's telemetry model, as
    ``Device.state()`` gives it; ``None`` before the gateway had one), and its joint (name,
    type, unit, calibration and limits)."""

    gateway: str
    bus: str
    name: str
    kind: str
    id: int
    state: TelemetryEnvelope | None
    joint: JointInfo | None = None


def gateway_infos(answers: list[Answer]) -> dict[str, dict[str, Any]]:
    """Each gateway's ``info`` among ``answers``, by name, as it came: what finding a device
    and knowing a gateway is up need (its names), however the rest of the reply reads. An
    answer whose ``gateway`` is no gateway's name (``*`` would address every gateway's
    devices), or not the name it answered under, is left out."""
    return {
        answer.body["gateway"]: answer.body
        for answer in answers
        if answer.ok
        and isinstance(answer.body, dict)
        and is_name(gateway := answer.body.get("gateway"))
        and answered_as(answer, gateway)
    }


def answered_as(answer: Answer, gateway: object) -> bool:
    """Whether ``answer`` came on ``gateway``'s own ``info`` key (a peer answering on its own
    key may not speak for another gateway)."""
    return answer.key.split("/")[-2:] == [gateway, "info"]


def info_models(answers: list[Answer], keys: Keys) -> dict[str, InfoReply]:
    """Each gateway's ``info`` among ``answers`` as an ``InfoReply``, by name, in order. A
    reply that is not one (an error, even one whose body is an info; not JSON; a field or
    device kind this SDK does not know; one naming another gateway than its key) leaves its
    sender out, with a warning naming it: one bad peer never fails the fleet's answer.
    Validated as the JSON it came as (an enum's value is its text there)."""
    infos: dict[str, InfoReply] = {}
    for answer in answers:
        try:
            info = InfoReply.model_validate_json(json.dumps(answer.body))
        except UNPARSED as exc:  # a ValidationError is a ValueError; a deep reply, recursion
            log.warning(
                "gateway %.64r left out: its info reply is not an InfoReply (%s)",
                keys.gateway_of(answer.key),
                _first_error(exc),
            )
            continue
        if not answer.ok:  # zenoh's error reply (which names no key): its body an info
            log.warning(
                "gateway %.64r left out: its info reply came as an error reply", info.gateway
            )
            continue
        if not answered_as(answer, info.gateway):
            log.warning(
                "gateway %.64r left out: its info reply names gateway %.64r",
                keys.gateway_of(answer.key),
                info.gateway,
            )
            continue
        infos[info.gateway] = info
    return dict(sorted(infos.items()))


def _first_error(exc: Exception) -> str:
    """What is wrong with a reply, in a line: the first of pydantic's errors and their count."""
    if not isinstance(exc, ValidationError):
        return str(exc)[:200]
    first = exc.errors(include_url=False, include_input=False)[0]
    where = ".".join(str(part) for part in first["loc"]) or "the reply"
    more = exc.error_count() - 1
    return f"{where}: {first['msg']}" + (f"; {more} more" if more else "")


def fleet_devices(infos: dict[str, InfoReply]) -> list[FleetDevice]:
    """Every device of ``infos``, one each, by gateway then name."""
    devices = [
        FleetDevice(
            gateway, bus.name, device.name, device.kind, device.id, device.state, device.joint
        )
        for gateway, info in infos.items()
        for bus in info.buses
        for device in bus.devices
    ]
    return sorted(devices, key=lambda d: (d.gateway, d.name, d.bus))


def locate(infos: dict[str, dict[str, Any]], name: str, what: str, asked: str) -> Found:
    """The one device (``what="device"``) or bus named ``name`` in ``infos``; a device is
    named by its own name or its joint's. Errors name the gateways that answered (on
    ``asked``), or those that have it if several do."""
    gateway, leaf = split_name(name)
    if not infos:
        raise NoAnswerError(f"no gateway answered on {asked}")
    found = [
        found
        for gateway_name, info in sorted(infos.items())
        for found in _named(gateway_name, info, what, leaf)
        if gateway is None or gateway_name == gateway
    ]
    if not found:
        code = "unknown_device" if what == "device" else "unknown_bus"
        raise error_for(code)(
            f"no {what} {leaf!r} on the gateways that answered ({', '.join(sorted(infos))}"
            f"{_meant(infos, gateway, leaf, what)})"
        )
    if len(found) > 1:
        names = [f.gateway for f in found]
        raise AmbiguousError(
            f"{len(found)} gateways have a {what} {leaf!r} ({', '.join(names)}): name one, "
            f"e.g. {names[0]}/{leaf}",
            gateways=names,
        )
    return found[0]


def _named(gateway: str, info: dict[str, Any], what: str, leaf: str) -> list[Found]:
    """What ``info`` lists under ``leaf``: the buses of that name, or the devices of that
    name or whose joint has it. Entries that are not of the shape a gateway sends (a bus that
    is no object, a device named with a wildcard) are passed over, as is a device of a kind
    this SDK does not know, with a warning (a newer gateway's: it could not be driven)."""
    buses = [bus for bus in _listed(info, "buses") if is_name(bus.get("name"))]
    if what == "bus":
        return [
            Found(gateway, leaf, str(bus.get("protocol")))
            for bus in buses
            if bus.get("name") == leaf
        ]
    devices = [
        device
        for bus in buses
        for device in _listed(bus, "devices")
        if is_name(device.get("name")) and leaf in (device.get("name"), _joint_name(device))
    ]
    found = []
    for device in devices:
        if device.get("kind") in FAMILIES:
            found.append(Found(gateway, device["name"], device["kind"], joint_info(device)))
        else:
            log.warning(
                "device %s/%s left out: its kind %.40r is one this SDK does not know",
                gateway,
                device["name"],
                device.get("kind"),
            )
    return found


def _meant(infos: dict[str, dict[str, Any]], gateway: str | None, leaf: str, what: str) -> str:
    """What a name no gateway has likely meant: for a gateway named, one that has ``leaf``
    (the closest to the one named); else the name of theirs closest to ``leaf``, else the
    names they have (a few)."""
    if gateway is not None:  # a gateway named: one that has ``leaf``, if another has it
        holders = [name for name, info in sorted(infos.items()) if _named(name, info, what, leaf)]
        meant = closest(gateway, holders) or (holders[0] if holders else None)
        offered = "" if meant is None else f"did you mean {meant}/{leaf}?"
        if gateway not in infos:
            return f"; no gateway {gateway!r}" + (f": {offered}" if offered else "")
        if offered:
            return f"; {offered}"
    names = {
        name
        for gateway_name, info in infos.items()
        if gateway is None or gateway_name == gateway
        for name in _names(info, what)
    }
    return name_hint(leaf, names)


def name_hint(leaf: str, names: Iterable[str]) -> str:
    """``; did you mean 'la1'?`` for the one of ``names`` that ``leaf`` likely misspells (up
    to ``TIED_SHOWN`` of them, as close as each other), else ``; they have …`` (a few), else
    nothing."""
    names = sorted(set(names))
    if meant := likeliest(leaf, names):
        shown = [repr(name) for name in meant[:TIED_SHOWN]]
        said = shown[0] if len(shown) == 1 else f"{', '.join(shown[:-1])} or {shown[-1]}"
        return f"; did you mean {said}?"
    return f"; they have {', '.join(names)}" if 0 < len(names) <= SUGGESTED_NAMES_MAX else ""


def _names(info: dict[str, Any], what: str) -> list[str]:
    """Every name ``info`` answers to for ``what``: its buses', or its devices' and joints'."""
    buses = [bus for bus in _listed(info, "buses") if is_name(bus.get("name"))]
    if what == "bus":
        return [bus["name"] for bus in buses]
    devices = [device for bus in buses for device in _listed(bus, "devices")]
    return [
        str(name)
        for device in devices
        for name in (device.get("name"), _joint_name(device))
        if is_name(name)
    ]


def _listed(entry: dict[str, Any], field: str) -> list[dict[str, Any]]:
    """The objects listed under ``field`` of a reply's ``entry`` (none when it lists none)."""
    listed = entry.get(field)
    return [item for item in listed if isinstance(item, dict)] if isinstance(listed, list) else []


def _joint_name(device: dict[str, Any]) -> Any:
    joint = device.get("joint")
    return joint.get("name") if isinstance(joint, dict) else None


def joint_info(device: dict[str, Any]) -> JointInfo | None:
    """The joint an ``info`` reply's ``device`` describes, or ``None`` when it describes none
    (a gateway of an earlier release) or one this SDK cannot read (a warning names it)."""
    joint = device.get("joint")
    if joint is None:
        return None
    try:
        return JointInfo.model_validate_json(json.dumps(joint))
    except UNPARSED as exc:
        log.warning(
            "the joint of device %.64r is left undescribed: %s",
            device.get("name"),
            _first_error(exc),
        )
        return None


def as_body(command: Any) -> dict[str, Any]:
    """A command as the JSON object sent: a dict as given, a schemas model dumped."""
    if isinstance(command, BaseModel):
        return command.model_dump(mode="json", exclude_unset=True)
    if isinstance(command, dict):
        return dict(command)
    raise CommandError(f"a command is a dict or a busgate.schemas model, not {type(command)}")


def raw_payload(payload: bytes | str | dict[str, Any] | None) -> bytes | None:
    """A raw query's or put's payload: bytes and text as given, a dict as JSON."""
    if payload is None or isinstance(payload, bytes):
        return payload
    return payload.encode() if isinstance(payload, str) else dumps(payload)


def failed_as(future: Future, make: Callable[[BaseException], BaseException]) -> Future:
    """``future``, its exception (if any) replaced by ``make(exception)``."""
    mapped: Future = Future()

    def settle(done: Future) -> None:
        error = done.exception()
        if error is None:
            mapped.set_result(done.result())
        else:
            mapped.set_exception(make(error))

    future.add_done_callback(settle)
    return mapped


def settled(value: Any) -> Future:
    """A future already done with ``value``."""
    done: Future = Future()
    done.set_result(value)
    return done


def known_gateway(gateway: str, known: set[str], outcome: str) -> None:
    """Nothing when ``gateway`` is among the gateways ``known``; else the
    ``UnknownGatewayError`` that names them, saying the ``outcome`` (what came of it)."""
    if gateway not in known:
        up = sorted(known)
        raise UnknownGatewayError(
            f"no gateway {gateway!r} is up: {outcome} (the gateways that answer: "
            f"{', '.join(up) or 'none'})",
            gateway=gateway,
            gateways=up,
        )


def scan_command(ids: list[int] | None) -> dict[str, Any]:
    return {"op": "scan"} | ({} if ids is None else {"ids": ids})


def reenable_command(kind: str) -> dict[str, Any]:
    """The command that lets a device of ``kind`` move again after an e-stop."""
    return dict(FAMILIES[kind].schema.REENABLE_COMMAND)


class Shared:
    """What every face of one client uses: the core, the timers of its claims, its claims."""

    def __init__(self, core: Core) -> None:
        self.core = core
        self.timers = Timers()
        #: This client's claims, by the command key they are held on (a device's, a base's).
        self.leases: dict[str, ClaimLease] = {}
        self._latest: dict[str, Latest] = {}
        self._latest_lock = threading.Lock()
        self._leases_lock = threading.Lock()  # ``claim``'s look and its lease, as one

    def close(self) -> None:
        self.timers.close()
        self.core.close()

    # -- finding things ------------------------------------------------------------------------

    def infos(self, gateway: str | None, timeout_s: float) -> Future:
        """A future of ``{gateway: info}`` of every gateway answering (or just ``gateway``),
        each as it came (``gateway_infos``)."""
        key = self.core.keys.info(gateway or "*")
        return then(self.core.ask(key, timeout_s=timeout_s), gateway_infos)

    def gateways(self, timeout_s: float) -> Future:
        """A future of ``{gateway: InfoReply}`` of every gateway answering within
        ``timeout_s`` whose reply is one (``info_models``)."""
        keys = self.core.keys
        asked = self.core.ask(keys.info("*"), timeout_s=timeout_s)
        return then(asked, lambda answers: info_models(answers, keys))

    def devices(self, timeout_s: float) -> Future:
        """A future of every device of those gateways, as ``FleetDevice``s in order."""
        return then(self.gateways(timeout_s), fleet_devices)

    def find_all(self, names: list[str], what: str, timeout_s: float) -> Future:
        """A future of the ``Found`` device or bus (``what``) of each name (``"gw/x"`` or a
        bare ``"x"``), from one ``info`` query of the gateways they name (all, when any name
        is bare)."""
        named = {split_name(name)[0] for name in names}  # None: a bare name
        gateway = next(iter(named)) if len(named) == 1 else None
        if gateway is not None and gateway not in self.core.gateways_up:
            gateway = None  # not seen up: every gateway's, to name those up if it is none
        asked = self.core.keys.info(gateway or "*")

        def located(infos: dict[str, Any]) -> list[Found]:
            if gateway is None and (infos or self.core.gateways_up):  # else: no answer at all
                for each in (g for g in named if g is not None):
                    known_gateway(each, {*infos, *self.core.gateways_up}, "nothing was sent")
            return [locate(infos, name, what, asked) for name in names]

        return then(self.infos(gateway, timeout_s), located)

    def find(self, name: str, what: str, timeout_s: float) -> Future:
        """A future of the ``Found`` device or bus ``name``."""
        return then(self.find_all([name], what, timeout_s), lambda found: found[0])

    # -- devices (and bases: ``bases.py``) ---------------------------------------------------

    def command_key(self, found: Found) -> str:
        """Where a device or a base (``found.room``) takes commands, claims included."""
        keys = self.core.keys
        if found.room == "base":
            return keys.base(found.gateway, found.name, "cmd")
        return keys.device(found.gateway, found.name, "cmd")

    def lease_of(self, found: Found) -> ClaimLease | None:
        """This client's claim on the device or base ``found``, held or lost, if it has one."""
        return self.leases.get(self.command_key(found))

    def send(self, device: Found, command: Any, timeout_s: float | None) -> Future:
        """A device's command (or a base's). While this client has a claim on it (held or lost), it
        asks the gateway to refuse it unless the claim holds (``require_claim``): a lapsed
        claim is never silently done without, and reads and stops still go through, as the
        gateway's authority decides. Once the SDK knows the claim is lost, the gateway's
        refusal is told as ``ClaimLostError`` with the reason, and nothing is sent while the
        claim's gateway is gone (nothing could reach it)."""
        body = as_body(command)
        key = self.command_key(device)
        lease = self.leases.get(key)
        if lease is None:
            return self.core.command(key, body, timeout_s=timeout_s)
        body.setdefault("require_claim", True)
        if lease.lost is not None and device.gateway not in self.core.gateways_up:
            lease.check()
        sent = self.core.command(key, body, timeout_s=timeout_s)
        return failed_as(sent, lambda exc: lease.lost_error(exc))

    def claim(self, device: Found, ttl_s: float) -> ClaimLease:
        """Claim the device or base ``found`` (a ``ClaimLease`` to ``take``). One claim block
        a device at a time, this client's: the gateway keeps one claim a client, so an inner
        block's exit gave the outer's back, and another client moved the device inside it
        (``CommandError``; a block whose claim was lost or given back does not count)."""
        key = self.command_key(device)
        with self._leases_lock:
            held = self.leases.get(key)
            if held is not None and not held.ended and held.lost is None:
                raise CommandError(
                    f"{device.gateway}/{device.name} is claimed already by a claim block of "
                    "this client: one block a device (the gateway holds one claim a client)"
                )
            lease = ClaimLease(self.core, self.timers, device.gateway, device.name, ttl_s, key)
            self.leases[key] = lease
        return lease

    def unclaim(self, lease: ClaimLease) -> Future:
        """Give the claim back: a future of the release, or of ``ClaimLostError`` when the
        claim was lost meanwhile (nothing to give back, and the block must hear of it); of
        ``None`` when it was given back already (``Base.release``)."""
        if self.leases.get(lease.key) is lease:
            del self.leases[lease.key]
        ended = lease.ended
        released = lease.release()
        if released is not None:
            return released
        if ended:
            return settled(None)
        lost: Future = Future()
        try:
            lease.check()
        except ClaimLostError as exc:
            lost.set_exception(exc)
        return lost

    def telemetry(self, device: Found, payload: bytes) -> Any:
        """A state message of ``device`` as the telemetry model of its kind; ``None`` when it
        is not one, or names another device (a warning names the gateway, the first time:
        ``published_naming``)."""
        model = TELEMETRY_MODELS[device.kind]
        return published_naming(model, payload, "states", device.gateway, "device", device.name)

    def latest(self, key: str, gateway: str, timeout: float, max_age: float) -> Latest:
        """The latest message on ``key``, one of ``gateway``'s, subscribed at the first ask
        and kept until the client closes (one subscription per key however often asked);
        asked for one within ``max_age`` s, else the next within ``timeout`` s, both checked
        here (``CommandError`` for NaN, a negative …), and refused by a closed client, whose
        last message is no news."""
        seconds("timeout", timeout, 0, MAX_WAIT_S)
        seconds("max_age", max_age, 0, math.inf)
        self.core.require_open(key)
        with self._latest_lock:
            latest = self._latest.get(key)
            if latest is None:
                latest = self._latest[key] = Latest(self.core, key, gateway)
            return latest

    def follow(self, device: Found, model: Any = None) -> FollowSender:
        """The puts of a new follow stream to ``device`` (``follow.py``), each target checked
        against ``model`` (the follow target of the device's kind when ``None``)."""
        key = self.core.keys.device(device.gateway, device.name, "follow")
        return FollowSender(
            self.core,
            self.timers,
            key,
            FOLLOW_MODELS[device.kind] if model is None else model,
            lambda: self.lease_of(device),
            device.name,
        )

    def end_follow(self, device: Found, sender: FollowSender) -> Future:
        """Put the stream's last target, end the stream (``end_follow``: no ``stream_stale``
        event) and undeclare its publisher."""
        sender.close()
        return self.send(device, {"op": "end_follow", "seq": self.core.next_seq()}, None)

    # -- buses --------------------------------------------------------------------------------

    def bus_command(self, bus: Found, command: dict[str, Any], timeout_s: float) -> Future:
        key = self.core.keys.bus(bus.gateway, bus.name, "cmd")
        return self.core.command(key, command, timeout_s=timeout_s)

    # -- gateways and raw keys ------------------------------------------------------------------

    def query(self, key: str, payload: Any, timeout_s: float) -> Future:
        """Every answer to a get on any key expression, the payload as given."""
        return self.core.ask(key, raw_payload(payload), timeout_s=timeout_s)

    def subscribe(
        self,
        key: str,
        callback: Callable[[str, Any], None],
        ended: Callable[[], None] | None = None,
    ) -> Callable[[], None]:
        """``callback(key, body)`` for each sample on ``key`` (zenoh's thread: it may not
        block); ``body`` is the sample's JSON, or ``None`` when it is not JSON or is larger
        than any message a gateway publishes on that key (``largest_published``); then
        ``ended()`` (``Core.subscribe``)."""

        def sink(sample_key: str, payload: bytes) -> None:
            body = None
            if len(payload) <= largest_published(sample_key):
                with contextlib.suppress(*UNPARSED):
                    body = json.loads(payload)
            callback(sample_key, body)

        return self.core.subscribe(key, sink, ended)

    def estop(self, gateway: str | None) -> Future:
        """E-stop one gateway, or every gateway of the fleet (``None``, or ``"*"`` as the
        key names it): see ``to_gateway``."""
        if gateway is None or gateway == "*":
            self.core.put(self.core.keys.estop("*"), self.signed(), urgent=True)
            return settled(None)
        return self.to_gateway(self.core.keys.estop, gateway)

    def reset_estop(self, gateway: str) -> Future:
        """Have one gateway reset its e-stop: see ``to_gateway``. It goes as an e-stop does:
        zenoh keeps the order of puts of one priority only, and an e-stop put after a reset
        must never overtake it."""
        return self.to_gateway(self.core.keys.estop_reset, gateway)

    def to_gateway(self, key: Callable[[str], str], gateway: str) -> Future:
        """Put this client's id on ``key(gateway)`` at once, with an e-stop's priority, then
        check that a gateway of that name is up: the future's ``None``, or
        ``UnknownGatewayError`` naming those that answer. The put comes first, so that a
        safety stop is never slowed by a lookup (a put nobody takes is harmless). A gateway
        whose liveliness token this client has seen is known at once; else every gateway's
        ``info`` is asked for (just after a connect the tokens are still coming, and a
        liveliness query then answers from that partial view: none). Not a gateway's name
        (``""``, ``None``, a wildcard): ``CommandError``, a ``ValueError``, nothing put."""
        where = key(check_name("gateway", gateway))
        self.core.put(where, self.signed(), urgent=True)
        if gateway in self.core.gateways_up:
            return settled(None)
        return then(
            self.infos(None, self.core.timeout_s),
            lambda infos: known_gateway(
                gateway, {*infos, *self.core.gateways_up}, f"the put on {where} reached none"
            ),
        )

    def signed(self) -> bytes:
        """The body of a put to gateways: this client's id."""
        return dumps({"client": self.core.client_id})
