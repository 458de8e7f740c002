"""DS servo driver: a ``busgate.schemas.ds_servo`` command becomes the codec frames that do it,
and the servo's status replies become its state (``DsServoDriver``).

Every op is one frame (``frames_for``, also used by the CLI); each frame says what it does
(``frame_effect``), the position targets it sets (``frame_setpoints``) and the id it gives
(``frame_id_changes``). ``action`` and ``group_move`` always go to the broadcast id, whatever
``device_id`` says: they are bus-level ops, one frame for every servo on the bus; the other
ops go to ``device_id`` and the codec refuses the ones the manual forbids to broadcast (ping,
read, deferred move) when it encodes them.

Rules of the driver (below ``frames_for``):

1. State changes only in ``apply``, from what the servo confirmed with its status reply, or,
   for frames that bring none (SYNC WRITE, ACTION), from the frame having gone out.
2. Every reply carries the status byte (voltage, temperature, overload): faults are taken
   from every exchange, and each change of them emits exactly one ``fault`` event.
3. Values are named by the codec (``values_from``) whatever op carried them: a client's own
   ``read`` of the position updates the telemetry as a poll does.
4. The id changes (``set_id``, ``write`` at 0x05, ``reset``) only once the servo confirmed.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any, ClassVar, Final

from busgate.codecs import ds_servo as codec
from busgate.errors import CommandError
from busgate.gateway.bus.request import Request
from busgate.gateway.drivers.base import Driver, Effect, FrameRules, IdChange, RuledFrames, Setpoint
from busgate.schemas import ds_servo as schema
from busgate.schemas.telemetry import flag_names

_TORQUE = codec.REGISTERS["torque_enable"].address
_SERVO_ID = codec.REGISTERS["servo_id"].address


@functools.cache  # one an id (1-250)
def _torque_off(device_id: int) -> Request:
    """Torque off for ``device_id``, as an e-stop sends it: built once, as the driver is made
    or its id changes, as the Inspire LA's e-stop is (``inspire_la._estop_request``)."""
    return Request.of(codec, codec.Write(device_id, _TORQUE, b"\x00"), idempotent=True)


def _move(command: schema.Move, device_id: int) -> codec.Frame:
    if command.deferred:
        return codec.RegWrite(device_id, command.position, command.time_ms)
    return codec.Write(
        device_id, codec.MOVE_ADDRESS, codec.move_data(command.position, command.time_ms)
    )


def _group_move(command: schema.GroupMove, device_id: int) -> codec.Frame:
    return codec.SyncWrite(
        tuple(codec.SyncTarget(t.id, t.position, t.time_ms) for t in command.targets)
    )


_FRAME_FOR: dict[type, Callable[[Any, int], codec.Frame]] = {
    schema.Ping: lambda c, device_id: codec.Ping(device_id),
    schema.Read: lambda c, device_id: codec.Read(device_id, c.address, c.length),
    schema.Write: lambda c, device_id: codec.Write(device_id, c.address, bytes.fromhex(c.data)),
    schema.Move: _move,
    schema.Action: lambda c, device_id: codec.Action(),
    schema.GroupMove: _group_move,
    schema.Torque: lambda c, device_id: codec.Write(device_id, _TORQUE, bytes([int(c.on)])),
    schema.SetId: lambda c, device_id: codec.Write(device_id, _SERVO_ID, bytes([c.new_id])),
    schema.GotoPreset: lambda c, device_id: codec.Write(
        device_id, codec.GOTO_PRESET_ADDRESSES[c.n - 1], b""
    ),
    schema.StorePreset: lambda c, device_id: codec.Write(
        device_id, codec.PRESET_ADDRESSES[c.n - 1], b""
    ),
    schema.Reset: lambda c, device_id: codec.Reset(device_id),
}


def frames_for(command: Any, device_id: int) -> list[codec.Frame]:
    """The frames, in order, that carry out ``command`` on servo ``device_id``.

    >>> from busgate.codecs.ds_servo import encode
    >>> move = schema.COMMAND_ADAPTER.validate_json('{"op":"move","position":2048,"time_ms":1000}')
    >>> [encode(f).hex(" ") for f in frames_for(move, 254)]   # manual 2.1
    ['ff ff fe 07 03 2a 08 00 03 e8 da']
    """
    return [_FRAME_FOR[type(command)](command, device_id)]


