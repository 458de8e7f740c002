"""The ZLAC706 state machine and driver behaviour, shared by the CAN and the RS232 driver.

The ZLAC706 is one device with two wire formats, so its rules live here once, in terms of the
*role* a register write plays (mode, enable, speed target …). Each protocol module names the
role of each of its registers (a ``roles`` table) and its own frames; nothing else differs.

Rules of this file:

1. Order, as the manual demands: mode, then enable, then target. A position target before
   enable is refused (in position mode the device silently ignores it), and so is a target
   of another mode than the current one (speed outside velocity mode, torque outside torque
   mode, position outside position mode: the device would ignore those too). Speed and torque
   may be preset before enable: the manual's own sequences do so. The mode is not changed
   while the motor is enabled (the manual always sets it first): disable first.
2. The state (``Settings``) is what the device acknowledged; it changes only in ``apply``. A
   command is checked against what the device *will* hold once the writes already queued for
   it have landed (``Zlac706State.expected``): one device's writes go out in order, so
   ``enable`` then ``move`` sent back to back is right. A write that went unanswered, or an
   e-stop that dropped the queue, voids that outlook: those writes may never land.
3. Idempotent (retried after a lost reply): every absolute write. Not: alarm reset, origin
   search, and a position target unless the position mode is known to be absolute.
4. Alarms (the CAN alarm report, the RS232 status word: the same bits) become fault names;
   each change emits exactly one ``fault`` event.
5. Keep-alive: while the device is enabled in velocity mode with a non-zero speed, the
   driver asks for its protocol's refresh (``keepalive_period_s``), so that a feed-forward
   gain of 1 never locks the shaft by surprise.
"""

from __future__ import annotations

import abc
import enum
import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, ClassVar

from pydantic import TypeAdapter, ValidationError

from busgate.codecs import zlac706_common as common
from busgate.codecs.errors import CommandError
from busgate.gateway.bus.request import Request
from busgate.gateway.drivers.base import Driver, Effect
from busgate.schemas import zlac706 as schema
from busgate.schemas.base import CommandModel
from busgate.schemas.errors import describe_validation_error

Mode = common.Mode


class Role(enum.Enum):
    """What a register write does; the tracked ones are named after their ``Settings`` field."""

    MODE = "mode"
    ENABLE = "enabled"
    POSITION_MODE = "relative"
    POSITION = "target_position"
    POSITION_HIGH = "position_high"  # RS232 sends a position as two writes, high half first
    SPEED = "speed_raw"
    TORQUE = "torque_raw"
    POSITION_RAMP = "position_ramp"
    SPEED_RAMP = "speed_ramp"
    MAX_SPEED = "max_speed_raw"
    ONE_SHOT = "one_shot"  # an action (alarm reset, origin search): a repeat does it again
    SETTING = "setting"  # an absolute setting the state does not track (gains, rated current)


_UNTRACKED = frozenset({Role.ONE_SHOT, Role.SETTING})
#: Writes that set how the drive works rather than what it does now: written again after a
#: reboot. Enable and targets are not: only a fresh command moves the motor again.
_RESTORED = frozenset(
    {
        Role.MODE,
        Role.POSITION_MODE,
        Role.POSITION_RAMP,
        Role.SPEED_RAMP,
        Role.MAX_SPEED,
        Role.SETTING,
    }
)
#: A position report of exactly 0 after one this far away (pulses) is the counter's power-up
#: value, not motion: with note 6's 10000 pulses per turn, a hub motor at its 1000 rpm limit
#: covers 16,667 pulses between two reports 100 ms apart; this is four times that.
REBOOT_POSITION_JUMP = 65_536


@dataclass(frozen=True, slots=True)
class Settings:
    """What the device holds, as far as the gateway knows (``None``: unknown).

    Speeds and torque stay raw: the scale is the same on both wires, and the keep-alive must
    repeat the very value that was written.
    """

    mode: Mode | None = None
    enabled: bool | None = None
    relative: bool | None = None
    target_position: int | None = None
    position_high: int | None = None
    speed_raw: int | None = None
    torque_raw: int | None = None
    position_ramp: int | None = None
    speed_ramp: int | None = None
    max_speed_raw: int | None = None

    def change(self, role: Role, value: Any) -> dict[str, Any]:
        """The fields a write of ``value`` in ``role`` sets."""
        return {} if role in _UNTRACKED else {role.value: value}


