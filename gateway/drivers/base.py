"""The device driver contract: sans-I/O, a JSON command becomes requests, replies become state.

Rules of this file (and of every driver):

1. A driver never touches a port, a clock or a thread. The runner passes ``now`` in, sends the
   requests a driver plans and hands back the replies; so drivers are tested with plain calls.
2. A driver owns the device's state as the gateway knows it: what was commanded (targets,
   mode), what was measured (from replies or heartbeats), whether it is online, its faults.
3. What a client should hear about (a fault raised or cleared, online/offline, a reboot
   detected) is queued with ``emit`` and drained by the runner, never published from here.
4. Every request a driver makes goes through ``Request.of`` so the codec checks every value
   and says which reply to expect.
"""

from __future__ import annotations

import abc
import enum
import json
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import Any, ClassVar, Literal, NamedTuple

from pydantic import TypeAdapter

from busgate.errors import CommandError, RefusedError
from busgate.gateway.bus.request import Request
from busgate.schemas.families import PROTOCOLS, WireProtocol
from busgate.schemas.joints import Joint, JointDeclaration, Quantity
from busgate.schemas.validation import command_from_json, follow_target_from

#: What a family's driver must define beyond the abstract methods (see ``Driver``).
FAMILY_PARTS = ("follow_target", "follow_request", "follow_sample", "probe", "setpoints")

#: Consecutive unanswered requests after which a device is marked offline.
OFFLINE_AFTER = 3
#: Added to the time between two readings of a device before a change between them is judged
#: one the device cannot make (a wheel's jump, a ZLAC706's counter back at 0): a reading is
#: dated when its bus thread takes it, and two taken in one look, after a held-up thread, are
#: dated nearly together however far apart they were read.
READING_DATE_SLACK_S = 0.05


class Effect(enum.IntEnum):
    """What a frame does to the devices it addresses; the gateway authorises by it."""

    READ = 0  # asks, changes nothing: never refused
    STOP = 1  # stops or releases: never refused
    SETTING = 2  # changes how the device works: needs the claim
    MOTION = 3  # may move the device: needs the claim, refused while e-stopped


#: What a follow stream's targets are, raw: positions or speeds (``Driver.follows``).
Follows = Literal["position", "velocity"]

#: The devices a frame addresses: a set of ids, or ``EVERY`` device of the bus (broadcast).
EVERY = None
Addressed = frozenset[int] | None


class Setpoint(NamedTuple):
    """What a frame sets on the device with ``device_id``, in the units its family declares
    (``busgate.schemas.joints``): a position (raw), a speed or an effort. ``value`` is
    ``None`` when the frame sets a position the gateway cannot know (a preset stored in the
    device): a limited joint refuses it."""

    device_id: int
    quantity: Quantity
    value: float | None


class IdChange(NamedTuple):
    """A frame gives the device it addresses at ``device_id`` the id ``new_id``: a
    ``set_id``, a raw write of the id, a factory reset."""

    device_id: int
    new_id: int


@dataclass(frozen=True, slots=True)
class DeviceEvent:
    """Something about a device that clients should hear: ``type`` plus fields."""

    device: str
    type: str
    fields: dict[str, Any]


@dataclass(frozen=True, slots=True)
class Deadman:
    """A client's command that keeps a device moving after the client has gone (a speed), and
    the command that stops it when the client's liveliness token goes away."""

    op: str
    stop: str


@dataclass(frozen=True, slots=True)
class FrameRules:
    """A family's rules per frame, as its frames module states them: what a frame does, the
    setpoints it carries, the ids it gives (``Driver.effect``, ``setpoints``, ``id_changes``)."""

    effect: Callable[[Any], Effect]
    setpoints: Callable[[Any], Iterable[Setpoint]]
    id_changes: Callable[[Any], Iterable[IdChange]]


class RuledFrames:
    """Before ``Driver`` in a family's driver whose per-frame answers are its
    ``frame_rules``: the same three methods, once for every such family."""

    frame_rules: ClassVar[FrameRules]

    def effect(self, frame: object) -> Effect:
        return self.frame_rules.effect(frame)

    def setpoints(self, frames: Sequence[object]) -> list[Setpoint]:
        return [s for frame in frames for s in self.frame_rules.setpoints(frame)]

    def id_changes(self, frames: Sequence[object]) -> list[IdChange]:
        return [c for frame in frames for c in self.frame_rules.id_changes(frame)]


