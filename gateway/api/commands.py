"""The gateway's public API without zenoh: a client's payload in, a JSON reply out.

The bridge (the only zenoh module) hands payloads here and sends back what comes out; so
every rule of the API is tested without a network. Rules of this file:

1. A payload is refused before anything reaches a bus (``busgate.schemas.payload``) when it
   is over 64 KiB, not UTF-8, not JSON (NaN, infinities and numbers past a double included),
   an object with a key twice, not an object, or not a valid command; the reply says why with
   a stable code
   (``not_utf8``, ``not_json``, ``too_large``, ``bad_command``, ``out_of_range``,
   ``unknown_device`` …) and a human message (for an op the device's key does not take,
   one line naming the op it most likely misspells: ``busgate.schemas.validation``), the code
   from the one mapping of exceptions to codes (``busgate.schemas.replies``), as for what
   the bus refuses later. Whatever the payload, there is exactly one reply: a bug becomes
   ``internal``, logged with its traceback. The payload is parsed once: the command is
   validated from the parsed object, against every op the device's key takes (its kind's
   and the gateway's: ``DEVICE_COMMAND_ADAPTERS``).
2. Claims: a client may hold exclusive motion control of a device; others get ``claimed``
   (naming the holder) until release, the TTL lapses, or the holder's liveliness goes. Reads
   and e-stops are never refused. Each bus's ``Authority`` decides this for every request,
   by the devices its frames address (``busgate.gateway.scheduler.authority``).
3. Deadman: when a client goes, its claims are released, its follow streams stop, and a
   ZLAC706 whose speed it commanded is brought to 0 rpm at once, unless a follow stream, a
   kept target (``ramp_to``) or a play (a trajectory, a base's twist: they ramp) has driven
   it since: its speed is theirs then. A client may
   end a stream itself (``end_follow``): claimed like a follow target, never refused for an
   e-stop. zenoh hands a put (a target) and a query (the end) to different threads, so a
   target sent before the end may be taken after it; it must not start a stream that then
   goes stale. The order holds by construction when the client numbers what it sends a
   stream (``seq``, as the SDK does): a target of that client numbered below the end was
   sent before it and is dropped, whenever it arrives (so is one with the end's own number:
   a client that numbers twice alike cannot be ordered, and nothing moves); one above
   starts a new stream at once.
   Without numbers on both, the client's targets within ``END_FENCE_S`` of the end are
   taken as sent before it. A stop the stream's client sends on ``cmd`` (a pause, 0 rpm:
   its bus ends the stream) fences that client's targets as an unnumbered end does. A
   target and an end taken at once on two of zenoh's threads are handed to the bus in the
   order they passed the fence (one lock over the check and the hand-over), so a target
   checked before the end can never start its stream after it.
4. Nothing here blocks: commands go to the bus runners and come back as futures. One wait,
   bounded: an e-stop, handed to every bus, waits for its first exchange on each bus of this
   process (``runner.let_estops_go``) before its log line, so that the bus threads have the
   interpreter first, not the caller's bookkeeping.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import threading
from collections.abc import Callable
from concurrent.futures import Future, InvalidStateError
from typing import Any, ClassVar

from busgate.errors import BusgateError, BusUnavailableError, CommandError, RefusedError
from busgate.gateway import installed_version
from busgate.gateway.api.group import group_command, scan_requests, scan_result
from busgate.gateway.api.put_reports import client_field
from busgate.gateway.api.taken import estops_when_taken
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import DeviceEvent, Driver, Effect, Follows
from busgate.gateway.scheduler.outcomes import cancelled_by_estop, settled
from busgate.gateway.scheduler.runner import BusRunner, let_estops_go
from busgate.schemas.api import (
    DEVICE_COMMAND_ADAPTERS,
    MAX_VERSION,
    BusGroupMove,
    BusScan,
    Claim,
    EndFollow,
    JointCommand,
    JointFollow,
    Release,
    ResetEstop,
)
from busgate.schemas.payload import MAX_PAYLOAD, decode_object, ok_reply
from busgate.schemas.replies import error_reply, failure_reply
from busgate.schemas.validation import command_from_object, cut, follow_target_from, shown

#: A scan that could take longer than this on its bus is refused: ask for fewer ids.
SCAN_MAX_S = 4.0
#: The room a scan gets beyond its planned duration before its last probes are dropped:
#: twice the plan (it shares the bus with commands, ticks and polls) plus this.
SCAN_SLACK_S = 1.0
#: After a client's ``end_follow`` without ``seq``, or its stop of its own stream, how long
#: its targets for that device are taken as sent before the end (rule 3; with ``seq`` on the
#: end and the target, not at all). zenoh hands a put and a query to their callbacks on
#: different threads, so a target sent just before the end can be taken after it; on a
#: loaded host that was seen past 100 ms (CI), so the fence is wider. A client that streams
#: again that soon after ending loses its first half second of targets: the SDK numbers its
#: targets and ends (``seq``) and meets the fence only after a stop (which carries none).
END_FENCE_S = 0.5

log = logging.getLogger(__name__)


def answered(handler: Callable[..., Future]) -> Callable[..., Future]:
    """Whatever ``handler`` meets, a reply: a refusal's own code, or ``internal`` (logged with
    its traceback) for a bug. Every query gets exactly one answer, never silence."""

    @functools.wraps(handler)
    def wrapper(self: GatewayApi, *args: Any) -> Future:
        try:
            return handler(self, *args)
        except Exception as exc:
            return settled(failure_reply(exc, log, f"{handler.__name__}{args[:1]!r}"))

    return wrapper


class GatewayApi:
    """Every device and bus of the gateway, as clients see them."""

    def __init__(
        self,
        name: str,
        runners: dict[str, BusRunner],
        *,
        on_event: Callable[[DeviceEvent], None] = lambda event: None,
    ) -> None:
        self.name = name
        self.runners = runners
        self.on_event = on_event
        #: E-stops handed to the buses so far: a command taken off the network before one
        #: and carried out later (a play's lane, a ROS 2 message's decoding) is refused.
        self.estops = 0
        self.devices: dict[str, tuple[BusRunner, Driver]] = {
            device: (runner, driver)
            for runner in runners.values()
            for device, driver in runner.drivers.items()
        }
        #: Device → the client whose command keeps it moving (its driver's ``deadman`` op).
        self._deadman_clients: dict[str, str] = {}
        self._stream_clients: dict[str, str] = {}  # device → client of its follow stream
        #: Device → (client, when, seq) of its last ``end_follow``: which of that client's
        #: targets were sent before it (rule 3).
        self._ended: dict[str, tuple[str | None, float, int | None]] = {}
        self._fence = threading.Lock()  # a target's check and hand-over vs an end (rule 3)
        #: The base whose drive plays a device (a wheel), if one does: set by the bridge.
        self.driven_by: Callable[[str], str | None] = lambda device: None

    # -- commands ---------------------------------------------------------------------------

    @answered
    def command(self, device: str, payload: bytes) -> Future:
        """Validate a device command and hand it to its bus, which authorises it (by the
        devices its frames address) and carries it out; the future's result is the reply
        dict. Refusals come back as an already finished future."""
        fields = decode_object(payload)
        runner, driver = self._device(device)
        op, client = fields.get("op"), fields.get("client")
        gateway_op = self._GATEWAY_OPS.get(op) if isinstance(op, str) else None
        if gateway_op is not None:
            reply = gateway_op(self, runner, device, fields)
            return reply if isinstance(reply, Future) else settled(reply)
        adapter = DEVICE_COMMAND_ADAPTERS[driver.kind]
        command = command_from_object(adapter, fields, driver.kind)
        in_si = isinstance(command, JointCommand)
        if in_si:  # the kind's own command, in its raw units (refused beyond a limit)
            command = command_from_object(adapter, _kind_command(driver, command), driver.kind)
        self._require_no_estop_since_taken()
        refused = None
        if driver.deadman and command.op == driver.deadman.op and client:
            refused = self._hold_deadman(device, client)  # before it goes: a client gone
        if client:
            self._fence_own_streams(runner, driver, command, client)
        submitted = runner.submit(device, command, client)  # while it runs stops it
        if refused is not None:
            submitted.add_done_callback(refused)
        return _chained(submitted, _joint_reply) if in_si else _mapped(submitted)

    def _fence_own_streams(
        self, runner: BusRunner, driver: Driver, command: Any, client: str
    ) -> None:
        """Rule 3: ``command`` of ``client`` stops devices (a pause, 0 rpm …), judged as its
        bus judges it (``BusWork.plan_command`` ends their streams): the streams of those that
        are ``client``'s end, and its targets sent before, taken after, start nothing."""
        try:
            effects = driver.effects_of(driver.frames_of(command))
        except BusgateError:  # its bus refuses it, with the reason: it stops nothing
            return
        for stopped in runner.authority.addressed(effects, Effect.STOP):
            if self._stream_clients.get(stopped.name) == client:
                with self._fence:
                    self._stream_clients.pop(stopped.name, None)
                    self._ended[stopped.name] = (client, now(), None)

    def _hold_deadman(self, device: str, client: str) -> Callable[[Future], None]:
        """``client``, who sends ``device`` a one-shot speed, is the one whose going stops it;
        unless its bus refuses the command (nothing sent): a client never let move the device
        must not stop it when it goes. What to call with the command's future: the one before
        holds it again if refused."""
        before = self._deadman_clients.get(device)
        self._deadman_clients[device] = client

        def unless_refused(done: Future) -> None:
            refused = not done.cancelled() and isinstance(
                done.exception(), (RefusedError, CommandError)
            )
            if refused and self._deadman_clients.get(device) == client:
                if before is None:
                    self._deadman_clients.pop(device, None)
                else:
                    self._deadman_clients[device] = before

        return unless_refused

    def _claim(self, runner: BusRunner, device: str, fields: dict[str, Any]) -> dict[str, Any]:
        request = Claim.model_validate(fields)
        authority = runner.authority
        authority.claims.claim(device, request.client, request.ttl_s, authority.clock())
        self._event(device, "claimed", client=request.client, ttl_s=request.ttl_s)
        return ok_reply(claimed_by=request.client, expires_in_s=request.ttl_s)

    def _release(self, runner: BusRunner, device: str, fields: dict[str, Any]) -> dict[str, Any]:
        request = Release.model_validate(fields)
        authority = runner.authority
        released = authority.claims.release(device, request.client, authority.clock())
        if released:  # a release of nothing held tells nobody of anything
            self._event(device, "released", client=request.client)
        return ok_reply(released=released)

    def _end_follow(self, runner: BusRunner, device: str, fields: dict[str, Any]) -> dict[str, Any]:
        """The stream ends on the bus thread (``stream_stopped``, then ``stale_stream``)."""
        request = EndFollow.model_validate(fields)
        # Ending a stream moves nothing: the claim alone, never refused for an e-stop.
        runner.authority.judge(
            device, Effect.SETTING, request.client, require_claim=request.require_claim
        )
        with self._fence:
            self._stream_clients.pop(device, None)
            self._ended[device] = (request.client, now(), request.seq)
            runner.stop_stream(device, f"ended by {request.client}" if request.client else "ended")
        return ok_reply(ended=True)

    def _reset_estop(self, runner: BusRunner, device: str, fields: dict[str, Any]) -> Future:
        """Out of the e-stop on the bus thread (``Driver.reset_estop``); the claim alone is
        judged: the reset moves nothing."""
        request = ResetEstop.model_validate(fields)
        runner.authority.judge(
            device, Effect.SETTING, request.client, require_claim=request.require_claim
        )
        self._event(device, "estop_reset", **client_field(request.client))
        return _mapped(runner.reset_estop(device))

    #: The ops every device's ``cmd`` key takes besides its kind's own (``GatewayCommand``):
    #: a reply, or a future of one.
    _GATEWAY_OPS: ClassVar[
        dict[str, Callable[[GatewayApi, BusRunner, str, dict[str, Any]], dict[str, Any] | Future]]
    ] = {
        "claim": _claim,
        "release": _release,
        "end_follow": _end_follow,
        "reset_estop": _reset_estop,
    }

    def follow(self, device: str, payload: bytes) -> dict[str, Any] | None:
        """A follow stream's new target; ``None`` when taken, else the error reply."""
        try:
            runner, driver = self._device(device)
            fields = decode_object(payload)
            target, follows = _follow_target(driver, fields)
            client, seq = fields.get("client"), fields.get("seq")
            with self._fence:
                if self._sent_before_the_end(device, client, seq):
                    return None
                self._refuse_while_playing(runner, device, "a follow stream")
                runner.authority.judge(
                    device, Effect.MOTION, client, require_claim=fields.get("require_claim") is True
                )
                if client is not None:
                    self._stream_clients[device] = client
                self._deadman_clients.pop(device, None)  # rule 3: the stream moves it now
                runner.follow(device, target, follows)
            return None
        except Exception as exc:
            return failure_reply(exc, log, f"follow on {device}")

    def _refuse_while_playing(self, runner: BusRunner, device: str, what: str) -> None:
        """``busy`` while a base drives ``device`` (a wheel), from its twist taken on, or
        while it plays a trajectory: ``what`` would fight it over its target. Each named as
        what it is: a wheel told to cancel a trajectory had none to cancel (an audit)."""
        base = self.driven_by(device)
        if base is not None:
            raise RefusedError(
                "busy",
                f"{device} is a wheel of base {base}, which is driving it: stop the base first "
                f"({what} would take one wheel from it)",
            )
        if not runner.plays.playing(device):
            return
        raise RefusedError(
            "busy",
            f"{device} is playing a trajectory: cancel it first ({what} and a trajectory would "
            "fight over its target)",
        )

    def ramp_to(
        self, device: str, fields: dict[str, Any], client: str, claim_ttl_s: float
    ) -> dict[str, Any] | None:
        """A joint's new target (``{"joint": x}`` or ``{"joint_velocity": v}``) from a client
        that sends a target once and expects it kept, as a ROS controller does: ``client``
        holds ``device`` while its targets come (each renews the claim for ``claim_ttl_s``;
        another client's claim refuses it), and the device ramps to the target within its
        joint's limits and stays there (``BusRunner.ramp``). ``None`` when taken, else the
        error reply: an e-stopped device is refused ``estopped``, one on a bus that is down
        ``bus_unavailable``, and neither is claimed."""
        try:
            runner, driver = self._device(device)
            target, follows = _follow_target(driver, fields)
            self._refuse_while_playing(runner, device, "a target kept")
            if not runner.owner.is_open:
                raise BusUnavailableError(f"bus {runner.name} is down: {device} cannot move")
            authority = runner.authority
            authority.judge(device, Effect.MOTION, client)  # claimed by another, e-stopped
            if authority.claims.hold(device, client, claim_ttl_s, authority.clock()):
                self._event(device, "claimed", client=client, ttl_s=claim_ttl_s)
            self._deadman_clients.pop(device, None)  # rule 3: the ramp moves it now
            runner.ramp(device, target, follows)
            return None
        except Exception as exc:
            return failure_reply(exc, log, f"ramp on {device}")

    def _sent_before_the_end(self, device: str, client: str | None, seq: int | None) -> bool:
        """A target of the client that ended ``device``'s stream, come after the end but sent
        before it (it took another of zenoh's threads): it must not start the stream again
        (rule 3). By its ``seq`` against the end's when both have one, else by the fence."""
        ended = self._ended.get(device)
        if ended is None or ended[0] != client:
            return False
        _, when, end_seq = ended
        if seq is not None and end_seq is not None:
            return seq <= end_seq
        return now() - when < END_FENCE_S

    def stop_every_bus(self) -> list[Future]:
        """Stop every device of the gateway, ahead of everything; never refused: every bus's
        e-stop handed over, and let go (rule 4: they have the interpreter first). Told by the
        caller (the bridge's ``put_reports``, rate-limited)."""
        self.estops += 1  # first: what was taken before it is judged by it (``intake`` rule 5)
        stopped = [runner.estop() for runner in self.runners.values()]
        let_estops_go(self.runners.values())
        return stopped

    def reset_every_bus(self, sender: str | None = None) -> tuple[list[Future], list[str]]:
        """Every device of the gateway out of its e-stop, holding still
        (``Driver.reset_estop``), but those claimed by a client other than ``sender``, which
        are their holder's to reset (a device's own ``reset_estop`` from another is refused
        ``claimed``). The buses' futures, and the devices not reset; a bus whose reset fails
        (down, its worker down) says so in a line of its own, its devices still e-stopped.
        Told by the caller (the bridge's ``put_reports``, rate-limited)."""
        reset: list[Future] = []
        not_reset: list[str] = []
        for runner in self.runners.values():
            held = frozenset(
                d for d in runner.drivers if runner.authority.holder(d) not in (None, sender)
            )
            future = runner.reset_estop(skip=held)
            future.add_done_callback(functools.partial(_tell_bus_not_reset, runner.name))
            reset.append(future)
            not_reset += sorted(held)
        return reset, not_reset

    @answered
    def bus_command(self, bus: str, payload: bytes) -> Future:
        """``group_move`` or ``scan`` on one bus."""
        runner = self.runners.get(bus)
        if runner is None:
            raise RefusedError("unknown_bus", f"no bus '{shown(bus)}' on gateway {self.name}")
        fields = decode_object(payload)
        op = fields.get("op")
        handler = self._BUS_OPS.get(op) if isinstance(op, str) else None
        if handler is None:
            raise RefusedError("bad_command", "bus ops are group_move and scan")
        return handler(self, runner, fields)

    def _require_no_estop_since_taken(self) -> None:
        """``estopped`` for a command taken off the network before the latest e-stop and
        validated while it came (``taken``): a reset right after the e-stop would otherwise
        let it move a device. Asked as it goes to its bus, after its validation."""
        if estops_when_taken(self.estops) != self.estops:
            raise cancelled_by_estop()

    def _group_move(self, runner: BusRunner, fields: dict[str, Any]) -> Future:
        request = BusGroupMove.model_validate(fields)
        for target in request.targets:
            if target.device not in runner.drivers:
                raise RefusedError(
                    "unknown_device", f"no device '{shown(target.device)}' on this bus"
                )
        first, command = group_command(runner, request)  # the kind's schema checks targets
        self._require_no_estop_since_taken()
        return _mapped(runner.submit(first, command, request.client))

    def _scan(self, runner: BusRunner, fields: dict[str, Any]) -> Future:
        request = BusScan.model_validate(fields)
        protocol = runner.timing.protocol
        probes = scan_requests(protocol, request.ids)
        planned_s = sum(runner.timing.worst_case(p) + runner.timing.gap_s for p in probes)
        if planned_s > SCAN_MAX_S:
            most = int(len(probes) * SCAN_MAX_S / planned_s)
            raise RefusedError(
                "out_of_range",
                f"a scan of {len(probes)} ids takes up to "
                f"{planned_s:.1f} s on bus {runner.name}; ask for at most "
                f"{most} ids at a time",
            )
        scanning = runner.scan(probes, start_by=now() + 2 * planned_s + SCAN_SLACK_S)
        return _chained(scanning, lambda outcomes: ok_reply(found=scan_result(protocol, outcomes)))

    _BUS_OPS: ClassVar[dict[str, Callable[[GatewayApi, BusRunner, dict[str, Any]], Future]]] = {
        "group_move": _group_move,
        "scan": _scan,
    }

    # -- clients ----------------------------------------------------------------------------

    def client_left(self, client: str) -> None:
        """Deadman: the client's liveliness token went away."""
        for runner in self.runners.values():
            for device in runner.authority.claims.drop_client(client):
                self._event(device, "released", client=client, reason="client gone")
        for device, owner in list(self._stream_clients.items()):
            if owner == client:
                del self._stream_clients[device]
                runner, _ = self.devices[device]
                runner.stop_stream(device, f"client {client} gone")
        with self._fence:  # its ends order nothing more: its next targets start streams
            for device, ended in list(self._ended.items()):
                if ended[0] == client:
                    del self._ended[device]
        for device, owner in list(self._deadman_clients.items()):
            if owner == client:
                del self._deadman_clients[device]
                runner, driver = self.devices[device]
                if runner.plays.playing(device):  # a play moves it now (a base's, a trajectory)
                    continue
                assert driver.deadman is not None
                runner.submit(device, driver.parse(driver.deadman.stop))
                self._event(device, "stopped", client=client, reason="client gone")

    # -- information ------------------------------------------------------------------------

    def info(self) -> dict[str, Any]:
        """The ``info`` reply (a version past what a client takes is cut: ``MAX_VERSION``)."""
        return ok_reply(
            gateway=self.name,
            version=cut(installed_version(), MAX_VERSION - 1),
            buses=[
                {
                    "name": name,
                    "protocol": runner.timing.protocol,
                    "devices": [
                        {
                            "name": device,
                            "kind": driver.kind,
                            "id": driver.device_id,
                            "joint": driver.joint.describe(),
                            "state": runner.states.get(device),
                        }
                        for device, driver in runner.drivers.items()
                    ],
                }
                for name, runner in self.runners.items()
            ],
        )

    def _device(self, device: str) -> tuple[BusRunner, Driver]:
        try:
            return self.devices[device]
        except KeyError:
            message = f"no device '{shown(device)}' on gateway {self.name}"
            raise RefusedError("unknown_device", message) from None

    def _event(self, device: str, type_: str, **fields: Any) -> None:
        self.on_event(DeviceEvent(device, type_, fields))


