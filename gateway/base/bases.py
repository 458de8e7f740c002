"""The gateway's bases: ``<p>/<gw>/base/<name>/cmd``, ``…/twist`` and ``…/odom``.

Rules of this file:

1. A base moves only as a whole. A twist is judged against both wheels as any client's
   motion (claims, e-stop) and refused unless both are on (``enable``); then both wheels play
   the base's ``Drive`` from one start, so each slot's speeds come from one twist.
2. A claim of the base is the claim of both wheels, taken or refused together; a client that
   holds either wheel blocks the base, and a base's claim blocks each wheel.
3. A base never drives on one wheel: when one wheel leaves the play (e-stopped, refused its
   target), its device goes offline (silent, or taking no write: ``zlac706_can`` rule 2),
   reports a fault (its drive's alarm: its power stage is off) or is no longer on in
   velocity mode (a client's disable, which stops no play), both are ramped to 0 at once
   (over ``plays.RAMP_S``, whatever the base's deceleration limits: the sooner, the less it
   turns), with a ``base_stopped`` event naming the wheel and why. A
   twist while a wheel is offline or in fault is refused, naming it, as an enable of the
   base while a wheel is in fault is; while a wheel plays a trajectory, refused ``busy``, as
   a trajectory naming a wheel of a driving base is (``trajectory.playing`` rule 1: a drive
   and a play are chosen under one lock, the trajectories' ``players``); while the wheels
   still ramp to 0 after a ``base_stopped``, or a wheel of a base at rest follows a stream
   of its own, refused ``busy`` too (the drive starts its next play from rest: its first
   tick would stop that wheel at once; a wheel that turns at a speed of its own command and
   has a ``max_acceleration`` leaves the play when it reaches the bus, ``plays`` rule 6).
   An e-stop takes both out.
4. A twist holds for ``cmd_timeout_s`` (or its ``duration_s``); a put stream that stops
   putting, a client that goes, a ``stop``: the base ramps to 0 at its deceleration limits
   (``stream_stale``, ``stopped``). A client that numbers its twists (``seq``) and its
   ``stop`` has its twists sent before the stop (numbered at or below it) dropped, whichever
   thread brought them late. Once at rest with nothing holding it (both wheels have sent 0
   rpm: ``drive`` rule 3), its play ends and the wheels keep 0 rpm.
5. Odometry comes from the wheels' readings (their joints' measured positions), published on
   ``…/odom`` whenever both have been read past the last step, stamped with the readings'
   time. A reading is a state whose measurement (the joint's position, velocity, effort) is
   new, dated by that state's ``ts``; a state that repeats it (a write's acknowledgement
   restamps the state with the old heartbeat's values) is no reading, unless the wheel was
   measured at rest: it stays where it was until a write moves it, so its position holds at
   the repeat's ``ts`` (a base at rest, or pivoting on that wheel, goes on publishing). The
   two wheels are read at different moments (each its own heartbeat): the step is taken at
   the earlier of their latest readings, the other wheel's position there interpolated
   between its last two, so a lag between them is not taken for a turn. A wheel whose
   reading moved further than its drive turns it at top speed since the last, and
   ``READING_DATE_SLACK_S`` more (its counter set back: a drive that rebooted counts from 0
   again), is re-based, not integrated: its reading is taken as the last one, and the pose
   keeps what it had.
6. Wheels are put in velocity mode when they come online (``set_mode``, once per time they
   come online).
7. Threads: commands come on zenoh's threads (the drive's lock, the claim tables' locks; a
   twist's drive is chosen under the trajectories' ``players``, rule 3); ``tick`` and
   ``take_state`` run on the loop's thread, ``driving_wheel`` on any (a trajectory's lane).
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any, Protocol

from busgate.errors import DeviceTimeoutError, RefusedError
from busgate.gateway.base.drive import Drive
from busgate.gateway.base.kinematics import Geometry, Odometry, Twist
from busgate.gateway.bus.clock import now
from busgate.gateway.drivers.base import READING_DATE_SLACK_S, DeviceEvent, Driver, Effect
from busgate.gateway.scheduler.outcomes import settled
from busgate.gateway.scheduler.plays import RAMP_S
from busgate.gateway.scheduler.runner import BusRunner
from busgate.schemas.bases import (
    BASE_COMMAND_ADAPTER,
    BaseClaim,
    BaseConfig,
    BasePower,
    BaseRelease,
    BaseStop,
    ResetOdometry,
    TwistCommand,
    TwistTarget,
    reachable_radps,
    reachable_radps2,
    top_radps,
)
from busgate.schemas.payload import decode_object, ok_reply
from busgate.schemas.replies import failure_reply
from busgate.schemas.validation import shown

log = logging.getLogger(__name__)

#: How long after a play started its wheels may still be missing from their buses' plays (the
#: bus threads take the play from their inboxes) before a missing one counts as gone.
PLAY_TAKEN_S = 0.2
VELOCITY_MODE_OP: dict[str, Any] = {"op": "set_mode", "mode": "velocity"}
#: The clients whose last numbered ``stop`` a base keeps (rule 4): past so many, the one that
#: stopped it longest ago is forgotten (a client naming itself anew at each stop cannot grow
#: the table).
STOPS_KEPT = 256


class Gateway(Protocol):
    """What a base needs of its gateway (``busgate.gateway.api.commands.GatewayApi``): its
    name, its devices with their buses' runners, and the device commands (enable, mode)."""

    @property
    def name(self) -> str: ...

    @property
    def devices(self) -> Mapping[str, tuple[BusRunner, Driver]]: ...

    def command(self, device: str, payload: bytes) -> Future: ...