@dataclass(frozen=True, slots=True)
class RoleOf:
    """A register's role, and its raw value as the state holds it (given the settings, so
    that RS232's low position half can be joined to the high half written before it)."""

    role: Role
    value: Callable[[int, Settings], Any] = lambda raw, _settings: raw


SETTING = RoleOf(Role.SETTING)


# -- the order rules --------------------------------------------------------------------------


def _needs_mode(mode: Mode, what: str) -> Callable[[Settings, Any], str | None]:
    def rule(settings: Settings, _value: Any) -> str | None:
        if settings.mode is mode:
            return None
        now = f"the motor is in {settings.mode} mode" if settings.mode else "its mode is not known"
        return (
            f"{what} needs {mode} mode (set_mode {mode} first): {now}, "
            "and the device would ignore it"
        )

    return rule


def _position_rule(settings: Settings, value: Any) -> str | None:
    reason = _needs_mode(Mode.POSITION, "a position target (move)")(settings, value)
    if reason is None and not settings.enabled:
        reason = (
            "move before enable: in position mode the ZLAC706 silently ignores a target "
            "sent before the motor is enabled; send enable first"
        )
    return reason


def _mode_rule(settings: Settings, value: Any) -> str | None:
    if settings.enabled and value is not settings.mode:
        return (
            f"set_mode {value} while the motor is enabled: disable first (the mode is "
            "chosen before enable)"
        )
    return None


_RULES: dict[Role, Callable[[Settings, Any], str | None]] = {
    Role.MODE: _mode_rule,
    Role.POSITION: _position_rule,
    Role.POSITION_HIGH: _position_rule,
    Role.SPEED: _needs_mode(Mode.VELOCITY, "a speed target (velocity)"),
    Role.TORQUE: _needs_mode(Mode.TORQUE, "a torque target (torque)"),
}


#: What a write in each role does; a role not here changes a setting. An origin search (a
#: one-shot, like alarm reset) runs the motor, so one-shots count as motion.
_ROLE_EFFECTS: dict[Role, Effect] = {
    Role.POSITION: Effect.MOTION,
    Role.POSITION_HIGH: Effect.MOTION,
    Role.TORQUE: Effect.MOTION,
    Role.ONE_SHOT: Effect.MOTION,
}


def role_effect(role: Role | None, value: Any) -> Effect:
    """What a frame in ``role`` writing ``value`` does (``None``: not a write, it asks)."""
    if role is None:
        return Effect.READ
    if role is Role.ENABLE:
        return Effect.SETTING if value else Effect.STOP
    if role is Role.SPEED:
        return Effect.MOTION if value else Effect.STOP
    return _ROLE_EFFECTS.get(role, Effect.SETTING)


def check(role: Role, value: Any, settings: Settings) -> None:
    """Refuse (``CommandError``) a write the device would ignore or should not get now."""
    rule = _RULES.get(role)
    reason = rule(settings, value) if rule else None
    if reason:
        raise CommandError(reason)


def is_idempotent(role: Role | None, settings: Settings) -> bool:
    """True when repeating the write is harmless (``None``: not a write, e.g. the monitor)."""
    if role is Role.ONE_SHOT:
        return False
    if role in (Role.POSITION, Role.POSITION_HIGH):
        return settings.relative is False  # relative, or unknown: a repeat moves again
    return True


class Zlac706State:
    """The acknowledged settings, the writes in flight on top of them, and the alarms."""

    def __init__(self) -> None:
        self.settings = Settings()
        self.alarms = common.AlarmFlags(0)
        self._pending: dict[str, Any] = {}

    def expected(self) -> Settings:
        """The settings once every write queued so far has been acknowledged."""
        return replace(self.settings, **self._pending)

    def planned(self, change: dict[str, Any]) -> None:
        self._pending.update(change)

    def acknowledged(self, change: dict[str, Any]) -> None:
        self.settings = replace(self.settings, **change)
        for name, value in change.items():
            if self._pending.get(name, object()) == value:
                del self._pending[name]

    def forget_pending(self) -> None:
        self._pending.clear()


def fault_names(alarms: common.AlarmFlags) -> list[str]:
    """``["over_current", …]``: the fault bits of an alarm code, by name."""
    return list(_fault_names(int(alarms)))