#: Registers after whose write no target says where the shaft goes: the centre's offset (the
#: same target is then another angle), the angle limits (the servo clamps each target to
#: them: a target below a raised ``min_angle`` is driven to it), and the motor mode and its
#: direction (the manual documents neither value: a servo turned into a motor may spin).
_SHIFTS_TARGETS = frozenset(
    {"centre_offset", "min_angle", "max_angle", "motor_mode", "motor_direction"}
)
#: Registers whose write moves the shaft: the target (with the move time after it), the
#: go-to-preset addresses, and those above, which change where or how it drives with its
#: torque on.
_MOTION_REGISTERS = frozenset(
    {
        "target_position",
        *_SHIFTS_TARGETS,
        *(r.name for r in map(codec.REGISTERS.at, codec.GOTO_PRESET_ADDRESSES) if r is not None),
    }
)
_FRAME_EFFECTS: dict[type, Effect] = {
    codec.Ping: Effect.READ,
    codec.Read: Effect.READ,
    codec.RegWrite: Effect.MOTION,  # a stored move: the next ACTION starts it
    codec.Action: Effect.MOTION,
    codec.SyncWrite: Effect.MOTION,
    # Factory settings switch torque on (its factory value): the servo drives its shaft
    # again, so an e-stopped one refuses it as it refuses a move.
    codec.Reset: Effect.MOTION,
}


def frame_effect(frame: codec.Frame) -> Effect:
    """What ``frame`` does: torque off stops; a write reaching a register that moves the
    shaft (``_MOTION_REGISTERS``) moves; other writes change settings."""
    if not isinstance(frame, codec.Write):
        return _FRAME_EFFECTS[type(frame)]
    if frame.address == _TORQUE and frame.data == b"\x00":
        return Effect.STOP
    if _writes_motion(frame):
        return Effect.MOTION
    return Effect.SETTING


def frame_id_changes(frame: codec.Frame) -> list[IdChange]:
    """The id ``frame`` gives the servo: a write of the id register (``set_id`` is one), or
    the factory id after a reset (manual 2.3.7: "all data")."""
    new_id = codec.id_given(frame)
    if new_id is None:
        return []
    return [IdChange(frame.device_id, new_id)]  # type: ignore[union-attr]  # a Write, a Reset


def _torque_written(frame: object) -> int | None:
    """The torque switch's value a write sets (``None``: the write does not reach it)."""
    if isinstance(frame, codec.Write):
        return codec.values_from(frame.address, frame.data).get("torque_enable")
    return None


def _writes_motion(frame: codec.Write) -> bool:
    """Whether ``frame`` reaches a register that moves the shaft (``_MOTION_REGISTERS``)."""
    return bool(codec.REGISTERS.touched(frame.address, len(frame.data)) & _MOTION_REGISTERS)


def frame_setpoints(frame: codec.Frame) -> list[Setpoint]:
    """The position targets ``frame`` sets, raw: a stored move's (its ACTION sets nothing
    more), each SYNC WRITE target under its own id, and a write's value of the target
    register; ``None`` for a go-to-preset (the preset is stored in the servo), a write of
    part of the target register, and one of ``_SHIFTS_TARGETS`` or a factory reset, which
    restores them (where the shaft goes then is the servo's)."""
    if isinstance(frame, codec.Reset):
        return [Setpoint(frame.device_id, "position", None)]
    if isinstance(frame, codec.RegWrite):
        return [Setpoint(frame.device_id, "position", frame.position_raw)]
    if isinstance(frame, codec.SyncWrite):
        return [Setpoint(t.device_id, "position", t.position_raw) for t in frame.targets]
    if isinstance(frame, codec.Write) and _writes_motion(frame):
        values = codec.values_from(frame.address, frame.data)
        if values.keys() & _SHIFTS_TARGETS:  # the target, if written too, is another angle
            return [Setpoint(frame.device_id, "position", None)]
        return [Setpoint(frame.device_id, "position", values.get("target_position"))]
    return []


# --- the driver ------------------------------------------------------------------------------

#: Registers one poll reads, and the telemetry name each value is published under. The speed
#: register's unit is undocumented ("?"), so it is published raw, not as ``speed_rpm``.
_MEASURED: dict[str, str] = {
    "current": "current_ma",
    "present_position": "position",
    "speed": "speed_raw",
    "temperature": "temperature_c",
}