class TrajectoryPlayers(Protocol):
    """What a base needs of the gateway's trajectories (``trajectory.playing.Trajectories``):
    the lock a device's player is chosen under, and the trajectory a device plays (rule 3)."""

    players: threading.Lock

    def playing(self, device: str) -> str | None: ...


@dataclass(slots=True)
class Wheel:
    name: str
    runner: BusRunner
    driver: Driver
    #: (position rad, ts) of its last two readings, the latest last
    readings: tuple[tuple[float, float], ...] = ()
    #: The joint's (position, velocity, effort) of its last reading (rule 5)
    measured: tuple[Any, ...] = ()
    #: Added to its joint's position: its readings go on across a counter set back (rule 5)
    offset_rad: float = 0.0
    online: bool = False
    #: The faults its last state reported (its drive's alarms; rule 3)
    faults: tuple[str, ...] = ()
    #: The fastest its drive turns it: a reading further than this allows is no motion
    top_speed_radps: float = field(init=False)

    def __post_init__(self) -> None:
        self.top_speed_radps = top_radps(self.driver.joint)


@dataclass(slots=True)
class LiveBase:
    """One configured base and what it is doing."""

    config: BaseConfig
    wheels: tuple[Wheel, Wheel]
    drive: Drive
    odometry: Odometry
    client: str | None = None  # whose twist drives it (the deadman's)
    #: Client (``None``: one that names none) → seq of its last numbered ``stop``: its twists
    #: numbered at or below it were sent before it (rule 4); the ``STOPS_KEPT`` latest
    #: clients', under ``stops_lock`` (zenoh's threads bring stops and twists)
    stopped_by: dict[str | None, int] = field(default_factory=dict)
    stops_lock: threading.Lock = field(default_factory=threading.Lock)
    playing_since: float | None = None  # bus clock
    stale_told: bool = False
    #: Bus clock: until then its wheels may still ramp down after a ``base_stopped`` (rule 3)
    ramped_until: float = 0.0

    @property
    def names(self) -> tuple[str, str]:
        return self.wheels[0].name, self.wheels[1].name


