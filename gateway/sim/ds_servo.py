"""A simulated DS (德晟) serial-bus smart servo, protocol v4.01 (manual ch. 2-3; docs/protocols.md).

The model owns one servo's control table, its shaft and its protections. Rules of this file:

1. State is the control table (``ds_servo_table.py``): ``TABLE_END`` bytes laid out by the
   codec's ``REGISTERS``, with the manual's defaults. Live values (present position, speed,
   current, temperature, the REG WRITE flag) are written into it from ``now`` just before a
   READ, so a read sees real values.
2. Motion is a function of time: a ``Move`` (origin, target, start, duration) gives the position
   at any ``now``. Nothing ticks; protections that trip after a delay are settled lazily at the
   start of every call, from ``now``.
3. A servo answers only a frame that names its own id: broadcast (254), ACTION and SYNC WRITE
   are carried out in silence. Every reply carries the status bits (voltage, temperature,
   overload) as they stand after the command.
4. Saved registers (the manual's 掉电保存 column: everything below the torque switch 0x28)
   survive ``reboot``; RESET (instruction 06) restores the factory values of all of them,
   id included.

Where the manual is silent, this file chooses (each choice is commented where it applies):
move time 0 runs at ``TOP_SPEED_STEPS_PER_S``; torque is on at power-up; targets are clamped
to the angle limits; a write changing the id is answered under the old id; bytes written to a
read-only or unknown address are ignored and the write is still answered (the codec's decoder
already discards such frames, so on the wire the servo stays silent). Registers whose meaning
the manual leaves open (speed adjust 0x12 and 0x41, unload condition, centre offset, motor
mode and direction, lock flag) are stored and read back but do not change the motion.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

from busgate.codecs.ds_servo import (
    ADDRESS_ONLY_WRITES,
    BROADCAST_ID,
    GOTO_PRESET_ADDRESSES,
    PRESET_ADDRESSES,
    REGISTERS,
    TIMING,
    Action,
    Ping,
    Read,
    RegWrite,
    Reset,
    ServoStatus,
    StatusReply,
    SyncWrite,
    Write,
)
from busgate.gateway.sim.ds_servo_table import DsServoTable

#: Move time 0 means "as fast as it goes" (0x2C); the manual gives no speed. 4096 steps per
#: second is a full turn (0-4095) in 1 s, 60° in 0.17 s: a typical standard-size bus servo.
#: A move never runs faster than this, whatever move time it asks for.
TOP_SPEED_STEPS_PER_S: Final = 4096.0
#: Where the shaft is when the simulation starts: the centre, as servos ship.
CENTRE_POSITION: Final = 2048
#: Motor current (0x2E, mA), which the manual documents only by its unit: a plausible draw
#: when released, holding, moving and straining against a blocked shaft.
CURRENT_MA: Final = {"released": 0, "holding": 20, "moving": 250, "straining": 1500}
AMBIENT_C: Final = 25
#: What 0x3F reads while ``over_temperature`` is injected.
OVER_TEMPERATURE_C: Final = 80


@dataclass(frozen=True, slots=True)
class Move:
    """A straight run from ``origin`` to ``target`` (raw steps) over ``duration_s`` from
    ``start_s``; a hold is a move of duration 0."""

    start_s: float
    origin: float
    target: int
    duration_s: float = 0.0

    @classmethod
    def hold(cls, position: float, now: float) -> Move:
        return cls(now, position, round(position))

    def position(self, now: float) -> float:
        if now >= self.start_s + self.duration_s:
            return float(self.target)
        done = max(0.0, now - self.start_s) / self.duration_s
        return self.origin + (self.target - self.origin) * done

    def speed(self, now: float) -> float:
        """Steps per second at ``now`` (0 outside the move)."""
        if not self.start_s <= now < self.start_s + self.duration_s:
            return 0.0
        return abs(self.target - self.origin) / self.duration_s


class DsServoDevice:
    """One DS servo on a simulated bus (``SimDevice``); ``position_raw`` is where it starts."""

    turnaround_s = (
        TIMING.reply_min_s,
        TIMING.reply_max_s,
    )

    def __init__(self, device_id: int, *, position_raw: int = CENTRE_POSITION) -> None:
        REGISTERS["servo_id"].check(device_id)
        REGISTERS["present_position"].check(position_raw)
        self._lock = threading.Lock()
        self._table = DsServoTable()
        self._table.set("servo_id", device_id)
        self._environment = ServoStatus(0)  # injected over-temperature / under-voltage
        self._move = Move.hold(position_raw, 0.0)
        self._power_up(0.0)

    # --- SimDevice ---------------------------------------------------------------------------

    @property
    def device_id(self) -> int:
        return self._table.get("servo_id")

    def accepts(self, command: object) -> bool:
        if isinstance(command, Action):
            return True
        if isinstance(command, SyncWrite):
            return any(t.device_id == self.device_id for t in command.targets)
        return getattr(command, "device_id", None) in (self.device_id, BROADCAST_ID)

    def handle(self, command: object, now: float) -> list[object]:
        """Carry out ``command``; answer with a status reply when it named this servo's id.

        The reply goes out under the id the frame named, even when the command changed it.
        """
        addressed = getattr(command, "device_id", BROADCAST_ID)
        with self._lock:
            self._settle(now)
            data = _HANDLERS[type(command)](self, command, now)
            if addressed == BROADCAST_ID:
                return []
            return [StatusReply(addressed, self._status(), data)]

    def spontaneous(self, now: float) -> list[object]:
        return []  # a DS servo only ever answers

    def reboot(self, now: float) -> None:
        """Power-cycle: saved registers stay, the rest powers up; trips and injected
        conditions clear (the power-cycle that ends a real servo's protection)."""
        with self._lock:
            self._table.power_cycle()
            self._environment = ServoStatus(0)
            self._power_up(now)

    def inject_fault(self, fault: str, now: float) -> None:
        """``over_temperature`` / ``under_voltage``: the status bit (and 0x3F) until reboot;
        ``stall``: the shaft jams and protection trips after the stall protection time (0x06);
        ``overload`` (alias ``over_current``): protection trips at once."""
        with self._lock:
            try:
                raise_fault = _FAULTS[fault]
            except KeyError:
                raise ValueError(
                    f"a DS servo has no fault {fault!r}; it has {', '.join(sorted(_FAULTS))}"
                ) from None
            self._settle(now)
            raise_fault(self, now)

    # --- the control table -------------------------------------------------------------------

    def _refresh(self, now: float) -> None:
        """Write the live values into the table, as the servo's firmware keeps them current."""
        self._table.set("present_position", self._position(now))
        self._table.set("speed", min(round(self._move.speed(now)), 0xFFFF))
        self._table.set("current", CURRENT_MA[self._effort(now)])
        hot = self._environment & ServoStatus.TEMPERATURE
        self._table.set("temperature", OVER_TEMPERATURE_C if hot else AMBIENT_C)
        self._table.set("reg_write_pending", int(self._pending is not None))

    # --- the shaft and its protections -------------------------------------------------------

    def _power_up(self, now: float) -> None:
        """RAM state after power-up or RESET: the shaft holds where it is, nothing pending."""
        self._move = Move.hold(self._position(now), now)
        self._table.set("target_position", self._move.target)
        self._pending: tuple[int, int] | None = None
        self._jammed_since: float | None = None
        self._overloaded = False

    def _position(self, now: float) -> int:
        return round(self._move.position(now))

    def _effort(self, now: float) -> str:
        if not self._table.get("torque_enable"):
            return "released"
        if self._jammed_since is not None:
            return "straining"
        return "moving" if self._move.speed(now) else "holding"

    def _status(self) -> ServoStatus:
        return self._environment | (ServoStatus.OVERLOAD if self._overloaded else 0)

    def _settle(self, now: float) -> None:
        """Trip the stall protection if the shaft has been jammed for the protection time."""
        if self._jammed_since is None:
            return
        trip_at = self._jammed_since + self._table.get("stall_protection_time")
        if now >= trip_at:
            self._trip(trip_at)

    def _overheat(self, now: float) -> None:
        self._environment |= ServoStatus.TEMPERATURE

    def _brown_out(self, now: float) -> None:
        self._environment |= ServoStatus.VOLTAGE

    def _jam(self, now: float) -> None:
        """The shaft stops where it is; the motor strains until protection trips."""
        self._move = Move.hold(self._move.position(now), now)
        if self._table.get("torque_enable") and not self._overloaded:
            self._jammed_since = now
            self._settle(now)

    def _trip(self, now: float) -> None:
        """Overload protection: the servo unloads (torque off) and sets bit 5 until torque is
        switched on again (the manual says only that the bit is set once protection trips)."""
        self._move = Move.hold(self._move.position(now), now)
        self._jammed_since = None
        self._overloaded = True
        self._table.set("torque_enable", 0)

    def _start_move(self, now: float) -> None:
        """Run to the target register in the move time register, if the torque is on.

        The target is clamped to the angle limits (the manual clamps to 0-4095 and gives the
        limits no description; a servo with limits holds its motion inside them).
        """
        span = REGISTERS["target_position"]
        low = max(self._table.get("min_angle"), span.limits[0])
        high = min(self._table.get("max_angle"), span.limits[1])
        target = min(max(self._table.get("target_position"), low), high)
        self._table.set("target_position", target)
        if not self._table.get("torque_enable") or self._jammed_since is not None:
            return  # with torque off (or a jammed shaft) the target is stored, nothing moves
        origin = self._move.position(now)
        fastest = abs(target - origin) / TOP_SPEED_STEPS_PER_S
        duration = max(self._table.get("move_time") / 1000, fastest)
        self._move = Move(now, origin, target, duration)

    def _switch_torque(self, now: float, before: bytes) -> None:
        """Off: the shaft stops where it is. On: it holds where it is (not a stale target) and
        an overload trip is cleared. Writing the value it already has changes nothing."""
        address = REGISTERS["torque_enable"].address
        if bool(before[address]) == bool(self._table.get("torque_enable")):
            return
        self._move = Move.hold(self._move.position(now), now)
        self._jammed_since = None
        if self._table.get("torque_enable"):
            self._overloaded = False
            self._table.set("target_position", self._move.target)

    # --- commands ----------------------------------------------------------------------------

    def _ping(self, command: Ping, now: float) -> bytes:
        return b""

    def _read(self, command: Read, now: float) -> bytes:
        self._refresh(now)
        return self._table.read(command.address, command.length)

    def _write(self, command: Write, now: float) -> bytes:
        if command.address in ADDRESS_ONLY_WRITES:
            action, number = _PRESET_ACTIONS[command.address]
            action(self, number, now)
            return b""
        before = bytes(self._table)
        touched = self._table.store(command.address, command.data)
        for register in sorted(touched, key=lambda r: r.address):
            effect = _WRITE_EFFECTS.get(register.name)
            if effect is not None:
                effect(self, now, before)
        return b""

    def _reg_write(self, command: RegWrite, now: float) -> bytes:
        # The manual: a REG WRITE arriving before ACTION replaces the one stored.
        self._pending = (command.position_raw, command.time_ms)
        return b""

    def _action(self, command: Action, now: float) -> bytes:
        if self._pending is not None:
            self._run_to(*self._pending, now)
            self._pending = None
        return b""

    def _sync_write(self, command: SyncWrite, now: float) -> bytes:
        own = next(t for t in command.targets if t.device_id == self.device_id)
        self._run_to(own.position_raw, own.time_ms, now)
        return b""

    def _run_to(self, position_raw: int, time_ms: int, now: float) -> None:
        """What a 4-byte write at 0x2A does: REG WRITE (on ACTION) and SYNC WRITE write there."""
        self._table.set("target_position", min(position_raw, 0xFFFF))
        self._table.set("move_time", time_ms)
        self._start_move(now)

    def _reset(self, command: Reset, now: float) -> bytes:
        """Factory settings for every register, id included (the manual: "all data")."""
        self._table = DsServoTable()
        self._power_up(now)
        return b""

    def _store_preset(self, number: int, now: float) -> None:
        # The manual: "the system writes the current position"; the address alone is sent.
        self._table.set(f"preset_{number}", self._position(now))

    def _goto_preset(self, number: int, now: float) -> None:
        # The manual gives no move time for it: the move time register applies, as for 0x2A.
        self._table.set("target_position", self._table.get(f"preset_{number}"))
        self._start_move(now)


_HANDLERS: dict[type, Callable[[DsServoDevice, Any, float], bytes]] = {
    Ping: DsServoDevice._ping,
    Read: DsServoDevice._read,
    Write: DsServoDevice._write,
    RegWrite: DsServoDevice._reg_write,
    Action: DsServoDevice._action,
    SyncWrite: DsServoDevice._sync_write,
    Reset: DsServoDevice._reset,
}

# What a written register sets off once the whole write is stored (so a 4-byte write at 0x2A
# moves in its own move time); each gets the table as it was before the write. A new id needs
# no action: ``device_id`` reads the table, so it takes effect with the next frame.
_WRITE_EFFECTS: dict[str, Callable[[DsServoDevice, float, bytes], None]] = {
    "torque_enable": DsServoDevice._switch_torque,
    "target_position": lambda device, now, before: device._start_move(now),
}

_PRESET_ACTIONS: dict[int, tuple[Callable[[DsServoDevice, int, float], None], int]] = {
    **{address: (DsServoDevice._store_preset, n) for n, address in enumerate(PRESET_ADDRESSES, 1)},
    **{
        address: (DsServoDevice._goto_preset, n)
        for n, address in enumerate(GOTO_PRESET_ADDRESSES, 1)
    },
}

_FAULTS: dict[str, Callable[[DsServoDevice, float], None]] = {
    "over_temperature": DsServoDevice._overheat,
    "under_voltage": DsServoDevice._brown_out,
    "stall": DsServoDevice._jam,
    "overload": DsServoDevice._trip,
    "over_current": DsServoDevice._trip,  # the servo's one current protection is its overload
}