#: Ops whose repeat is harmless, so a lost reply may be retried: queries, absolute targets and
#: switches. A REG WRITE is among them since a new one replaces the one stored (manual 2.3.4).
#: Not: write (it may hit anything), set_id and reset (once the first took effect the servo
#: has left the id a repeat is sent to, so the repeat can only fail), store_preset (the shaft
#: may have moved in between), action (it starts whatever was stored since).
_IDEMPOTENT: frozenset[type] = frozenset(
    {schema.Ping, schema.Read, schema.Move, schema.GroupMove, schema.Torque, schema.GotoPreset}
)


def _no_write_only_between(start: int, end: int) -> bool:
    """True when ``[start, end)`` holds no write-only address (reserved ones are fine)."""
    return all(r is None or r.access.readable for r in codec.REGISTERS.covering(start, end - start))


def poll_spans(names: Iterable[str]) -> tuple[tuple[int, int], ...]:
    """The fewest ``(address, length)`` reads that cover the registers ``names``.

    Neighbours share one read across reserved addresses, but not across write-only ones (the
    go-to-preset addresses 0x3C-0x3E): the manual marks those "write" with no data type, and
    ``check_read`` only keeps a read inside the table, so reading them is left untried.

    >>> [(hex(a), n) for a, n in poll_spans(_POLLED)]
    [('0x28', 20), ('0x3f', 1)]
    """
    spans: list[tuple[int, int]] = []
    for register in sorted((codec.REGISTERS[n] for n in names), key=lambda r: r.address):
        if spans and _no_write_only_between(sum(spans[-1]), register.address):
            start = spans[-1][0]
            spans[-1] = (start, register.end - start)
        else:
            spans.append((register.address, register.size))
    for address, length in spans:
        codec.check_read(address, length)
    return tuple(spans)


#: A poll also reads the torque switch and the target: a servo that powered up again shows
#: torque on (its factory value) where the gateway had switched it off.
_POLLED: Final = (*_MEASURED, "torque_enable", "target_position")
_POLL_SPANS: Final = poll_spans(_POLLED)