class Bases:
    """Every base of the gateway (the rules above)."""

    def __init__(
        self,
        configs: list[BaseConfig],
        api: Gateway,
        on_event: Callable[[DeviceEvent], None],
        publish: Callable[[str, dict[str, Any]], None],
        trajectories: TrajectoryPlayers,
        *,
        estop_reset_key: str,
    ) -> None:
        self.api = api
        self._estop_reset_key = estop_reset_key  # named in the refusal that needs it
        self.on_event = on_event
        self.publish = publish  # (base name, odometry message)
        #: A twist and a trajectory's play are chosen under one lock, theirs (rule 3).
        self._trajectories = trajectories
        self.bases = {config.name: self._live(config) for config in configs}
        self._wheel_of = {w.name: (b, w) for b in self.bases.values() for w in b.wheels}

    def _live(self, config: BaseConfig) -> LiveBase:
        wheels = (
            Wheel(config.left, *self.api.devices[config.left]),
            Wheel(config.right, *self.api.devices[config.right]),
        )
        left, right = wheels[0].driver.joint, wheels[1].driver.joint
        geometry = Geometry(
            config.wheel_radius_m,
            config.track_m,
            config.max_linear_mps,
            config.max_angular_radps,
            config.max_linear_accel,
            config.max_angular_accel,
            min(reachable_radps(left), reachable_radps(right)),
            min(reachable_radps2(left), reachable_radps2(right)),
        )
        return LiveBase(config, wheels, Drive(geometry, left, right), Odometry(geometry))

    # -- commands (zenoh's threads) -------------------------------------------------------------

    def command(self, name: str, payload: bytes) -> Future:
        """The reply to a query on ``…/base/<name>/cmd``, as a future."""
        try:
            base = self._base(name)
            request = BASE_COMMAND_ADAPTER.validate_python(decode_object(payload))
            if isinstance(request, TwistCommand):
                hold = request.duration_s or base.config.cmd_timeout_s
                twist = Twist(request.linear, request.angular)
                return settled(
                    self._drive(base, twist, hold, request.client, request.require_claim)
                )
            if isinstance(request, BasePower):
                return self._power(base, request)
            return settled(self._other(base, request))
        except Exception as exc:
            return settled(failure_reply(exc, log, f"base {name}: command"))

    def twist(self, name: str, payload: bytes) -> dict[str, Any] | None:
        """A put on ``…/base/<name>/twist``: ``None`` when taken, else the error reply."""
        try:
            target = TwistTarget.model_validate(decode_object(payload))
        except Exception as exc:
            return failure_reply(exc, log, f"base {name}: twist")
        return self.stream(
            name,
            Twist(target.linear, target.angular),
            target.client,
            target.require_claim,
            target.seq,
        )

    def stream(
        self,
        name: str,
        twist: Twist,
        client: str | None,
        require_claim: bool = False,
        seq: int | None = None,
    ) -> dict[str, Any] | None:
        """One twist of a stream (a put, a ROS ``cmd_vel``), held ``cmd_timeout_s``: ``None``
        when taken (or dropped: sent before its client's ``stop``, rule 4), else the error
        reply."""
        try:
            base = self._base(name)
            if _sent_before_stop(base, client, seq):
                return None
            self._drive(base, twist, base.config.cmd_timeout_s, client, require_claim)
            return None
        except Exception as exc:  # a bug too: told as the put's refusal, not lost (an audit)
            return failure_reply(exc, log, f"base {name}: twist")

    def _drive(
        self, base: LiveBase, twist: Twist, hold_s: float, client: str | None, require: bool
    ) -> dict[str, Any]:
        with self._trajectories.players:  # rule 3: a trajectory takes no wheel meanwhile
            return self._drive_chosen(base, twist, hold_s, client, require)

    def _drive_chosen(
        self, base: LiveBase, twist: Twist, hold_s: float, client: str | None, require: bool
    ) -> dict[str, Any]:
        for wheel in base.wheels:  # rule 1: as any client's motion, both wheels
            try:
                wheel.runner.authority.judge(
                    wheel.name, Effect.MOTION, client, require_claim=require
                )
            except RefusedError as exc:
                if exc.code != "estopped":
                    raise
                raise RefusedError(  # what the base takes, not the wheel's own op
                    "estopped",
                    f"base {base.config.name}: wheel {wheel.name} is e-stopped: send "
                    '{"op":"enable"} to the base to let it move again (or reset the e-stop: '
                    f"a put on {self._estop_reset_key})",
                ) from None
            if (trajectory := self._trajectories.playing(wheel.name)) is not None:  # rule 3
                raise RefusedError(
                    "busy",
                    f"base {base.config.name}: wheel {wheel.name} plays trajectory "
                    f"{trajectory!r}: cancel it first (the base and the trajectory would fight "
                    "over its speed)",
                )
            if not wheel.driver.online:  # rule 3: it would stop the base at once
                raise DeviceTimeoutError(
                    f"base {base.config.name}: wheel {wheel.name} is offline",
                    device_id=wheel.driver.device_id,
                )
            telemetry = wheel.driver.telemetry(now())
            _refuse_fault(base, wheel, telemetry)
            if now() < base.ramped_until and wheel.runner.plays.playing(wheel.name):
                raise RefusedError(  # rule 3: started from rest, it would cut the ramp short
                    "busy",
                    f"base {base.config.name}: wheel {wheel.name} still ramps to 0 after the "
                    f"base stopped (within {RAMP_S:g} s): send the twist again once it rests",
                )
            if not _on(wheel, now()):
                raise RefusedError(
                    "bad_command",
                    f"base {base.config.name}: wheel {wheel.name} is not on in velocity mode: "
                    'send {"op":"enable"} to the base first',
                )
            if base.playing_since is None:
                _refuse_streamed(base, wheel)
        moment = now()
        target = base.drive.command(twist, moment, hold_s)
        base.client, base.stale_told = client, False
        if base.playing_since is None:
            base.drive.begin(moment, base.drive.sent)
            base.playing_since, base.ramped_until = moment, 0.0  # any ramp before it is over
            for side, wheel in enumerate(base.wheels):
                wheel.runner.play({wheel.name: base.drive.sampler(side)}, moment)
        return ok_reply(base=self._status(base) | {"target": _twist(target)})

    def _other(self, base: LiveBase, request: Any) -> dict[str, Any]:
        if isinstance(request, BaseStop):
            base.drive.stop()
            _note_stop(base, request.client, request.seq)
            if base.playing_since is not None:
                base.stale_told = True  # stopped, not stale
                self._event(base, "stopped", client=request.client, reason="stop")
        elif isinstance(request, BaseClaim):
            self._claim(base, request.client, request.ttl_s)
        elif isinstance(request, BaseRelease):
            released = self._release(base, request.client)
            return ok_reply(base=self._status(base), released=released)
        elif isinstance(request, ResetOdometry):
            base.odometry.reset()
        return ok_reply(base=self._status(base))

    def _release(self, base: LiveBase, client: str) -> bool:
        """Both wheels or neither (rule 2), told as a device's release is: whether ``client``
        held a claim to give back, and a ``released`` event when it did."""
        for wheel in base.wheels:  # ``claimed``, with nothing given back, if another holds one
            authority = wheel.runner.authority
            authority.claims.check(wheel.name, client, authority.clock())
        released = False
        for wheel in base.wheels:
            authority = wheel.runner.authority
            released |= authority.claims.release(wheel.name, client, authority.clock())
        if released:
            self._event(base, "released", client=client)
        return released

    def _claim(self, base: LiveBase, client: str, ttl_s: float) -> None:
        """Both wheels or neither (rule 2)."""
        for wheel in base.wheels:
            authority = wheel.runner.authority
            authority.claims.check(wheel.name, client, authority.clock())
        taken: list[Wheel] = []
        try:
            for wheel in base.wheels:
                authority = wheel.runner.authority
                authority.claims.claim(wheel.name, client, ttl_s, authority.clock())
                taken.append(wheel)
        except RefusedError:
            for wheel in taken:  # another client took the other wheel meanwhile
                authority = wheel.runner.authority
                authority.claims.release(wheel.name, client, authority.clock())
            raise
        self._event(base, "claimed", client=client, ttl_s=ttl_s)

    def _power(self, base: LiveBase, request: BasePower) -> Future:
        """Both power stages: velocity mode, 0 rpm, then enable, or disable (and stop the
        twist), as the requester (its client id and ``require_claim``: a base's claim is its
        wheels')."""
        if request.op == "disable":
            base.drive.stop()
        else:
            for wheel in base.wheels:  # its power stage would stay off: the base on one wheel
                _refuse_fault(base, wheel, wheel.driver.telemetry(now()))
        who = request.model_dump(include={"client", "require_claim"}, exclude_none=True)
        # 0 rpm before the enable: a speed preset (a wheel's own velocity op while the base
        # was off) would start the motor the moment it is enabled; a base moves on twists only.
        ops: list[dict[str, Any]] = [
            VELOCITY_MODE_OP,
            {"op": "velocity", "rpm": 0},
            {"op": "enable"},
        ]
        payloads = [
            json.dumps({**op, **who}).encode()
            for op in (ops if request.op == "enable" else [{"op": "disable"}])
        ]
        replies = [
            self.api.command(wheel.name, payload) for payload in payloads for wheel in base.wheels
        ]
        answer: Future = Future()

        def one_done(_: Future) -> None:
            if all(reply.done() for reply in replies) and not answer.done():
                failed = [r.result() for r in replies if not r.result().get("ok")]
                answer.set_result(failed[0] if failed else ok_reply(base=self._status(base)))

        for reply in replies:
            reply.add_done_callback(one_done)
        return answer

    def client_left(self, client: str) -> None:
        """The deadman: a base its client drove ramps to 0."""
        for base in self.bases.values():
            if base.client == client and base.playing_since is not None:
                base.drive.stop()
                base.stale_told = True  # stopped, not stale
                self._event(base, "stopped", client=client, reason="client gone")

    # -- the loop's thread ----------------------------------------------------------------------

    @property
    def driving(self) -> bool:
        """Whether a base plays its wheels' speeds (``tick`` has work every round)."""
        return any(base.playing_since is not None for base in self.bases.values())

    def driving_wheel(self, device: str) -> str | None:
        """The base that drives ``device`` (one of its wheels), if one does (rule 3)."""
        found = self._wheel_of.get(device)
        if found is None or found[0].playing_since is None:
            return None
        return found[0].config.name

    def tick(self) -> None:
        """Plays that ended, a wheel that left, a twist that timed out (rules 3 and 4)."""
        moment = now()
        for base in self.bases.values():
            if base.playing_since is None:
                continue
            taken = moment - base.playing_since > PLAY_TAKEN_S
            gone = [
                w
                for w in base.wheels
                if not w.driver.online
                or w.faults
                or not _on(w, moment)
                or (taken and not w.runner.plays.playing(w.name))
            ]
            if gone:
                self._one_wheel_gone(base, gone[0])
            elif base.drive.finished(moment):
                for wheel in base.wheels:  # both have sent 0 (``drive`` rule 3): they keep it
                    wheel.runner.stop_playing(wheel.name, speed=False)
                base.playing_since = None
            elif not base.stale_told and moment > base.drive.held_until:
                base.stale_told = True
                self._event(base, "stream_stale", client=base.client)

    def _one_wheel_gone(self, base: LiveBase, wheel: Wheel) -> None:
        if not wheel.driver.online:  # still in the play: it is ramped down too, if it hears
            reason = "went offline"
        elif wheel.faults:
            reason = f"in fault: {', '.join(wheel.faults)}"
        elif not _on(wheel, now()):
            reason = "is not on in velocity mode"
        elif (refusal := wheel.runner.plays.refusal(wheel.name)) is not None:
            reason = refusal[1]
        else:
            reason = "left the base's play"
        base.drive.halt()  # its next play starts from rest (``drive`` rule 5)
        for each in base.wheels:  # one that left the play already: nothing to stop
            each.runner.stop_playing(each.name, speed=True)
        base.playing_since = None
        # each ramp begins once its bus thread takes the stop, as it takes a play
        base.ramped_until = now() + RAMP_S + PLAY_TAKEN_S
        self._event(base, "base_stopped", wheel=wheel.name, reason=reason)

    def take_state(self, device: str, state: dict[str, Any]) -> None:
        """A wheel's new state: odometry (rule 5), velocity mode (rule 6)."""
        found = self._wheel_of.get(device)
        if found is None:
            return
        base, wheel = found
        online = bool(state.get("online"))
        if online and not wheel.online and state.get("mode") != "velocity":
            self.api.command(device, json.dumps(VELOCITY_MODE_OP).encode())
        wheel.online = online
        wheel.faults = tuple(state.get("faults") or ())
        joint, ts = state.get("joint") or {}, state.get("ts")
        position = joint.get("position")
        if position is None or ts is None or state.get("stale"):
            return
        if not _new_reading(wheel, joint, ts):
            return
        wheel.readings = (*wheel.readings[-1:], (_rebased(wheel, position, ts), ts))
        if not all(w.readings for w in base.wheels):
            return
        at = min(w.readings[-1][1] for w in base.wheels)
        left, right = (_at(w.readings, at) for w in base.wheels)
        if base.odometry.take(left, right, at):
            pose, twist = base.odometry.pose, base.odometry.twist
            self.publish(
                base.config.name,
                {
                    "base": base.config.name,
                    "ts": at,
                    "x": pose.x,
                    "y": pose.y,
                    "theta": pose.theta,
                    "linear": twist.linear,
                    "angular": twist.angular,
                    "commanded": _twist(base.drive.sent),
                },
            )

    # -- helpers ------------------------------------------------------------------------------

    def _base(self, name: str) -> LiveBase:
        base = self.bases.get(name)
        if base is None:
            raise RefusedError(
                "unknown_device", f"no base '{shown(name)}' on gateway {self.api.name}"
            )
        return base

    def _status(self, base: LiveBase) -> dict[str, Any]:
        pose = base.odometry.pose
        return {
            "name": base.config.name,
            "wheels": list(base.names),
            "driving": base.playing_since is not None,
            "client": base.client if base.playing_since is not None else None,  # whose it drives
            "twist": _twist(base.drive.sent),
            "odometry": {"x": pose.x, "y": pose.y, "theta": pose.theta},
        }

    def _event(self, base: LiveBase, type_: str, **fields: Any) -> None:
        self.on_event(DeviceEvent(base.config.name, type_, {"base": base.config.name, **fields}))