class Driver(abc.ABC):
    """One device on a bus, as the gateway knows it.

    Its kind, codec and command schema are the registry's (``busgate.schemas.families``):
    the entry of its ``protocol`` says them, so a driver does not repeat them.
    """

    #: The commands that make a device ready to follow (sent by ``busgate bench``, and planned
    #: by the bus budget before it sizes a follow frame).
    follow_preparation: ClassVar[tuple[str, ...]] = ()
    #: What a client's going away stops (``None``: nothing it sent outlives it).
    deadman: ClassVar[Deadman | None] = None
    #: How many devices' follow targets one frame can carry (1: no coalescing).
    follow_group_limit: ClassVar[int] = 1
    #: The id a frame sent to every device carries (``None``: the protocol has none).
    broadcast_id: ClassVar[int | None] = None
    #: The protocol this class drives, by its name in the registry (each family's driver sets
    #: it; ``busgate.gateway.drivers.families.DRIVERS`` is the table of them).
    protocol: ClassVar[str]

    def __init__(
        self,
        name: str,
        device_id: int,
        *,
        follow_period_s: float = 0.02,
        joint: Joint | None = None,
    ) -> None:
        self.name = name
        self.device_id = device_id
        self.follow_period_s = follow_period_s
        #: The device as a joint: SI units, calibration, limits (its config's table, or the
        #: family's raw joint).
        self.joint = joint or Joint.of(name, self.joint_declaration(), None)
        self.online = False
        self.was_online = False
        self.last_reply: float | None = None
        self.misses = 0
        #: Settings the device confirmed, by what they set: written again after a reboot.
        self.applied_settings: dict[object, Request] = {}
        #: A reboot was seen and ``restore`` has not been sent yet.
        self.restore_pending = False
        #: Set by ``safe_stop`` (a gateway e-stop), cleared when ``reenable_op`` is planned.
        self.estop_latched = False
        #: Whether the device was driving its motor when the e-stop latched: what
        #: ``reset_estop`` puts back (``note_estop``).
        self.driving_before_estop = False
        self._events: list[DeviceEvent] = []

    # -- what the registry says of this driver -------------------------------------------------

    @classmethod
    def protocol_entry(cls) -> WireProtocol:
        """The registry's entry of the protocol this class drives (``protocol``)."""
        return PROTOCOLS[cls.protocol]

    @classmethod
    def joint_declaration(cls) -> JointDeclaration:
        """What the family's raw fields mean as a joint (its schema module's ``JOINT``)."""
        return cls.protocol_entry().schema.JOINT  # type: ignore[no-any-return]

    @property
    def kind(self) -> str:
        return self.protocol_entry().kind

    @property
    def codec(self) -> ModuleType:
        return self.protocol_entry().codec

    @property
    def schema(self) -> ModuleType:
        return self.protocol_entry().schema

    @property
    def reenable_op(self) -> str:
        """The command that lets the device move again after an e-stop, as the refusals name
        it: the kind's ``REENABLE_COMMAND`` (its schema module)."""
        return json.dumps(self.schema.REENABLE_COMMAND, separators=(",", ":"))

    @property
    def commands(self) -> TypeAdapter[Any]:
        """The kind's own commands (the gateway adds ``claim`` and ``release``)."""
        return self.schema.COMMAND_ADAPTER

    # -- planning ---------------------------------------------------------------------------

    @property
    def estopped(self) -> bool:
        """Motion is refused (``estopped``) until ``reenable_op``: the gateway e-stopped the
        device. Read from any thread; changed on the bus thread only."""
        return self.estop_latched

    def estopped_error(self) -> RefusedError:
        """The refusal of motion while e-stopped, saying how to recover."""
        return RefusedError(
            "estopped",
            f'{self.name} is e-stopped: send {{"op":"reset_estop"}} to reset it (it holds '
            f"still in the power state it had), or {self.reenable_op} to let it move again",
        )

    def parse(self, text: str | bytes) -> Any:
        """A JSON command for this kind, validated (``CommandError`` when refused)."""
        return command_from_json(self.commands, text, self.kind)

    @abc.abstractmethod
    def frames_of(self, command: Any) -> Sequence[object]:
        """The frames that carry out ``command``, without planning it: no state changes, so
        any thread may ask (the gateway authorises a command by them before planning it)."""

    @abc.abstractmethod
    def effect(self, frame: object) -> Effect:
        """What ``frame`` does to the devices it addresses."""

    def addressed(self, frame: object) -> Addressed:
        """The ids ``frame`` addresses: each target of a group frame, its own id, or
        ``EVERY`` device for a broadcast (or a frame with no id: a point-to-point line)."""
        targets = getattr(frame, "targets", None)
        if targets is not None:
            return frozenset(target.device_id for target in targets)
        device_id: Any = getattr(frame, "device_id", self.broadcast_id)
        return EVERY if device_id == self.broadcast_id else frozenset({device_id})

    def setpoints(self, frames: Sequence[object]) -> list[Setpoint]:
        """What ``frames`` (one command's, its ``frames_of``) set on each device they address:
        a position, a speed or an effort, in the family's units (``JointDeclaration``). The
        authority judges these against each device's joint before anything is planned; a
        frame that sets none of them (a read, a setting) adds none. Any thread may ask: the
        driver's state is only read (a relative target is judged from the position known)."""
        return []

    def id_changes(self, frames: Sequence[object]) -> list[IdChange]:
        """The ids ``frames`` (one command's) give the devices they address; the authority
        refuses one another device of the bus has. By default none: a family whose frames
        never change an id."""
        return []

    def follow_mode_ids(self, frames: Sequence[object]) -> frozenset[int]:
        """The ids of the devices ``frames`` (one command's) send a follow-mode target, which
        the manual asks at a fixed period (an Inspire LA's follow and group follow): a command
        that sends one is judged against the device's follow stream and period. By default
        none: a family with no such mode."""
        return frozenset()

    def effects_of(self, frames: Sequence[object]) -> list[tuple[Addressed, Effect]]:
        """What each of ``frames`` does, and to which ids."""
        return [(self.addressed(frame), self.effect(frame)) for frame in frames]

    def plan(self, command: Any) -> list[Request]:
        """The requests that carry out ``command`` now, its frames built here (the runner
        builds them once, judges their effects and plans them: ``plan_frames``)."""
        return self.plan_frames(command, self.frames_of(command))

    @abc.abstractmethod
    def plan_frames(self, command: Any, frames: Sequence[object]) -> list[Request]:
        """The requests that carry out ``command`` by ``frames`` (its ``frames_of``), and the
        state they change; ``CommandError`` when the device's state forbids it (e.g. a ZLAC706
        position target before enable), nothing changed then."""

    @abc.abstractmethod
    def poll(self) -> list[Request]:
        """The requests of one telemetry poll (may be empty: heartbeats only)."""

    @abc.abstractmethod
    def safe_stop(self) -> list[Request]:
        """The requests that put the device in its safe state (e-stop, shutdown); each
        driver's calls ``note_estop`` first."""

    def note_estop(self) -> None:
        """Before a safe stop: whether the device is driving now, unless an e-stop already
        latched (a second one must not forget what the first stopped)."""
        if not self.estopped:
            self.driving_before_estop = self.driving()

    def driving(self) -> bool:
        """Whether the motor is driven (power stage, torque, enable) as far as the gateway
        knows; not known counts as not."""
        return False

    def reset_estop(self) -> list[Request]:
        """Out of the gateway's e-stop, back in the power state the device had before it and
        holding still: driving again with its target where it is (``hold_still``), or still
        off with the latch cleared (``stay_off``). Nothing moves until a new command; nothing
        is sent when the device is not e-stopped."""
        if not self.estopped:
            return []
        if self.driving_before_estop:
            self.driving_before_estop = False
            return self.hold_still()
        self.stay_off()
        return []

    def hold_still(self) -> list[Request]:
        """The requests that drive the motor again with its target at its present position
        (or a speed of 0), planned as its own commands are."""
        self.stay_off()
        return []

    def stay_off(self) -> None:
        """The latch cleared, the motor left undriven: a new command may drive it."""
        self.estop_latched = False

    def moved_by(self, frame: object) -> None:  # noqa: B027 - optional hook
        """``frame``, sent by another device's command (a group or broadcast frame), went out
        and moves this device too: what it does to the state nobody's answer will tell. By
        default nothing (the device's next reading tells)."""

    def sent_position_raw(self) -> float | None:
        """The position target (raw) the device was last sent by a frame nobody answers, when
        its telemetry's ``target`` does not say it yet (an Inspire LA's follow tick, whose
        target the next poll tells): where a stream starts from. By default ``None``: a
        family's telemetry says every target it sent (a DS servo's SYNC WRITE's)."""
        return None

    def why_positions_are_steps(self) -> str | None:
        """Why a position target sent now would be a step from where the device is, not the
        place a joint's position names (``None``: it is a place, as every family's is but a
        ZLAC706's in relative position mode)."""
        return None

    def position_to_hold(self, raw: float | None) -> int | None:
        """``raw``, the position read last, as the target ``hold_still`` may give: ``None``
        when none was read, or when it lies beyond the joint's limits (a reading that cannot
        be right, or a device pushed past them): no target the gateway sends goes there, and
        none goes to a limit the device is not at either."""
        if raw is None:
            return None
        low, high = self.joint.raw_limits
        return round(raw) if low <= raw <= high else None

    def switched_off(self) -> None:
        """A command switched the motor off: a reset that follows leaves it off."""
        self.driving_before_estop = False

    def init(self) -> list[Request]:
        """The requests that (re)initialise the device after the bus (re)opens or it rebooted:
        by default, one poll, which also tells whether it answers."""
        return self.poll()

    # A family's driver defines the parts named in ``FAMILY_PARTS`` (the registry's check
    # names one that is missing); the defaults serve drivers that are not a family's.

    def follow_target(self, payload: dict[str, Any]) -> float:
        """A follow stream's payload (``{"position": P}``…) validated: the value it sets, in
        the family's units (a raw position, or a speed); ``CommandError`` if bad."""
        raise CommandError(f"{self.kind} has no follow stream")

    @property
    def turning_on(self) -> bool:
        """Whether its motor is known to be on, so that a speed sent now is ramped from the
        speed it turns at (``BusWork``'s one-shot speeds); a family that cannot tell: on."""
        return True

    @property
    def follows(self) -> Follows | None:
        """What its follow stream's targets are now, raw: positions or speeds (its joint's; a
        family whose stream carries both may say which by the device's mode, ``None`` in a
        mode that takes neither). A target is judged with what the device follows then, and
        goes only to a stream of that (``BusWork.start_stream``); a stream whose device
        follows something else now ends (``tickers`` rule 7)."""
        return self.joint.follows

    def follow_carries(self, payload: Mapping[str, Any]) -> Follows:
        """What a follow payload of its kind carries, by its field: a position or a speed
        (the kind of target its ``follow_target`` judged it as)."""
        return "position" if self.joint.declaration.follow_position in payload else "velocity"

    def unsent(self) -> None:  # noqa: B027 - optional hook
        """Frames planned for this device were taken out before they went (their command
        expired, was withdrawn, or its bus went down): what they would have set is not to
        be counted on. By default nothing (a driver that plans by what queued writes will
        set forgets them)."""

    def follow_payload(self, payload: dict[str, Any]) -> Any:
        """``payload`` as the kind's ``FollowTarget`` model (``CommandError`` if it is not one)."""
        return follow_target_from(self.schema.FollowTarget, payload)

    @classmethod
    def follow_request(cls, targets: Sequence[tuple[Driver, float]]) -> Request:
        """One frame carrying the latest follow targets (``follow_target``'s values) of up to
        ``follow_group_limit`` devices of this kind on one bus."""
        raise CommandError(f"{cls.protocol_entry().kind} has no follow stream")

    @staticmethod
    def follow_sample(t_s: float, index: int) -> dict[str, Any]:
        """A follow payload for device ``index`` at ``t_s`` seconds into a smooth trajectory:
        what benchmarks stream, and what the bus budget sizes follow frames with."""
        raise CommandError("this driver has no follow stream")

    # -- what spans the devices of a bus -----------------------------------------------------

    @classmethod
    def probe(cls, device_id: int) -> Request:
        """The most harmless request a device with ``device_id`` answers (a scan's probe)."""
        raise CommandError(f"{cls.__qualname__} has no scan probe")

    def group_entry(self, position: int, time_ms: int | None) -> dict[str, Any]:
        """This device's entry in its kind's ``group_move`` op (``CommandError``: the kind
        has no group move, or cannot take these values)."""
        raise CommandError(f"a {self.protocol_entry().name} bus has no group move")

    @classmethod
    def heartbeat_frames(cls, device_id: int) -> tuple[object, ...]:
        """What a device sends unasked at each heartbeat (none by default)."""
        return ()

    def stale_stream(self) -> list[Request]:
        """Requests to send when this device's follow stream went stale (e.g. 0 rpm)."""
        return []

    def keepalive(self, now: float) -> tuple[float, Request] | None:
        """``(period, request)`` the device needs while in its current state, or ``None``."""
        return None

    def refreshes_keepalive(self, request: Request) -> bool:
        """Whether ``request``, answered, does what the keep-alive does (a follow tick's speed
        write does, on CAN): the next keep-alive is then due a full period later."""
        return False

    # -- interpreting -----------------------------------------------------------------------

    @abc.abstractmethod
    def apply(self, request: Request, reply: tuple[object, ...], now: float) -> dict[str, Any]:
        """Update the state from ``reply`` to ``request``: the events of the answer, each one
        matched to ``request.expected`` by the bus owner (none for a frame without a reply;
        a device that answered has been marked ``heard`` already). Return what the command's
        answer should carry besides the state (e.g. ``{"data": "e803"}`` for a read).
        ``DeviceRefusedError`` when the answer says the device did not do it: the state is
        left as it was, and the command is answered ``device_refused``."""

    def went(self, frame: object) -> None:  # noqa: B027 - optional hook
        """``frame``, this device's request or a frame carrying it a target, went on the
        wire: told before its answer is applied (``apply``) or found missing (``missed``).
        By default nothing follows from it."""

    def begins_reading(self, event: object) -> bool:
        """Whether ``event``, a frame nobody asked for, is the first of a new reading (a
        heartbeat's first frame): the reading before it is then published first. By default
        none is."""
        return False

    def unsolicited(self, event: object, now: float) -> bool:
        """A frame from this device nobody asked for (heartbeat, alarm report), taken in;
        whether the device's state is news with it. Only CAN devices send any, so the
        default ignores it."""
        return False

    @abc.abstractmethod
    def telemetry(self, now: float) -> dict[str, Any]:
        """The device's values in named units (``position``, ``faults`` …) and whether its
        power stage drives the motor (``enabled``, ``None`` when not known), without the
        envelope fields (``device``, ``kind``, ``online`` …) that the bus's telemetry adds
        (``Telemetry``). A new dict
        at each call, its values never changed afterwards: the bus's telemetry keeps the one
        it published, to tell whether the next differs."""

    # -- liveness ---------------------------------------------------------------------------

    def heard(self, now: float) -> None:
        """The device answered: no request of it is unanswered, and it is online."""
        self.misses = 0
        self.reported(now)

    def reported(self, now: float) -> None:
        """The device showed it is there (an answer, or a report it sent unasked): it is
        online; what it left unanswered stays counted."""
        self.last_reply = now
        if not self.online:
            # Back after going offline, it may have lost power: its settings go again.
            self.restore_pending = self.was_online
            self.online = self.was_online = True
            self.emit("online")

    def missed(self, now: float, frame: object = None) -> None:
        """A request (its ``frame``, when known) went unanswered; after ``OFFLINE_AFTER`` in a
        row the device is offline."""
        self.misses += 1
        if self.online and self.misses >= OFFLINE_AFTER:
            self.went_offline("no reply")

    def mirror(self, state: dict[str, Any]) -> None:  # noqa: B027 - optional hook
        """A shadow's driver (a bus in a worker, docs/workers.md) takes from a state its
        worker's driver made what the gateway judges a target by; by default nothing: the
        family judges a target by its joint and limits alone."""

    def check_heartbeat(self, now: float) -> None:  # noqa: B027 - optional hook
        """Called by the runner before each publication: a device that reports unasked
        (heartbeats) goes offline here once they stop; by default there are none."""

    def went_offline(self, reason: str) -> None:
        if self.online:
            self.online = False
            self.emit("offline", reason=reason)

    # -- reboots ---------------------------------------------------------------------------

    def rebooted(self, evidence: str) -> None:
        """The device was seen powering up again (its registers back at their defaults): the
        picture of it is reset, the settings it had are due again (``restore``, sent with the
        next poll), and a ``rebooted`` event says so. The runner drops its follow stream:
        only a fresh command moves it again."""
        self.forget_on_reboot()
        self.restore_pending = True
        self.emit("rebooted", evidence=evidence, restoring=len(self.restore()))

    def forget_on_reboot(self) -> None:  # noqa: B027 - optional hook
        """Reset what a power-up resets (targets, power stage …); by default nothing."""

    def restore(self) -> list[Request]:
        """What to write again after a reboot: the settings the device had confirmed."""
        return list(self.applied_settings.values())

    def emit(self, type_: str, **fields: Any) -> None:
        self._events.append(DeviceEvent(self.name, type_, fields))

    def drain_events(self) -> list[DeviceEvent]:
        events, self._events = self._events, []
        return events