def _kind_command(driver: Driver, command: JointCommand) -> dict[str, Any]:
    """The device kind's own command for a joint command in SI, with its ``require_claim``
    (its client goes to the bus beside it, as every command's does: ``command``)."""
    joint = driver.joint
    if command.position is not None:
        fields = joint.move_command(command.position)
        steps = driver.why_positions_are_steps()
        if steps is not None:
            raise RefusedError("bad_command", f"joint {joint.name} moves to places: {steps}")
    else:
        assert command.velocity is not None  # the model's rule: one of them
        fields = joint.turn_command(command.velocity)
    return {**fields, **command.model_dump(include={"require_claim"})}


def _joint_reply(result: dict[str, Any]) -> dict[str, Any]:
    """A joint command's reply: the device's state, and its joint's on its own."""
    return ok_reply(**result, joint=result["state"]["joint"])


def _follow_target(driver: Driver, fields: dict[str, Any]) -> tuple[float, Follows]:
    """A follow payload's target in the family's units, and whether it is a position or a
    speed: the kind's own payload validated by its driver, or a joint's (``joint``,
    ``joint_velocity``: SI) as asked, unclamped (the stream's limiter holds it within the
    joint's limits) once the nearest payload the kind takes passed its driver's checks (a
    ZLAC706 streams what its mode takes)."""
    if "joint" not in fields and "joint_velocity" not in fields:
        return driver.follow_target(fields), driver.follow_carries(fields)
    request = follow_target_from(JointFollow, fields)  # its client and seq too
    payload, raw = driver.joint.kind_follow(request.joint, request.joint_velocity)
    driver.follow_target(payload)
    return raw, driver.follow_carries(payload)