def _on(wheel: Wheel, moment: float) -> bool:
    """Whether ``wheel``'s drive turns it at the speeds it is sent: enabled, in velocity mode
    (rule 3: a disable or a mode set by any client does not take it out of the base's play)."""
    telemetry = wheel.driver.telemetry(moment)
    return telemetry.get("enabled") is True and telemetry.get("mode") == "velocity"


def _refuse_streamed(base: LiveBase, wheel: Wheel) -> None:
    """A wheel that a stream of its own drives (a client's, or the ramp of its own speed
    command) is refused for a base at rest (rule 3): the base's play starts from rest, and
    its first tick would stop the wheel at once."""
    if wheel.runner.streams.following(wheel.name):
        raise RefusedError(
            "busy",
            f"base {base.config.name}: wheel {wheel.name} follows a stream of its own (a "
            "client's follow key, or its speed command's ramp): the base starts from rest and "
            'would stop it at once; end it first ({"op":"end_follow"} to the wheel)',
        )


def _refuse_fault(base: LiveBase, wheel: Wheel, telemetry: dict[str, Any]) -> None:
    """A wheel in fault is refused for the base (rule 3: the other would drive alone)."""
    if faults := telemetry.get("faults"):
        raise RefusedError(
            "bad_command",
            f"base {base.config.name}: wheel {wheel.name} is in fault ({', '.join(faults)}): "
            'clear its alarm first (disable, then {"op":"clear_alarm"} to the wheel)',
        )


