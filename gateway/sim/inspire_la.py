"""A simulated Inspire LA micro linear actuator (a force-sensing LAF, so force reads are real).

The model owns the actuator's control table (RAM, and the "flash" that ``save`` writes and a
power cycle reads back), its motion, its temperature and its protections. Rules of this file:

1. Nothing ticks. The state is a motion segment (a ``Stroke`` of ``inspire_la_physics.py``:
   start position, start time, goal) and a thermal state at a time; every entry point first
   calls ``_advance(now)``, which carries the state forward (heating, auto-clearing faults,
   over-temperature) to ``now``.
2. The control table (``inspire_la_table.py``) is bytes laid out by the codec's
   ``REGISTERS`` and checked with its rules (``check_write``, ``check_temperature_limits``);
   live registers (position, force) are filled in when read. Out-of-range values are
   ignored, never raised: a device does not crash on a host's bad frame.
3. Every reply is a frame of the codec; frames to id 255 are executed and never answered.

Where the manual is silent, the choices are marked "Manual silent" below.
"""

from __future__ import annotations

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
)
from busgate.gateway.sim.inspire_la_physics import (
    AMBIENT_C,
    FORCE_ADC_MID,
    Stroke,
    current_ma,
    force_adc,
    force_g,
    warmed,
)
from busgate.gateway.sim.inspire_la_table import InspireLaTable

FULL_STROKE_RAW = REGISTERS[TARGET_POSITION].limits[1]
#: Over-current and stall clear by themselves after 5 s, twice; the third one latches.
AUTO_CLEAR_S = 5.0
AUTO_CLEARS_BEFORE_LATCH = 2
SELF_CLEARING = (Fault.OVER_CURRENT, Fault.STALL)
#: Faults during which the actuator stops with its power stage off.
STOPPING = Fault.OVER_CURRENT | Fault.STALL | Fault.OVER_TEMPERATURE
#: "Motor fault" goes away by itself once the motor draws more than this.
MOTOR_FAULT_CLEAR_MA = 30


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
        self._table = InspireLaTable(device_id)
        self._temp_c, self._temp_t = AMBIENT_C, 0.0
        self._stroke = Stroke(0.0, 0.0, 0.0, self.speed_per_s)
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
            TARGET_POSITION: lambda now: self._go(self._table.get(TARGET_POSITION), now),
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
        return getattr(command, "device_id", None) in (self.device_id, BROADCAST_ID)

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
        return self._stroke.position(now)

    def temperature_c(self, now: float) -> float:
        self._advance(now)
        return self._temp_c

    def status(self, now: float) -> StatusReply:
        """The status frame the actuator would send at ``now``."""
        self._advance(now)
        return self._status(now)

    # --- power-up and the passing of time ------------------------------------------------

    def _power_up(self, now: float) -> None:
        self._table.power_up()
        self.device_id = self._table.get(ID)
        self._baudrate = BAUD_RATES[self._table.get(BAUD_CODE)]
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
            arrival = self._stroke.arrival_s
            stop = arrival if self._temp_t < arrival < end else end
            self._temp_c = warmed(self._temp_c, self._current_ma(self._temp_t), stop - self._temp_t)
            self._temp_t = stop

    def _check_temperature(self, now: float) -> None:
        tenths = self._temp_c * TENTHS_PER_DEGREE
        if tenths > self._table.get(OVERTEMP_LIMIT):
            self._trip(Fault.OVER_TEMPERATURE, now)
        elif self._faults & Fault.OVER_TEMPERATURE and tenths < self._table.get(REWARM_TEMPERATURE):
            self._recover(Fault.OVER_TEMPERATURE, now)

    # --- motion and current --------------------------------------------------------------

    def _current_ma(self, t: float) -> int:
        return current_ma(powered=self._powered, moving=self._stroke.moving(t), load_g=self.load_g)

    def _hold(self, now: float) -> None:
        """Stop where the rod is now; the target register follows."""
        position = self._stroke.position(now)
        self._stroke = Stroke(now, position, position, self.speed_per_s)
        self._table.put(TARGET_POSITION, round(position))

    def _go(self, target: int, now: float) -> None:
        """A new target: the register takes it; the rod moves unless e-stopped or faulted."""
        # Manual silent on targets outside 0–2000: ignored, like any out-of-range write.
        if not 0 <= target <= FULL_STROKE_RAW:
            return
        self._table.put(TARGET_POSITION, target)
        if self._estopped or self._faults & STOPPING:
            return
        self._stroke = Stroke(now, self._stroke.position(now), float(target), self.speed_per_s)
        self._powered = True  # after a pause, a target alone moves it again (3.5.4)
        self._check_current(now)

    def _check_current(self, now: float) -> None:
        if self._current_ma(now) > self._table.get(OVERCURRENT_LIMIT):
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
        self._temp_c = max(self._temp_c, self._table.get(OVERTEMP_LIMIT) / TENTHS_PER_DEGREE + 1.0)
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
        self._table.save()

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
        live = {
            "current_position": round(self._stroke.position(now)),
            "force": force_g(self.load_g, self._zero_adc),
            "force_raw": force_adc(self.load_g),
        }
        return ReadReply(
            self.device_id, command.index, self._table.read(command.index, command.length, live)
        )

    def _write(self, command: WriteCommand, now: float) -> StatusReply:
        """Write the table. Answered by the status frame (3.5.2, 3.7.1, 3.7.5, 3.7.6) rather
        than 3.4.1's one reserved byte: the examples name the reply of each write, from the id
        in force after the write (3.6: a new id is used at once)."""
        touched = self._table.write(command.index, command.data)
        for name, effect in self._write_effects.items():
            if name in touched:
                effect(now)
        return self._status(now)

    def _take_id(self, now: float) -> None:
        self.device_id = self._table.get(ID)

    def _zero_force(self, now: float) -> None:
        self._zero_adc = force_adc(self.load_g)
        # Manual silent on what the register reads afterwards: back to 0, the action done.
        self._table.put(FORCE_ZERO, 0)

    # --- what the actuator reports -------------------------------------------------------

    def _status(self, now: float) -> StatusReply:
        # The two "internal data" words look like the force ADC and its zero in the manual's
        # example (1800, 1802); this model reports those.
        return StatusReply(
            device_id=self.device_id,
            target_raw=self._table.get(TARGET_POSITION),
            position_raw=round(self._stroke.position(now)),
            temperature_c=round(self._temp_c),
            current_ma=self._current_ma(now),
            force_g=force_g(self.load_g, self._zero_adc),
            faults=self._faults,
            internal_1=force_adc(self.load_g),
            internal_2=self._zero_adc,
        )