def _tell_bus_not_reset(bus: str, done: Future) -> None:
    """A warning when the reset of ``bus`` failed: the reset's own line and event speak for
    every bus, and its devices are still e-stopped."""
    failure = None if done.cancelled() else done.exception()
    if failure is not None:
        log.warning(
            "e-stop reset: bus %s not reset, its devices still e-stopped (reset again once it "
            "is back): %s",
            bus,
            failure,
        )


def _mapped(submitted: Future) -> Future:
    """The runner's future (result dict, or a ``BusgateError``) as a reply envelope future."""
    return _chained(submitted, lambda result: ok_reply(**result))


def _chained(submitted: Future, make: Callable[[Any], dict[str, Any]]) -> Future:
    """A reply future made from ``submitted``'s outcome; cancelling it (the bridge answered
    without waiting) cancels ``submitted``, so a job that has not started never will."""
    answer: Future = Future()
    submitted.add_done_callback(lambda done: _settle(answer, done, make))
    answer.add_done_callback(lambda done: done.cancelled() and submitted.cancel())
    return answer


def _settle(answer: Future, done: Future, make: Callable[[Any], dict[str, Any]]) -> None:
    if done.cancelled():
        return  # cancelled through ``answer``, which has been answered already
    error = done.exception()
    try:
        reply = error_reply(error) if error is not None else make(done.result())
    except Exception as exc:
        log.exception("making a reply failed")
        reply = error_reply(exc)
    with contextlib.suppress(InvalidStateError):
        answer.set_result(reply)


__all__ = ["MAX_PAYLOAD", "GatewayApi", "decode_object"]