def _note_stop(base: LiveBase, client: str | None, seq: int | None) -> None:
    """``client``'s numbered ``stop`` (rule 4): kept for it, whoever stops the base after."""
    if seq is None:
        return
    with base.stops_lock:
        stops = base.stopped_by
        stops.pop(client, None)  # the latest last: the oldest is the one forgotten
        stops[client] = seq
        if len(stops) > STOPS_KEPT:
            del stops[next(iter(stops))]


def _sent_before_stop(base: LiveBase, client: str | None, seq: int | None) -> bool:
    """A numbered twist of a client whose numbered ``stop`` came after it, or has its number:
    numbered alike, the two cannot be ordered, and the base stays stopped (rule 4)."""
    if seq is None:
        return False
    with base.stops_lock:
        stopped = base.stopped_by.get(client)
    return stopped is not None and seq <= stopped


def _new_reading(wheel: Wheel, joint: dict[str, Any], ts: float) -> bool:
    """Whether ``joint``, of a wheel's state stamped ``ts``, is a new reading of it (rule 5):
    a new measurement, or the last one again of a wheel measured at rest."""
    if wheel.readings and ts <= wheel.readings[-1][1]:
        return False  # the same state again, or an older one
    measured = (joint.get("position"), joint.get("velocity"), joint.get("effort"))
    fresh, wheel.measured = measured != wheel.measured, measured
    return fresh or joint.get("velocity") == 0


def _rebased(wheel: Wheel, position_rad: float, ts: float) -> float:
    """``wheel``'s reading of its joint's ``position_rad`` at ``ts``, continuous across its
    counter set back (rule 5): a jump no turn of the wheel makes re-bases it."""
    reading = position_rad + wheel.offset_rad
    if wheel.readings:
        last, last_ts = wheel.readings[-1]
        if abs(reading - last) > wheel.top_speed_radps * (ts - last_ts + READING_DATE_SLACK_S):
            wheel.offset_rad += last - reading
            return last
    return reading


def _at(readings: tuple[tuple[float, float], ...], moment: float) -> float:
    """A wheel's position at ``moment``, between its last two readings (position, ts)."""
    position, ts = readings[-1]
    if ts <= moment or len(readings) < 2:
        return position
    before, before_ts = readings[0]
    if moment <= before_ts:
        return before
    return before + (position - before) * (moment - before_ts) / (ts - before_ts)


def _twist(twist: Twist) -> dict[str, float]:
    return {"linear": twist.linear, "angular": twist.angular}
