"""The ZLAC706 driver and its hub motor as one model, apart from either wire protocol.

The CAN and RS232 front-ends (``zlac706.py``) turn register writes into the calls below; this
module owns what the driver does with them (manual 8.1.2, 8.2.1 notes, 8.2.2; docs/protocols.md).
Rules of this file:

1. State is ``Settings`` (the writable values, by role, with the manual's defaults) plus the
   run state: enabled, alarms, the keep-alive, and one ``motion``. Raw units are the ones both
   wires share: speeds in raw speed units (8192 per 3000 rpm = 16384 per 6000 rpm), torque in
   ±7500 steps, ramps as the 16-bit word (accel steps high, decel steps low, 100 ms each).
2. Motion is a function of time: a short tuple of constant-acceleration ``Segment``s, the last
   of which runs for ever (``zlac706_motion.py``). Nothing ticks; the one timed rule (the
   keep-alive) is settled lazily, at the time it fell due, by ``settle(now)``, which every
   caller runs first.
3. The manual's order rules: a position target is ignored unless the motor is enabled (and in
   position mode); enabling in speed mode starts the preset speed at once; disabling releases
   the shaft (it stops where it is, no current); enabling in position mode makes the shaft's
   place the mechanical zero ("以驱动器使能启动时刻为机械 0 点").
4. An alarm switches the power stage off as a disable does, but keeps the enable command: an
   alarm reset with the motor still enabled restarts it, as the manual warns
   ("在运行信号状态下进行报警复位，会导致驱动器突然再启动").

Where the manual is silent, this file chooses (each choice is commented where it applies):
10000 pulses per turn (note 6's 2500-line encoder), ramps measured from 0 to the hub motor's
1000 rpm, the power-up settings, the currents and bus voltage reported, what a mode change
does to a running motor, and the origin search of a motor without a Z signal.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any, Final

from busgate.codecs.zlac706_common import (
    MAX_SPEED_RPM,
    RAMP_STEP_MS,
    TORQUE_RAW_PER_A,
    AlarmFlags,
    Mode,
    rpm_from_speed_raw,
    speed_raw_truncated,
)
from busgate.gateway.sim.zlac706_motion import (
    Motion,
    hold,
    position_motion,
    segment_at,
    speed_motion,
)

#: Note (6): a 2500-line encoder with a 1:1 electronic gear takes 10000 pulses per turn.
PULSES_PER_REV: Final = 10_000
#: A ramp is "the time from 0 to the top speed"; the top speed of a hub motor is 1000 rpm.
FULL_SPEED_PPS: Final = MAX_SPEED_RPM * PULSES_PER_REV / 60
#: Note (9): the origin search turns "slowly" until the Z signal; the manual gives no speed.
ORIGIN_SEARCH_RPM: Final = 10
#: Output current (A) when the manual gives none: the heartbeat log shows 0.03–0.04 A at
#: standstill and the heartbeat example 0.30 A at 398 rpm; while the speed changes we report
#: what an unloaded hub motor plausibly draws to accelerate its wheel.
HOLD_CURRENT_A: Final = 0.03
CRUISE_CURRENT_A: Final = 0.30
ACCEL_CURRENT_A: Final = 2.0
#: Bus voltage (V) reported by the RS232 monitor: a 48 V supply (the manual allows 24–60 V),
#: and under the voltage alarms a value past the LED table's thresholds (≤ 16 V, ≥ 80 V).
BUS_VOLTAGE_V: Final = {AlarmFlags.UNDER_VOLTAGE: 15, AlarmFlags.OVER_VOLTAGE: 82}
NOMINAL_BUS_V: Final = 48

#: inject_fault names → the alarm bit each raises.
FAULTS: Final = {
    "over_current": AlarmFlags.OVER_CURRENT,
    "over_voltage": AlarmFlags.OVER_VOLTAGE,
    "encoder": AlarmFlags.ENCODER_FAULT,
    "over_temperature": AlarmFlags.OVER_TEMPERATURE,
    "under_voltage": AlarmFlags.UNDER_VOLTAGE,
    "overload": AlarmFlags.OVERLOAD,
}


@dataclass(frozen=True, slots=True)
class Settings:
    """The writable values by role, at their power-up values (field names are the CAN
    codec's register names; the gains are the ``Gain`` values).

    The manual gives gains (table 5, and note 8.2.2: hub motors ship with the feed-forward gain
    at 1, which arms the keep-alive) and examples for the rest: ramps 10 × 100 ms, trapezoid
    speed 100 rpm, rated current 8000 mA. It states no power-up work mode or position mode:
    we take speed mode (the mode the keep-alive note describes) and absolute positions.
    """

    mode: Mode = Mode.VELOCITY
    relative: bool = False
    position_ramp: int = 0x0A0A
    speed_ramp: int = 0x0A0A
    max_speed: int = speed_raw_truncated(100)
    target_speed: int = 0
    target_torque: int = 0
    rated_current: int = 8000
    position_kp: int = 3000
    position_kd: int = 1
    position_kf: int = 1
    velocity_kp: int = 5000
    velocity_ki: int = 500
    velocity_kd: int = 0
    current_kp: int = 500
    current_kd: int = 500


def ramp_rates(word: int) -> tuple[float, float]:
    """Accel and decel rates (pulses/s²) of a ramp word; a zero ramp is a jump (``inf``)."""
    return tuple(  # type: ignore[return-value]
        FULL_SPEED_PPS / (steps * RAMP_STEP_MS / 1000) if steps else math.inf
        for steps in (word >> 8 & 0xFF, word & 0xFF)
    )


def pps(speed_raw: int) -> float:
    """Pulses per second of a raw speed value."""
    return rpm_from_speed_raw(speed_raw) * PULSES_PER_REV / 60


def _i32(value: float) -> int:
    """The driver's 32-bit position counter wraps."""
    return (round(value) + (1 << 31)) % (1 << 32) - (1 << 31)


class Zlac706Motor:
    """One ZLAC706 and its hub motor; ``keepalive_s`` is the protocol's keep-alive period."""

    def __init__(self, *, keepalive_s: float) -> None:
        self.keepalive_s = keepalive_s
        self.reset(0.0)

    def reset(self, now: float) -> None:
        """Power-up: settings at their defaults, released, no alarm, position counter 0."""
        self.settings = Settings()
        self.enabled = False
        self.alarms = AlarmFlags(0)
        self.motion: Motion = hold(0.0, now)
        self.target: int | None = None  # the position command, in position mode
        self.fed_s = now  # the last keep-alive
        self.locked = False  # the keep-alive ran out and the shaft locked
        self.searching = False  # an origin search is asked for (and runs while enabled)

    @property
    def running(self) -> bool:
        """The power stage is on: enabled and no alarm."""
        return self.enabled and not self.alarms

    # --- commands ----------------------------------------------------------------------------

    def store(self, name: str, value: Any, now: float) -> None:
        """Write one setting and carry out what it sets off (see ``_REACTIONS``)."""
        before = getattr(self.settings, name)
        self.settings = replace(self.settings, **{name: value})
        _REACTIONS.get(name, _no_reaction)(self, before, now)

    def enable(self, now: float) -> None:
        """Start. Already enabled: nothing changes (in particular the zero stays)."""
        if self.enabled:
            return
        self.enabled = True
        if self.running and self.settings.mode is Mode.POSITION:
            self.motion, self.target = hold(0.0, now), 0
        self._start(now)

    def disable(self, now: float) -> None:
        """Stop: the shaft is released at once and stops where it is."""
        self.enabled = self.searching = False
        self._stop(now)

    def move_to(self, position: int, now: float) -> None:
        """A position target; ignored unless enabled in position mode (manual 8.1.1 (3))."""
        if not self.running or self.settings.mode is not Mode.POSITION:
            return
        # Relative targets add to the last target, not to where the shaft happens to be, so
        # a run of relative moves sums exactly, as the commanded position (E6/E7) does.
        base = self.target if self.settings.relative and self.target is not None else 0
        self.target, self.searching = _i32(base + position), False
        self._drive(now)

    def search_origin(self, now: float) -> None:
        """Note (9): the search runs once enabled, turning slowly until the Z signal. A hub
        motor has none, so it turns on (forward at ``ORIGIN_SEARCH_RPM``) until a disable, a
        mode change, a new target or an alarm ends it."""
        self.searching = True
        if self.running:
            self._drive(now)

    def reset_alarm(self, now: float) -> None:
        """Clear the alarm (the injected condition is gone); still enabled, it restarts."""
        had_alarm, self.alarms = self.alarms, AlarmFlags(0)
        if had_alarm and self.enabled:
            self._start(now)

    def raise_fault(self, alarm: AlarmFlags, now: float) -> None:
        """An alarm: the power stage switches off and the shaft is released."""
        self.alarms |= alarm
        self.searching = False
        self._stop(now)

    def feed_keepalive(self, now: float) -> None:
        self.fed_s = now

    def settle(self, now: float) -> None:
        """Lock the shaft if the keep-alive ran out: in speed mode with feed-forward gain 1,
        ``keepalive_s`` after the last keep-alive. Locking is an immediate stop (锁轴, the
        shaft held); the next speed command restarts the motor."""
        deadline = self.fed_s + self.keepalive_s
        armed = self.running and self.settings.mode is Mode.VELOCITY
        if armed and self.settings.position_kf == 1 and not self.locked and now > deadline:
            self._stop(deadline)
            self.locked = True

    # --- readings ----------------------------------------------------------------------------

    def status(self) -> AlarmFlags:
        """The alarm code / status word: the alarm bits, and ``RUNNING`` while the power
        stage is on."""
        return self.alarms | (AlarmFlags.RUNNING if self.running else AlarmFlags(0))

    def feedback_position(self, now: float) -> int:
        return _i32(segment_at(self.motion, now).at(now)[0])

    def commanded_position(self, now: float) -> int:
        """The position target in position mode; elsewhere the command follows the shaft."""
        if self.settings.mode is Mode.POSITION and self.target is not None:
            return self.target
        return self.feedback_position(now)

    def speed_raw(self, now: float) -> int:
        rpm = segment_at(self.motion, now).at(now)[1] * 60 / PULSES_PER_REV
        return speed_raw_truncated(max(-MAX_SPEED_RPM, min(MAX_SPEED_RPM, rpm)))

    def current_raw(self, now: float) -> int:
        """Output current, A × 100, bounded by the rated current (the driver's limit)."""
        if not self.running:
            return 0
        segment = segment_at(self.motion, now)
        if self.settings.mode is Mode.TORQUE and not self.searching:
            amps = abs(self.settings.target_torque) / float(TORQUE_RAW_PER_A)
        elif segment.accel and now < segment.end_s:
            amps = ACCEL_CURRENT_A
        else:
            amps = CRUISE_CURRENT_A if segment.at(now)[1] else HOLD_CURRENT_A
        return round(min(amps, self.settings.rated_current / 1000) * 100)

    def bus_voltage_v(self) -> int:
        return next(
            (v for alarm, v in BUS_VOLTAGE_V.items() if alarm in self.alarms), NOMINAL_BUS_V
        )

    # --- the power stage ---------------------------------------------------------------------

    def _start(self, now: float) -> None:
        """The power stage comes on (enable, alarm reset): the mode's command takes over and
        the keep-alive is armed from now."""
        self.fed_s, self.locked = now, False
        if self.running:
            self._drive(now)

    def _stop(self, now: float) -> None:
        self.motion = hold(segment_at(self.motion, now).at(now)[0], now)

    def _drive(self, now: float) -> None:
        """Plan the motion the current mode commands, from the state at ``now``."""
        settings, start = self.settings, segment_at(self.motion, now)
        if settings.mode is Mode.POSITION and not self.searching:
            if self.target is None:
                self.target = self.feedback_position(now)
            top = pps(settings.max_speed)
            rates = ramp_rates(settings.position_ramp)
            self.motion = position_motion(start, now, self.target, top, *rates)
            return
        self.motion = speed_motion(
            start,
            now,
            self._commanded_pps(),
            *ramp_rates(
                settings.position_ramp if settings.mode is Mode.POSITION else settings.speed_ramp
            ),
        )

    def _commanded_pps(self) -> float:
        """Speed and torque mode, and the origin search: the speed the motor runs to. In
        torque mode an unloaded motor runs up to top speed in the torque's direction (8.1.2
        step 6: "以驱动器内部设定最高速度转动")."""
        if self.searching:
            return ORIGIN_SEARCH_RPM * PULSES_PER_REV / 60
        if self.settings.mode is Mode.TORQUE:
            return math.copysign(FULL_SPEED_PPS, self.settings.target_torque) * bool(
                self.settings.target_torque
            )
        return pps(self.settings.target_speed)

    # --- what a setting sets off -------------------------------------------------------------

    def _mode_changed(self, before: Mode, now: float) -> None:
        """A new mode while running: the motor stops where it is and the new mode takes over
        from standstill (the manual sets the mode before enabling; we choose the least
        surprising switch). The position command and an origin search are dropped."""
        if before is self.settings.mode:
            return
        self.target, self.searching = None, False
        if self.running:
            self._stop(now)
            self._start(now)

    def _speed_changed(self, before: int, now: float) -> None:
        if self.running and self.settings.mode is Mode.VELOCITY:
            if self.locked:  # a speed command after the lock: the motor runs again
                self.fed_s, self.locked = now, False
            self.searching = False
            self._drive(now)

    def _torque_changed(self, before: int, now: float) -> None:
        if self.running and self.settings.mode is Mode.TORQUE:
            self.searching = False
            self._drive(now)

    def _feed_forward_changed(self, before: int, now: float) -> None:
        # The keep-alive counts from the change, not from a keep-alive long gone.
        self.fed_s = now


def _no_reaction(motor: Zlac706Motor, before: object, now: float) -> None:
    """Ramps, the trapezoid speed, gains and the rated current apply to what comes next."""


#: What a setting's change sets off: ``reaction(motor, value_before, now)``.
_REACTIONS: dict[str, Callable[[Zlac706Motor, Any, float], None]] = {
    "mode": Zlac706Motor._mode_changed,
    "target_speed": Zlac706Motor._speed_changed,
    "target_torque": Zlac706Motor._torque_changed,
    "position_kf": Zlac706Motor._feed_forward_changed,
}