@functools.lru_cache(maxsize=256)
def _fault_names(code: int) -> tuple[str, ...]:
    """Cached per code: telemetry asks for every heartbeat, and flag arithmetic is slow."""
    faults = common.AlarmFlags(code).faults
    return tuple(flag.name.lower() for flag in common.AlarmFlags if flag in faults)


def ramp_ms(word: int | None) -> dict[str, int] | None:
    """A ramp register's value as ``{"accel_ms", "decel_ms"}`` (inverse of ``ramp_word``)."""
    if word is None:
        return None
    return {
        "accel_ms": (word >> 8) * common.RAMP_STEP_MS,
        "decel_ms": (word & 0xFF) * common.RAMP_STEP_MS,
    }


def _rpm(raw: int | None) -> float | None:
    return None if raw is None else common.rpm_from_speed_raw(raw)


class FollowTarget(CommandModel):
    """A ZLAC706 follow stream's payload: a speed, and the sending client."""

    rpm: schema.Rpm


_STOP = schema.Velocity(op="velocity", rpm=0.0)
_RELEASE = schema.Disable(op="disable")


# -- the driver -------------------------------------------------------------------------------


class Zlac706Driver(Driver):
    """What the CAN and the RS232 driver share: planning under the order rules, the state
    from acknowledged writes, faults, keep-alive, follow stream, safe stop, telemetry."""

    kind: ClassVar[str] = "zlac706"
    commands: ClassVar[TypeAdapter[Any]] = schema.COMMAND_ADAPTER
    #: Per protocol: the frames of a command, each register's role, the keep-alive period
    #: and the measured values its telemetry carries.
    frames: ClassVar[Callable[[Any, int], list[Any]]]
    roles: ClassVar[dict[int, RoleOf]]
    keepalive_period_s: ClassVar[float]
    measured_names: ClassVar[tuple[str, ...]] = ("position", "current_ma", "speed_rpm")
    reenable_op: ClassVar[str] = '{"op": "enable"}'

    def __init__(self, name: str, device_id: int, *, follow_period_s: float = 0.02) -> None:
        super().__init__(name, device_id, follow_period_s=follow_period_s)
        self.machine = Zlac706State()
        self.measured: dict[str, Any] = dict.fromkeys(self.measured_names)

    # -- planning -------------------------------------------------------------------------------

    def frames_of(self, command: Any) -> list[object]:
        return self.frames(command, self.device_id)

    def effect(self, frame: object) -> Effect:
        return role_effect(*self._role(frame, self.machine.settings))

    def plan(self, command: Any) -> list[Request]:
        """The command's requests, refused (``CommandError``) when the order rules forbid it."""
        outlook = self.machine.expected()
        requests, changes = [], {}
        for frame in self.frames(command, self.device_id):
            role, value = self._role(frame, outlook)
            if role is not None:
                check(role, value, outlook)
            requests.append(self._request(frame, role, outlook))
            if role is not None:  # the next frame is checked against what this one sets
                change = outlook.change(role, value)
                changes.update(change)
                outlook = replace(outlook, **change)
        self.machine.planned(changes)
        if changes.get(Role.ENABLE.value):
            self.estop_latched = False  # the re-enable op: the motor may run again
        return requests

    def _request(self, frame: object, role: Role | None, settings: Settings) -> Request:
        return Request.of(self.codec, frame, idempotent=is_idempotent(role, settings))

    def _unchecked(self, command: Any) -> list[Request]:
        """Requests the gateway itself sends (safe stop, init): no order rules apply."""
        settings = self.machine.settings
        return [
            self._request(frame, self._role(frame, settings)[0], settings)
            for frame in self.frames(command, self.device_id)
        ]

    def _role(self, frame: object, settings: Settings) -> tuple[Role | None, Any]:
        register = getattr(frame, "register", None)
        if register is None:
            return None, None  # not a write (the RS232 monitor request)
        entry = self.roles.get(register, SETTING)
        return entry.role, entry.value(frame.value, settings)  # type: ignore[attr-defined]

    def safe_stop(self) -> list[Request]:
        """Speed 0 (unless the mode is known not to be velocity), then release the motor.

        The queue is dropped on an e-stop, so the writes still in flight are forgotten."""
        self.estop_latched = True
        self.machine.forget_pending()
        return [*self.stale_stream(), *self._unchecked(_RELEASE)]

    def stale_stream(self) -> list[Request]:
        """0 rpm: a client that stopped streaming speeds must not leave the wheel turning."""
        if self.machine.settings.mode in (Mode.VELOCITY, None):
            return self._unchecked(_STOP)
        return []

    def keepalive(self, now: float) -> tuple[float, Request] | None:
        settings = self.machine.settings
        if settings.mode is Mode.VELOCITY and settings.enabled and settings.speed_raw:
            return self.keepalive_period_s, self.keepalive_request()
        return None

    @abc.abstractmethod
    def keepalive_request(self) -> Request:
        """What refreshes the device: the speed write (CAN), the monitor request (RS232)."""

    def follow_target(self, payload: dict[str, Any]) -> schema.Velocity:
        """``{"rpm": R}`` in velocity mode; positions are refused (a ZLAC706 streams speeds)."""
        if "position" in payload:
            raise CommandError(
                'a ZLAC706 follow stream carries speeds ({"rpm": R}) in '
                "velocity mode; send positions as move commands"
            )
        try:
            rpm = FollowTarget.model_validate(payload).rpm
        except ValidationError as exc:
            raise CommandError(f"invalid follow target: {describe_validation_error(exc)}") from exc
        check(Role.SPEED, rpm, self.machine.expected())
        return schema.Velocity(op="velocity", rpm=rpm)

    @classmethod
    def follow_request(cls, targets: Sequence[tuple[Driver, Any]]) -> Request:
        """The speed write of one device (a ZLAC706 frame addresses one node)."""
        if len(targets) != cls.follow_group_limit:
            raise CommandError(f"a ZLAC706 speed write carries one device, not {len(targets)}")
        driver, command = targets[0]
        (frame,) = cls.frames(command, driver.device_id)
        return Request.of(cls.codec, frame, idempotent=True)

    # -- interpreting ---------------------------------------------------------------------------

    def acknowledged(self, frame: object) -> None:
        """The device took the write ``frame``: the state follows."""
        role, value = self._role(frame, self.machine.settings)
        if role is not None:
            self.machine.acknowledged(self.machine.settings.change(role, value))
        if role in _RESTORED:
            self.applied_settings[frame.register] = Request.of(  # type: ignore[attr-defined]
                self.codec, frame, idempotent=True
            )

    def take_position(self, raw: int) -> None:
        """A reported position; a jump to 0 from far away means the drive powered up again."""
        before, self.measured["position"] = self.measured["position"], raw
        if raw == 0 and before is not None and abs(before) > REBOOT_POSITION_JUMP:
            self.rebooted(f"position counter back at 0 from {before}")

    def forget_on_reboot(self) -> None:
        """Power-up: released, every setting at its default until ``restore`` lands."""
        self.machine = Zlac706State()
        self.machine.settings = Settings(enabled=False)

    def take_alarms(self, alarms: common.AlarmFlags) -> None:
        """New alarm bits; one ``fault`` event when the fault names change."""
        before, self.machine.alarms = self.machine.alarms, alarms
        if alarms == before:  # every heartbeat says "no alarm": flag arithmetic is slow
            return
        old, new = before.faults, alarms.faults
        if old != new:
            self.emit(
                "fault",
                faults=fault_names(new),
                raised=fault_names(new & ~old),
                cleared=fault_names(old & ~new),
            )

    def has_measurements(self) -> bool:
        return True

    def telemetry(self, now: float) -> dict[str, Any]:
        settings = self.machine.settings
        relative = settings.relative
        return {
            "mode": settings.mode,
            "enabled": settings.enabled,
            "position_mode": None if relative is None else ("relative" if relative else "absolute"),
            "target": settings.target_position,
            "target_speed_rpm": _rpm(settings.speed_raw),
            "target_current_a": None
            if settings.torque_raw is None
            else float(settings.torque_raw / common.TORQUE_RAW_PER_A),
            "position_ramp": ramp_ms(settings.position_ramp),
            "velocity_ramp": ramp_ms(settings.speed_ramp),
            "max_speed_rpm": _rpm(settings.max_speed_raw),
            "measured": self.has_measurements(),
            **self.measured,
            "faults": fault_names(self.machine.alarms),
        }

    def missed(self, now: float) -> None:
        # An unanswered write may or may not have landed: stop counting on the queued ones.
        self.machine.forget_pending()
        super().missed(now)


def reverse(codes: dict[Mode, int]) -> dict[int, Mode]:
    """A protocol's mode codes, code → mode."""
    return {code: mode for mode, code in codes.items()}
