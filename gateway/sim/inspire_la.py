"""A simulated Inspire LA micro linear actuator (a force-sensing LAF, so force reads are real).

The model owns the actuator's control table (RAM, and the "flash" that ``save`` writes and a
power cycle reads back), its motion, its temperature and its protections. Rules of this file:

1. Nothing ticks. The state is a motion segment (start position, start time, goal) and a
   thermal state at a time; every entry point first calls ``_advance(now)``, which carries
   the state forward (heating, auto-clearing faults, over-temperature) to ``now``.
2. The control table is bytes laid out by the codec's ``REGISTERS`` and checked with its
   rules (``check_write``, ``check_temperature_limits``); live registers (position, force)
   are filled in when read. Out-of-range values are ignored, never raised: a device does not
   crash on a host's bad frame.
3. Every reply is a frame of the codec; frames to id 255 are executed and never answered.

Where the manual is silent, the choices are marked "Manual silent" below.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from busgate.codecs.errors import EncodeError
from busgate.codecs.inspire_la import (
    BAUD_CODE,
    BAUD_RATES,
    BROADCAST_ID,
    FORCE_ZERO,
    ID,
    OVERCURRENT_LIMIT,
    OVERTEMP_LIMIT,
    REGISTERS,
    REWARM_TEMPERATURE,
    TABLE_SIZE,
    TARGET_POSITION,
    TENTHS_PER_DEGREE,
    TIMING,
    ControlCode,
    ControlCommand,
    Fault,
    FollowCommand,
    GroupFollowCommand,
    GroupMoveCommand,
    MoveCommand,
    ReadCommand,
    ReadReply,
    StatusReply,
    WriteCommand,
    check_span,
    check_temperature_limits,
    check_write,
)
from busgate.codecs.registers import Register

FULL_STROKE_RAW = REGISTERS[TARGET_POSITION].maximum
#: Table addresses 0–1 read AA 55 ("table header", manual 3.6).
TABLE_HEADER = b"\xaa\x55"

# Electrical and thermal figures. The manual gives none; these are plausible for a micro
# actuator on 8 V: a free move draws a few hundred mA, a self-locking lead screw holds its
# position on almost nothing, and the motor warms with I² over minutes.
HOLD_CURRENT_MA = 12
MOVING_CURRENT_MA = 220
#: Extra current a push against a load costs while moving.
MA_PER_GRAM_LOAD = 0.1
AMBIENT_C = 25.0
#: Equilibrium rise over ambient per A²: a continuous free move settles ~15 °C warmer.
RISE_C_PER_A2 = 300.0
THERMAL_TAU_S = 120.0

#: Over-current and stall clear by themselves after 5 s, twice; the third one latches.
AUTO_CLEAR_S = 5.0
AUTO_CLEARS_BEFORE_LATCH = 2
SELF_CLEARING = (Fault.OVER_CURRENT, Fault.STALL)
#: Faults during which the actuator stops with its power stage off.
STOPPING = Fault.OVER_CURRENT | Fault.STALL | Fault.OVER_TEMPERATURE
#: "Motor fault" goes away by itself once the motor draws more than this.
MOTOR_FAULT_CLEAR_MA = 30

#: The force sensor: a 12-bit ADC centred on no load, in grams per count.
FORCE_ADC_MID = 2048
FORCE_ADC_MAX = 4095
GRAMS_PER_COUNT = 5

_LIVE = ("current_position", "force", "force_raw")


class InspireLaDevice:
    """One LA actuator on the bus, at raw stroke 0–2000; a full stroke takes ``stroke_s``.

    ``load_g`` is the external force on the rod (grams, may be changed at any time): it is
    what the force sensor reads and it raises the current of a move.
    """

    turnaround_s = (
        TIMING.reply_min_s,
        TIMING.reply_max_s,
    )

    def __init__(self, device_id: int, *, stroke_s: float = 1.0, load_g: float = 0.0) -> None:
        if not stroke_s > 0:
            raise ValueError(f"stroke_s must be positive, not {stroke_s}")
        self.speed_per_s = FULL_STROKE_RAW / stroke_s
        self.load_g = load_g
        self._flash = _factory_table(device_id)
        self._temp_c, self._temp_t = AMBIENT_C, 0.0
        self._pos0, self._t0, self._goal = 0.0, 0.0, 0.0
        self._handlers: dict[type, Callable[..., StatusReply | ReadReply | None]] = {
            ReadCommand: self._read,
            WriteCommand: self._write,
            MoveCommand: self._motion,
            FollowCommand: self._motion,
            ControlCommand: self._control,
            GroupMoveCommand: self._group,
            GroupFollowCommand: self._group,
        }
        self._controls: dict[ControlCode, Callable[[float], None]] = {
            ControlCode.ENABLE: self._enable,
            ControlCode.ESTOP: self._estop,
            ControlCode.PAUSE: self._pause,
            ControlCode.SAVE: self._save,
            ControlCode.STATUS: lambda now: None,
            ControlCode.CLEAR_FAULT: self._clear_fault,
        }
        self._injectors: dict[str, Callable[[float], None]] = {
            "over_current": lambda now: self._trip(Fault.OVER_CURRENT, now),
            "stall": lambda now: self._trip(Fault.STALL, now),
            "over_temperature": self._overheat,
            "motor_fault": lambda now: self._raise_flags(Fault.MOTOR_FAULT),
        }
        # What a write of each register does besides storing its value. The baud code does
        # nothing until it is saved and the actuator power-cycled (3.6).
        self._write_effects: dict[str, Callable[[float], None]] = {
            ID: self._take_id,
            TARGET_POSITION: lambda now: self._go(self._get(TARGET_POSITION), now),
            FORCE_ZERO: self._zero_force,
            OVERCURRENT_LIMIT: self._check_current,
            OVERTEMP_LIMIT: self._check_temperature,
            REWARM_TEMPERATURE: self._check_temperature,
        }
        self._power_up(0.0)

    # --- the SimDevice interface ---------------------------------------------------------

    def accepts(self, command: object) -> bool:
        """Its own id or 255; a group frame when one of its entries names this actuator."""
        if isinstance(command, GroupMoveCommand | GroupFollowCommand):
            return any(t.device_id == self.device_id for t in command.targets)
        if type(command) not in self._handlers:
            return False
        return command.device_id in (self.device_id, BROADCAST_ID)

    def handle(self, command: object, now: float) -> list[object]:
        """Execute ``command``; the status frame, a read reply, or nothing (id 255, no-reply
        instructions)."""
        self._advance(now)
        reply = self._handlers[type(command)](command, now)
        if reply is None or getattr(command, "device_id", BROADCAST_ID) == BROADCAST_ID:
            return []
        return [reply]

    def spontaneous(self, now: float) -> list[object]:
        """Nothing: an LA only ever answers."""
        return []

    def reboot(self, now: float) -> None:
        """Power cycle: the RAM table is read back from flash (what ``save`` stored), faults and
        their counts are forgotten, motion stops where it is. The motor keeps its heat."""
        self._advance(now)
        self._power_up(now)
        self._check_temperature(now)

    def inject_fault(self, fault: str, now: float) -> None:
        """Raise ``over_current``, ``stall``, ``over_temperature`` (heats the motor past its
        limit) or ``motor_fault``."""
        try:
            inject = self._injectors[fault]
        except KeyError:
            known = ", ".join(sorted(self._injectors))
            raise ValueError(f"unknown fault {fault!r} for inspire_la; known: {known}") from None
        self._advance(now)
        inject(now)

    # --- what tests and the CLI look at --------------------------------------------------

    @property
    def baudrate(self) -> int:
        """The line speed the actuator uses now: the baud code read from flash at power-up."""
        return self._baudrate

    def position(self, now: float) -> float:
        """Present position, raw stroke units."""
        self._advance(now)
        return self._position_at(now)

    def temperature_c(self, now: float) -> float:
        self._advance(now)
        return self._temp_c

    def status(self, now: float) -> StatusReply:
        """The status frame the actuator would send at ``now``."""
        self._advance(now)
        return self._status(now)

    # --- power-up and the passing of time ------------------------------------------------

    def _power_up(self, now: float) -> None:
        self._ram = bytearray(self._flash)
        self.device_id = self._get(ID)
        self._baudrate = BAUD_RATES[self._get(BAUD_CODE)]
        self._faults = Fault(0)
        self._clear_at: dict[Fault, float] = {}
        self._auto_clears = dict.fromkeys(SELF_CLEARING, 0)
        self._powered, self._estopped = True, False
        # The force zero is the factory one again: the table has no register that keeps it.
        self._zero_adc = FORCE_ADC_MID
        # Manual silent on the target after power-up; "waits for commands" (3.6) reads as:
        # it holds where it is, and the target register says so.
        self._hold(now)

    def _advance(self, now: float) -> None:
        now = max(now, self._temp_t)
        for deadline, fault in sorted((t, f) for f, t in self._clear_at.items() if t <= now):
            self._heat_until(deadline)
            del self._clear_at[fault]
            self._auto_clears[fault] += 1
            self._recover(fault, deadline)
        self._heat_until(now)
        self._check_temperature(now)
        if self._faults & Fault.MOTOR_FAULT and self._current_ma(now) > MOTOR_FAULT_CLEAR_MA:
            self._faults &= ~Fault.MOTOR_FAULT

    def _heat_until(self, end: float) -> None:
        """First-order heating, exact per stretch of constant current (split at arrival)."""
        while self._temp_t < end:
            arrival = self._arrival()
            stop = arrival if self._temp_t < arrival < end else end
            amps = self._current_ma(self._temp_t) / 1000
            settle = AMBIENT_C + RISE_C_PER_A2 * amps * amps
            decay = math.exp(-(stop - self._temp_t) / THERMAL_TAU_S)
            self._temp_c = settle + (self._temp_c - settle) * decay
            self._temp_t = stop

    def _check_temperature(self, now: float) -> None:
        tenths = self._temp_c * TENTHS_PER_DEGREE
        if tenths > self._get(OVERTEMP_LIMIT):
            self._trip(Fault.OVER_TEMPERATURE, now)
        elif self._faults & Fault.OVER_TEMPERATURE and tenths < self._get(REWARM_TEMPERATURE):
            self._recover(Fault.OVER_TEMPERATURE, now)

    # --- motion and current --------------------------------------------------------------

    def _position_at(self, t: float) -> float:
        delta = self._goal - self._pos0
        travelled = self.speed_per_s * max(0.0, t - self._t0)
        return self._pos0 + math.copysign(min(abs(delta), travelled), delta)

    def _arrival(self) -> float:
        return self._t0 + abs(self._goal - self._pos0) / self.speed_per_s

    def _moving(self, t: float) -> bool:
        return t < self._arrival()

    def _current_ma(self, t: float) -> int:
        if not self._powered:
            return 0
        if self._moving(t):
            return round(MOVING_CURRENT_MA + MA_PER_GRAM_LOAD * abs(self.load_g))
        return HOLD_CURRENT_MA

    def _hold(self, now: float) -> None:
        """Stop where the rod is now; the target register follows."""
        self._pos0 = self._goal = self._position_at(now)
        self._t0 = now
        self._put(TARGET_POSITION, round(self._pos0))

    def _go(self, target: int, now: float) -> None:
        """A new target: the register takes it; the rod moves unless e-stopped or faulted."""
        # Manual silent on targets outside 0–2000: ignored, like any out-of-range write.
        if not 0 <= target <= FULL_STROKE_RAW:
            return
        self._put(TARGET_POSITION, target)
        if self._estopped or self._faults & STOPPING:
            return
        self._pos0, self._t0, self._goal = self._position_at(now), now, float(target)
        self._powered = True  # after a pause, a target alone moves it again (3.5.4)
        self._check_current(now)

    def _check_current(self, now: float) -> None:
        if self._current_ma(now) > self._get(OVERCURRENT_LIMIT):
            self._trip(Fault.OVER_CURRENT, now)

    # --- faults --------------------------------------------------------------------------

    def _raise_flags(self, fault: Fault) -> None:
        self._faults |= fault

    def _trip(self, fault: Fault, now: float) -> None:
        """A protection stops the actuator with its power stage off."""
        if self._faults & fault:
            return
        self._hold(now)
        self._powered = False
        self._faults |= fault
        if fault in SELF_CLEARING and self._auto_clears[fault] < AUTO_CLEARS_BEFORE_LATCH:
            self._clear_at[fault] = now + AUTO_CLEAR_S

    def _recover(self, fault: Fault, now: float) -> None:
        """Back to the power-up state, waiting for a command (3.6, 3.8)."""
        self._faults &= ~fault
        self._powered, self._estopped = True, False

    def _overheat(self, now: float) -> None:
        self._temp_c = max(self._temp_c, self._get(OVERTEMP_LIMIT) / TENTHS_PER_DEGREE + 1.0)
        self._check_temperature(now)

    def _clear_fault(self, now: float) -> None:
        """Clears over-current, stall and motor fault and their counts; never over-temperature."""
        clearable = Fault.OVER_CURRENT | Fault.STALL | Fault.MOTOR_FAULT
        cleared = self._faults & clearable
        self._faults &= ~clearable
        self._clear_at.clear()
        self._auto_clears = dict.fromkeys(SELF_CLEARING, 0)
        if cleared & STOPPING:
            self._recover(cleared, now)

    # --- single control codes ------------------------------------------------------------

    def _enable(self, now: float) -> None:
        # Power on, but no motion until a new target (3.5.4: "enable, then send a position").
        if not self._faults & STOPPING:
            self._powered, self._estopped = True, False

    def _estop(self, now: float) -> None:
        self._hold(now)
        self._powered, self._estopped = False, True

    def _pause(self, now: float) -> None:
        self._hold(now)
        self._powered = False

    def _save(self, now: float) -> None:
        self._flash = bytes(self._ram)

    # --- commands --------------------------------------------------------------------------

    def _control(self, command: ControlCommand, now: float) -> StatusReply:
        self._controls[command.code](now)
        return self._status(now)

    def _motion(self, command: MoveCommand | FollowCommand, now: float) -> StatusReply | None:
        # Positioning and follow differ in how the host sends targets, not in how this model
        # moves: at constant speed without modelled acceleration, planner and tracker coincide.
        self._go(command.position_raw, now)
        return self._status(now) if command.reply else None

    def _group(self, command: GroupMoveCommand | GroupFollowCommand, now: float) -> None:
        # Manual silent on an id listed twice: the first entry counts.
        self._go(
            next(t for t in command.targets if t.device_id == self.device_id).position_raw, now
        )

    def _read(self, command: ReadCommand, now: float) -> ReadReply | None:
        # Manual silent on a span past the table's end: no answer (the host times out).
        try:
            check_span(command.index, command.length)
        except EncodeError:
            return None
        table = self._snapshot(now)
        return ReadReply(
            self.device_id,
            command.index,
            bytes(table[command.index : command.index + command.length]),
        )

    def _write(self, command: WriteCommand, now: float) -> StatusReply:
        """Write the table. Answered by the status frame (3.5.2, 3.7.1, 3.7.5, 3.7.6) rather
        than 3.4.1's one reserved byte: the examples name the reply of each write, from the id
        in force after the write (3.6: a new id is used at once)."""
        touched = self._apply_write(command.index, command.data)
        for name, effect in self._write_effects.items():
            if name in touched:
                effect(now)
        return self._status(now)

    def _apply_write(self, index: int, data: bytes) -> set[str]:
        """Store the write when the manual's rules allow it; return the registers it touched.

        Manual silent on refused writes: the table is left alone and the reply is the usual
        status frame, which carries no error field. A write of part of a register is judged
        by the whole register it leaves behind.
        """
        try:
            check_write(index, data)
            touched = {r for r in REGISTERS.covering(index, len(data)) if r}
            table = bytearray(self._ram)
            table[index : index + len(data)] = data
            for register in touched:
                register.check(_get(table, register))
            check_temperature_limits(
                _get(table, REGISTERS[OVERTEMP_LIMIT]), _get(table, REGISTERS[REWARM_TEMPERATURE])
            )
        except EncodeError:
            return set()
        self._ram = table
        return {register.name for register in touched}

    def _take_id(self, now: float) -> None:
        self.device_id = self._get(ID)

    def _zero_force(self, now: float) -> None:
        self._zero_adc = self._force_adc()
        # Manual silent on what the register reads afterwards: back to 0, the action done.
        self._put(FORCE_ZERO, 0)

    # --- what the actuator reports -------------------------------------------------------

    def _force_adc(self) -> int:
        counts = FORCE_ADC_MID + round(self.load_g / GRAMS_PER_COUNT)
        return min(max(counts, 0), FORCE_ADC_MAX)

    def _force_g(self) -> int:
        return (self._force_adc() - self._zero_adc) * GRAMS_PER_COUNT

    def _snapshot(self, now: float) -> bytearray:
        """The RAM table with the live registers filled in as of ``now``."""
        table = bytearray(self._ram)
        live = (round(self._position_at(now)), self._force_g(), self._force_adc())
        for name, value in zip(_LIVE, live, strict=True):
            _put(table, REGISTERS[name], value)
        return table

    def _status(self, now: float) -> StatusReply:
        # The two "internal data" words look like the force ADC and its zero in the manual's
        # example (1800, 1802); this model reports those.
        return StatusReply(
            device_id=self.device_id,
            target_raw=self._get(TARGET_POSITION),
            position_raw=round(self._position_at(now)),
            temperature_c=round(self._temp_c),
            current_ma=self._current_ma(now),
            force_g=self._force_g(),
            faults=self._faults,
            internal_1=self._force_adc(),
            internal_2=self._zero_adc,
        )

    def _get(self, name: str) -> int:
        return _get(self._ram, REGISTERS[name])

    def _put(self, name: str, value: int) -> None:
        _put(self._ram, REGISTERS[name], value)


def _factory_table(device_id: int) -> bytes:
    """The manual's defaults (3.6), with the id this actuator was given."""
    table = bytearray(TABLE_SIZE)
    table[0:2] = TABLE_HEADER
    for register in REGISTERS:
        if register.default is not None:
            _put(table, register, register.default)
    _put(table, REGISTERS[ID], REGISTERS[ID].check(device_id))
    return bytes(table)


def _get(table: bytes | bytearray, register: Register) -> int:
    raw = table[register.address : register.end]
    return int.from_bytes(raw, "little", signed=register.signed)


def _put(table: bytearray, register: Register, value: int) -> None:
    table[register.address : register.end] = value.to_bytes(
        register.size, "little", signed=register.signed
    )
