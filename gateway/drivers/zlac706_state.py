"""The ZLAC706 state machine, shared by the CAN and the RS232 driver (``drivers.zlac706``).

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
6. An alarm reset is refused unless the run signal is known to be off (the last enable
   written was a disable, or will be once the writes queued have landed), whatever the
   motor does: the manual's safety notes (运行) allow it only once the run signal is cut,
   "在运行信号状态下进行报警复位，会导致驱动器突然再启动" (an alarm reset with the run
   signal on makes the drive start again suddenly). A drive in alarm has stopped its motor
   (RS232's running bit clears) with its run signal still on. Cut, the reset moves nothing,
   so it is a setting, allowed while e-stopped (the e-stop's release cut the signal).
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any

from busgate.codecs import zlac706_common as common
from busgate.errors import CommandError
from busgate.gateway.drivers.base import READING_DATE_SLACK_S, Effect

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
    ONE_SHOT = "one_shot"  # an action (origin search): a repeat does it again
    ALARM_RESET = "alarm_reset"  # a one-shot too, only with the run signal cut (rule 6)
    SETTING = "setting"  # an absolute setting the state does not track (gains, rated current)


_UNTRACKED = frozenset({Role.ONE_SHOT, Role.ALARM_RESET, Role.SETTING})
#: Writes that set how the drive works rather than what it does now: written again after a
#: reboot. Enable and targets are not: only a fresh command moves the motor again.
RESTORED = frozenset(
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
#: covers 16,667 pulses between two reports 100 ms apart; this is four times that. Reports
#: further apart (a heartbeat set slower: the manual's example is 500 ms) allow more
#: (``reboot_jump_pulses``).
REBOOT_POSITION_JUMP = 65_536
#: The most a hub motor's counter moves in a second: its 1000 rpm limit.
_TOP_PULSES_PER_S = common.MAX_SPEED_RPM * common.PULSES_PER_TURN / 60


def reboot_jump_pulses(elapsed_s: float) -> float:
    """How far from 0 a position reported ``elapsed_s`` before a report of 0 must be for the
    0 to be a power-up: further than the motor turns at its limit meanwhile (an audit saw a
    real move home, between heartbeats 500 ms apart, taken for a reboot: the drive's settings
    written again and its next move refused as before enable)."""
    return max(REBOOT_POSITION_JUMP, _TOP_PULSES_PER_S * (elapsed_s + READING_DATE_SLACK_S))


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
    #: Where the position targets written so far send the shaft (``None``: not known): the
    #: last absolute target, or the drive's last target with each relative step since added
    #: to it (the drive adds a step to its last target, not to where the shaft has got: two
    #: steps sent back to back go twice as far), from the zero a position mode's enable sets.
    place: int | None = None
    #: The enable the gateway last wrote and the drive took: the manual's run signal, by
    #: which an alarm reset is judged (rule 6). ``enabled`` is whether the motor runs, which
    #: on RS232 the monitor's running bit tells: a fault clears it while the signal stays on.
    run_signal: bool | None = None

    def change(self, role: Role, value: Any) -> dict[str, Any]:
        """The fields a write of ``value`` in ``role`` sets."""
        if role is Role.ENABLE:
            change = {"enabled": value, "run_signal": value}
            if value and self.enabled is not True and self.mode is Mode.POSITION:
                # Enabled in position mode, the drive takes where the shaft is as its zero
                # and holds there (5.1): from off, its target is 0; from not known, not known.
                zero = 0 if self.enabled is False else None
                change |= {"target_position": zero, "place": zero}
            return change
        if role is Role.POSITION and self.relative is not False:
            # A step, not a place a client may take for its target (a stream or a trajectory
            # that took it for one would start from it); where it sends the shaft is known
            # only from a known place and a known relative mode.
            known = self.relative is True and self.place is not None and value is not None
            return {"target_position": None, "place": self.place + value if known else None}
        if role is Role.POSITION:
            return {"target_position": value, "place": value}
        if role is Role.ONE_SHOT:  # an origin search: a new zero, and no place known
            return {"place": None}
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


def _alarm_reset_rule(settings: Settings, _value: Any) -> str | None:
    if settings.run_signal is False:
        return None
    now = "on" if settings.run_signal else "perhaps on (not known)"
    return (
        f"clear_alarm while the drive's run signal (its enable) is {now}: the manual warns "
        "that an alarm reset with the run signal on starts the drive again suddenly; send "
        "disable first"
    )


_RULES: dict[Role, Callable[[Settings, Any], str | None]] = {
    Role.MODE: _mode_rule,
    Role.POSITION: _position_rule,
    Role.POSITION_HIGH: _position_rule,
    Role.SPEED: _needs_mode(Mode.VELOCITY, "a speed target (velocity)"),
    Role.TORQUE: _needs_mode(Mode.TORQUE, "a torque target (torque)"),
    Role.ALARM_RESET: _alarm_reset_rule,
}


#: What a write in each role does; a role not here changes a setting (an alarm reset too,
#: sent only with the run signal cut: rule 6). An origin search (a one-shot) runs the motor.
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
    if role in (Role.ONE_SHOT, Role.ALARM_RESET):
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
        """The settings once every write queued so far has been acknowledged (the settings
        themselves, frozen, while none is queued: asked at every follow tick)."""
        return replace(self.settings, **self._pending) if self._pending else self.settings

    def planned(self, change: dict[str, Any]) -> None:
        self._pending.update(change)

    def acknowledged(self, change: dict[str, Any]) -> None:
        self.settings = replace(self.settings, **change)
        for name, value in change.items():
            if self._pending.get(name, object()) == value:
                del self._pending[name]

    def forget_pending(self) -> None:
        self._pending.clear()


def reverse(codes: Mapping[Mode, int]) -> dict[int, Mode]:
    """A protocol's mode codes, code → mode."""
    return {code: mode for mode, code in codes.items()}