class DsServoDriver(RuledFrames, Driver):
    """One DS servo: commands become frames, status replies become its state.

    Rules: ``plan`` changes nothing; ``apply`` changes the state only from what the servo
    confirmed (its status reply), or, for frames that bring no reply (SYNC WRITE, ACTION),
    from the frame having been sent. Every reply carries the status byte, so faults follow
    every exchange, not only polls.
    """

    protocol: ClassVar[str] = "ds_servo"
    frame_rules: ClassVar[FrameRules] = FrameRules(frame_effect, frame_setpoints, frame_id_changes)
    follow_preparation: ClassVar[tuple[str, ...]] = ('{"op":"torque","on":true}',)
    follow_group_limit: ClassVar[int] = codec.MAX_SYNC_TARGETS
    broadcast_id: ClassVar[int | None] = codec.BROADCAST_ID

    def __init__(self, name: str, device_id: int, **options: Any) -> None:
        super().__init__(name, device_id, **options)
        _torque_off(device_id)  # ready before its first e-stop
        self.measured: dict[str, int | None] = dict.fromkeys(_MEASURED.values())
        self.target: int | None = None
        self.pending_target: int | None = None  # a REG WRITE waiting for ACTION
        #: A move may be stored for ACTION that this driver did not see answered: one sent
        #: unanswered (``missed``), or one stored before it was made (a gateway, or a bus
        #: worker, started anew: the servo kept it); an ACTION seen, or a reboot, clears it.
        self._store_unknown = True
        self.torque_on: bool | None = None
        self.faults = codec.ServoStatus(0)

    # -- planning -------------------------------------------------------------------------------

    def frames_of(self, command: Any) -> list[codec.Frame]:
        if type(command) not in _FRAME_FOR:
            raise CommandError(f"ds_servo has no command {type(command).__name__}")
        return frames_for(command, self.device_id)

    def plan_frames(self, command: Any, frames: Sequence[object]) -> list[Request]:
        if isinstance(command, schema.SetId) and command.new_id == self.device_id:
            # Nothing to change, and a confirmation could not be told from a no-op.
            raise CommandError(f"servo {self.name} already has id {self.device_id}")
        idempotent = type(command) in _IDEMPOTENT
        requests = [Request.of(codec, frame, idempotent=idempotent) for frame in frames]
        # By what the frames write, as the ZLAC706 judges its control word: a raw write of
        # the torque switch is the torque op's frame, and lets the servo move or not alike.
        for torque in map(_torque_written, frames):
            if torque:
                self.estop_latched = False  # the re-enable op: the servo may move again
            elif torque == 0:
                self.switched_off()
        return requests

    def poll(self) -> list[Request]:
        return [
            Request.of(codec, codec.Read(self.device_id, address, length), idempotent=True)
            for address, length in _POLL_SPANS
        ]

    def safe_stop(self) -> list[Request]:
        """Torque off: the manual documents no value for the lock (e-stop) flag at 0x30, and
        torque off is its one documented way to stop driving the shaft. The servo goes limp:
        a load it was holding against gravity is no longer held. Then a move stored for
        ACTION (a REG WRITE) is replaced by one to where the servo is (a new REG WRITE
        replaces the stored one, manual 2.3.4): an ACTION after the e-stop's reset, which any
        client may send to the bus, started the move stored before it."""
        self.note_estop()
        self.estop_latched = True
        return [_torque_off(self.device_id), *self._stored_here()]

    def _stored_here(self) -> list[Request]:
        """A move to where the servo is, stored for ACTION in place of one that may be stored
        (sent, answered or not, and no ACTION since); where it is not known, a move to the
        target it has, which torque on drives it to all the same, so that an ACTION moves it
        no further than torque on would; nothing where no move may be stored, or neither is
        known."""
        if self.pending_target is None and not self._store_unknown:
            return []
        here = self.position_to_hold(self.measured["position"])
        if here is None:
            here = self.position_to_hold(self.target)
        if here is None:
            return []
        return [Request.of(codec, codec.RegWrite(self.device_id, here, 0), idempotent=True)]

    def driving(self) -> bool:
        return self.torque_on is True

    def hold_still(self) -> list[Request]:
        """The target at the present position first (and the move stored for ACTION, if one
        may be: the stop's was where the servo was then, and a limp servo sags), then torque
        on: the servo holds where it is instead of going back to the target it had. Its
        position not known, or none the gateway would send (``position_to_hold``), it stays
        off (torque on would drive it to an old target)."""
        here = self.position_to_hold(self.measured["position"])
        if here is None:
            self.stay_off()
            return []
        requests = self.plan(schema.Move(op="move", position=here)) + self._stored_here()
        return requests + self.plan(schema.Torque(op="torque", on=True))

    def follow_target(self, payload: dict[str, Any]) -> int:
        return self.follow_payload(payload).position

    @staticmethod
    def follow_sample(t_s: float, index: int) -> dict[str, Any]:
        return {"position": round(2048 + 1500 * math.sin(t_s * math.pi + index))}

    @classmethod
    def probe(cls, device_id: int) -> Request:
        return Request.of(codec, codec.Ping(device_id))

    def group_entry(self, position: int, time_ms: int | None) -> dict[str, Any]:
        return {"id": self.device_id, "position": position, "time_ms": time_ms or 0}

    @classmethod
    def follow_request(cls, targets: Sequence[tuple[Driver, Any]]) -> Request:
        """One SYNC WRITE at 0x2A; each servo's move time is its follow period, so it glides
        to each target in one period instead of jumping at full speed."""
        if not 1 <= len(targets) <= cls.follow_group_limit:
            raise CommandError(
                f"a SYNC WRITE carries 1 to {cls.follow_group_limit} servos, not {len(targets)}"
            )
        frame = codec.SyncWrite(
            tuple(
                codec.SyncTarget(driver.device_id, position, round(driver.follow_period_s * 1000))
                for driver, position in targets
            )
        )
        return Request.of(codec, frame, idempotent=True)

    # -- interpreting ---------------------------------------------------------------------------

    def apply(self, request: Request, reply: tuple[object, ...], now: float) -> dict[str, Any]:
        answer: codec.StatusReply | None = None
        if request.expected is not None:
            # The owner matched the reply to the request: it is the servo's status frame.
            answer = next((e for e in reply if isinstance(e, codec.StatusReply)), None)
            if answer is None:
                return {}  # unconfirmed: the servo may or may not have done it
            self._set_faults(answer.status)
        return _APPLY[type(request.frame)](self, request.frame, answer) or {}

    def telemetry(self, now: float) -> dict[str, Any]:
        return {
            **self.measured,
            "target": self.target,
            "pending_target": self.pending_target,
            "torque_on": self.torque_on,
            "enabled": self.torque_on,
            "faults": flag_names(self.faults),
        }

    def forget_on_reboot(self) -> None:
        """Power-up: torque on, holding where it is; no target of ours stands, nor a move
        stored for ACTION."""
        self.target = self.pending_target = None
        self._store_unknown = False
        self.torque_on = True

    def _set_faults(self, status: codec.ServoStatus) -> None:
        if status == self.faults:
            return
        raised, cleared = status & ~self.faults, self.faults & ~status
        self.faults = status
        self.emit(
            "fault",
            faults=flag_names(status),
            raised=flag_names(raised),
            cleared=flag_names(cleared),
        )

    def _change_id(self, new_id: int, reason: str) -> None:
        if new_id != self.device_id:
            self.emit("id_changed", old_id=self.device_id, new_id=new_id, reason=reason)
            self.device_id = new_id
            _torque_off(new_id)  # ready before its first e-stop

    def missed(self, now: float, frame: object = None) -> None:
        """A torque write unanswered may have landed all the same: the torque is not known
        until it is read (and a read of it on is then no reboot); a REG WRITE unanswered may
        be stored all the same."""
        if isinstance(frame, codec.Write) and frame.address == _TORQUE:
            self.torque_on = None
        if isinstance(frame, codec.RegWrite):
            self._store_unknown = True
        super().missed(now, frame)

    def _applied_read(self, frame: codec.Read, answer: codec.StatusReply) -> dict[str, Any]:
        values = codec.values_from(frame.address, answer.data)
        if values.get("torque_enable") == 1:
            if self.torque_on is False:
                self.rebooted("torque on again, its power-up value")
            else:  # on as asked, or known again: a switch-off to restore no longer stands
                self.applied_settings.pop(_TORQUE, None)
        self._take_values(values)
        return {"data": answer.data.hex(), "values": values}

    def _applied_write(self, frame: codec.Write, answer: object) -> None:
        if frame.address == _TORQUE and frame.data == b"\x00":  # torque on is the power-up value
            self.applied_settings[_TORQUE] = Request.of(codec, frame, idempotent=True)
        elif frame.address == _TORQUE:
            self.applied_settings.pop(_TORQUE, None)
        if frame.address in codec.GOTO_PRESET_ADDRESSES:
            self.target = None  # the preset's position is on the servo, unknown here
        self._take_values(codec.values_from(frame.address, frame.data))

    def _take_values(self, values: dict[str, int]) -> None:
        """Values read from or confirmed written to the servo, whichever op carried them."""
        for register, value in values.items():
            if register in _MEASURED:
                self.measured[_MEASURED[register]] = value
        if "target_position" in values:
            self.target = values["target_position"]
        if "torque_enable" in values:
            self.torque_on = bool(values["torque_enable"])
        if "servo_id" in values:
            self._change_id(values["servo_id"], "written")

    def _applied_reg_write(self, frame: codec.RegWrite, answer: object) -> None:
        self.pending_target, self._store_unknown = frame.position_raw, False

    def _applied_action(self, frame: codec.Action, answer: object) -> None:
        # Sent by any driver on the bus, ACTION starts every servo's stored move; this one
        # knows only its own REG WRITE.
        self._store_unknown = False
        if self.pending_target is not None:
            self.target, self.pending_target = self.pending_target, None

    def _applied_sync_write(self, frame: codec.SyncWrite, answer: object) -> None:
        for target in frame.targets:
            if target.device_id == self.device_id:
                self.target = target.position_raw

    def moved_by(self, frame: object) -> None:
        """An ACTION starts this servo's stored move, a SYNC WRITE gives it its target, sent
        through another servo's command as through its own (nobody answers either)."""
        if isinstance(frame, codec.Action | codec.SyncWrite):
            _APPLY[type(frame)](self, frame, None)

    def _applied_reset(self, frame: codec.Reset, answer: object) -> None:
        """Factory settings for "all data" (manual 2.3.7), the id included: the servo now
        answers at the factory id, and what was commanded is gone."""
        self.target = self.pending_target = self.torque_on = None
        self._store_unknown = False
        self._change_id(codec.REGISTERS.default("servo_id"), "reset")


# What a confirmed (or, without a reply, sent) frame does to the state; reads also answer.
_APPLY: dict[type, Callable[[DsServoDriver, Any, Any], dict[str, Any] | None]] = {
    codec.Ping: lambda driver, frame, answer: None,
    codec.Read: DsServoDriver._applied_read,
    codec.Write: DsServoDriver._applied_write,
    codec.RegWrite: DsServoDriver._applied_reg_write,
    codec.Action: DsServoDriver._applied_action,
    codec.SyncWrite: DsServoDriver._applied_sync_write,
    codec.Reset: DsServoDriver._applied_reset,
}
