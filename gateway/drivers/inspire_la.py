"""Inspire LA driver: ``InspireLaDriver`` keeps one actuator's state as the gateway knows it,
planning each command's frames (``inspire_la_frames``) under the rules below.

Rules of ``InspireLaDriver``:

1. The power stage is known only from what was commanded (the status frame does not report
   it): on at power-up; ``estop`` switches it off until ``enable``, and motion planned in
   between is refused; ``pause`` switches it off too, but the next target switches it on again.
   Transitions are taken when a command is planned: commands on a bus run in the order they
   were planned, and an e-stop must hold from the moment it is asked for.
2. The over-temperature limit must stay ≥ rewarm + 5 °C (``codec.check_temperature_limits``).
   A write of either is checked against every value the other may hold on the device: the one
   last read or confirmed (at first the manual's default) and one planned but not yet confirmed.
   After a reboot, when both are written again (``restore``), the actuator holds what its
   flash had, which the driver does not know, and ignores a write out of the pair's range:
   rewarm goes to its floor (20 °C, below any limit) first, then the limit, then rewarm,
   each write within range whatever the actuator held.
3. Writes change the driver's picture of the control table, its id above all, only once the
   actuator's reply confirms them: polling a new id the actuator never took would lose it.
4. Faults come from status frames (polls, control and motion replies, writes answered the
   3.5.2 way); each change of the set emits one ``fault`` event naming what was raised and
   what cleared.
5. Where the actuator is commanded is the target the last frame nobody answers carried it
   (a follow tick, a move or a group frame without reply), from the moment it went, until a
   status frame tells its target: a bus carries one exchange at a time and the actuator
   takes each frame before the next, so a status answered after that frame went says its
   target or a newer one (the same, unless the frame was lost: then the one it really has).
   A follow frame has no reply, so its target reaches no telemetry before the next poll's;
   a stream or a play that starts meanwhile starts from it (``sent_position_raw``), not
   from the poll's older one, which would make its first tick a jump back.
"""

from __future__ import annotations

import enum
import functools
import math
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, cast

from busgate.codecs import inspire_la as codec
from busgate.codecs.errors import EncodeError
from busgate.errors import CommandError
from busgate.gateway.bus.request import Request
from busgate.gateway.drivers.base import Driver, FrameRules, RuledFrames
from busgate.gateway.drivers.inspire_la_frames import (
    frame_effect,
    frame_id_changes,
    frame_setpoints,
    frames_for,
)
from busgate.schemas import inspire_la as schema
from busgate.schemas.telemetry import flag_names

# --- the driver -----------------------------------------------------------------------------


class PowerStage(enum.StrEnum):
    """The power stage as commanded."""

    ON = "on"
    PAUSED = "paused"  # off; the next target switches it on
    ESTOPPED = "estopped"  # off until ``enable``


_POWER_AFTER: dict[type, PowerStage] = {
    schema.Enable: PowerStage.ON,
    schema.Estop: PowerStage.ESTOPPED,
    schema.Pause: PowerStage.PAUSED,
}

#: Sent twice, these do something else than once: a second save wears the flash, a set_id
#: retried to the old id goes nowhere, a second force zero takes another reading as zero, and a
#: raw write may be any of these. Everything else sets an absolute value or asks for one.
_NOT_IDEMPOTENT = frozenset(
    {schema.Save, schema.SetId, schema.Write, schema.SetBaudrate, schema.ZeroForce}
)

#: Control-table registers whose values the driver keeps (telemetry name → register).
_TRACKED = {
    "overcurrent_limit_ma": codec.OVERCURRENT_LIMIT,
    "overtemp_limit_c": codec.OVERTEMP_LIMIT,
    "rewarm_temperature_c": codec.REWARM_TEMPERATURE,
}

#: Telemetry name → field of the status frame.
_STATUS_FIELDS = {
    "position": "position_raw",
    "target": "target_raw",
    "temperature_c": "temperature_c",
    "current_ma": "current_ma",
    "force_g": "force_g",
}


def _request(frame: object, *, idempotent: bool) -> Request:
    return Request.of(codec, frame, idempotent=idempotent)


@functools.cache  # one an id (1-254)
def _estop_request(device_id: int) -> Request:
    """The e-stop (single control 0x23) of ``device_id``, built once, as the driver is made or
    its id changes, not when an e-stop comes: an e-stop's first frame waits for what its bus
    thread runs before it, and code not run for a while runs several times slower than in a
    loop (docs/performance.md, "An e-stop's frame first")."""
    return _request(codec.ControlCommand(device_id, codec.ControlCode.ESTOP), idempotent=True)


class InspireLaDriver(RuledFrames, Driver):
    """One Inspire LA actuator: commands → frames under the state rules, replies → state."""

    protocol: ClassVar[str] = "inspire_la"
    frame_rules: ClassVar[FrameRules] = FrameRules(frame_effect, frame_setpoints, frame_id_changes)
    follow_preparation: ClassVar[tuple[str, ...]] = ('{"op":"enable"}',)
    follow_group_limit: ClassVar[int] = codec.MAX_GROUP_TARGETS
    broadcast_id: ClassVar[int | None] = codec.BROADCAST_ID

    def __init__(self, name: str, device_id: int, **options: Any) -> None:
        super().__init__(name, device_id, **options)
        _estop_request(device_id)  # ready before its first e-stop
        self.power = PowerStage.ON  # the actuator works from power-up (manual 3.5.4)
        self.status: codec.StatusReply | None = None
        #: The target the last frame nobody answers gave it (a follow tick, a move or a group
        #: frame without reply), until a status frame says its target again (rule 5).
        self.target_sent_raw: int | None = None
        self.faults = codec.Fault(0)
        #: Raw values read or confirmed; the manual's defaults until then.
        self.table = {name: codec.REGISTERS.default(name) for name in _TRACKED.values()}
        self._planned: dict[str, int] = {}
        # What ``telemetry`` says of the status, the faults and the table, made when they
        # change rather than at every state (a state is taken after every exchange).
        self._measured: dict[str, Any] = dict.fromkeys(_STATUS_FIELDS)
        self._fault_names: tuple[str, ...] = ()
        self._limits = self._limits_of_table()

    # -- planning ---------------------------------------------------------------------------

    @property
    def estopped(self) -> bool:
        return self.power is PowerStage.ESTOPPED

    def frames_of(self, command: Any) -> list[codec.Frame]:
        return frames_for(command, self.device_id)

    def follow_mode_ids(self, frames: Sequence[object]) -> frozenset[int]:
        ids: set[int] = set()
        for frame in frames:
            if isinstance(frame, codec.FollowCommand):
                ids.add(frame.device_id)
            elif isinstance(frame, codec.GroupFollowCommand):
                ids.update(target.device_id for target in frame.targets)
        return frozenset(ids)

    def plan_frames(self, command: Any, frames: Sequence[object]) -> list[Request]:
        moves_me = self._moves_me(command)
        if moves_me:
            self.require_power()
        writes = [
            codec.register_values(frame.index, frame.data)
            for frame in frames
            if isinstance(frame, codec.WriteCommand)
        ]
        for values in writes:
            self._check_temperatures(values)
        idempotent = type(command) not in _NOT_IDEMPOTENT
        requests = [_request(frame, idempotent=idempotent) for frame in frames]
        # The state changes only once every check passed and every frame encoded.
        for values in writes:
            self._planned.update(values)
        if isinstance(command, schema.Estop):  # a client's own e-stop: reset as the gateway's
            self.note_estop()
        elif isinstance(command, schema.Pause):
            self.switched_off()
        self.power = self._power_after(command, moves_me)
        return requests

    def poll(self) -> list[Request]:
        """The status query: target, position, temperature, current, force, faults."""
        status = codec.ControlCommand(self.device_id, codec.ControlCode.STATUS)
        return [_request(status, idempotent=True)]

    def init(self) -> list[Request]:
        """A poll, then reads of the limits the driver keeps, so that the temperature rule
        is checked against the device's values rather than the manual's defaults."""
        reads = [
            codec.ReadCommand(self.device_id, register.address, register.size)
            for register in map(codec.REGISTERS.__getitem__, _TRACKED.values())
        ]
        return self.poll() + [_request(read, idempotent=True) for read in reads]

    def restore(self) -> list[Request]:
        """After a reboot the power stage is on again: an e-stop is sent again first. Both
        temperatures written again go in an order the actuator takes from any pair (rule 2)."""
        estop = [_estop_request(self.device_id)] if self.power is PowerStage.ESTOPPED else []
        rewarm = codec.REGISTERS[codec.REWARM_TEMPERATURE].address
        limit = codec.REGISTERS[codec.OVERTEMP_LIMIT].address
        if not {rewarm, limit} <= self.applied_settings.keys():
            return estop + super().restore()
        others = [r for index, r in self.applied_settings.items() if index not in (rewarm, limit)]
        floor, _ = codec.REGISTERS[codec.REWARM_TEMPERATURE].limits
        to_floor = codec.register_write(self.device_id, codec.REWARM_TEMPERATURE, floor)
        return [
            *estop,
            *others,
            _request(to_floor, idempotent=True),
            self.applied_settings[limit],
            self.applied_settings[rewarm],
        ]

    def safe_stop(self) -> list[Request]:
        """E-stop (single control 0x23): the power stage stays off until ``enable``."""
        self.note_estop()
        self.power = PowerStage.ESTOPPED
        return [_estop_request(self.device_id)]

    def driving(self) -> bool:
        return self.power is PowerStage.ON

    def hold_still(self) -> list[Request]:
        """Enable (no motion until a new target, manual 3.5.4), and a target at the present
        position, so that the target it had before the stop is gone for good; no target
        where the position read is none the gateway would send (``position_to_hold``)."""
        requests = self.plan(schema.Enable(op="enable"))
        here = self.position_to_hold(None if self.status is None else self.status.position_raw)
        if here is not None:
            requests += self.plan(schema.Move(op="move", position=here))
        return requests

    def stay_off(self) -> None:
        self.power = PowerStage.PAUSED  # off, and a new target switches it on

    def moved_by(self, frame: object) -> None:
        """A group target switches it on, paused or off (manual 3.5.4), as its own does, and
        is its target now, as its own is (rule 5)."""
        if self.power is not PowerStage.ESTOPPED:  # the authority let no motion reach it
            self.power = PowerStage.ON
        self._sent(frame)

    def sent_position_raw(self) -> int | None:
        return self.target_sent_raw

    def follow_target(self, payload: dict[str, Any]) -> int:
        """The position of a follow payload ``{"position": 0–2000}``."""
        return self.follow_payload(payload).position

    @staticmethod
    def follow_sample(t_s: float, index: int) -> dict[str, Any]:
        return {"position": round(1000 + 800 * math.sin(t_s * math.pi + index))}

    @classmethod
    def probe(cls, device_id: int) -> Request:
        return _request(codec.ControlCommand(device_id, codec.ControlCode.STATUS), idempotent=False)

    def group_entry(self, position: int, time_ms: int | None) -> dict[str, Any]:
        if time_ms is not None:
            raise CommandError("Inspire LA group moves have no move time; drop time_ms")
        return {"id": self.device_id, "position": position}

    @classmethod
    def follow_request(cls, targets: Sequence[tuple[Driver, Any]]) -> Request:
        """Follow without reply: ``0x19`` for one actuator, one broadcast ``0xF3`` for several.

        An e-stopped actuator is left out of the frame rather than failing its neighbours'
        tick; the first one's ``estopped`` refusal when none is left (an e-stop that came as
        a play was checked), ``CommandError`` when there are too many for one frame.
        """
        # A follow tick groups the targets of one driver class: here, actuators.
        actuators = cast("Sequence[tuple[InspireLaDriver, Any]]", targets)
        moving = [(d, p) for d, p in actuators if d.power is not PowerStage.ESTOPPED]
        if not moving:
            raise actuators[0][0].estopped_error()
        if len(moving) > cls.follow_group_limit:
            raise CommandError(
                f"{len(moving)} follow targets, one frame carries {cls.follow_group_limit}"
            )
        if len(moving) == 1:
            driver, position = moving[0]
            frame: codec.Frame = codec.FollowCommand(driver.device_id, position, reply=False)
        else:
            entries = tuple(codec.Target(d.device_id, p) for d, p in moving)
            frame = codec.GroupFollowCommand(entries)
        request = _request(frame, idempotent=True)
        for driver, _ in moving:
            driver.power = PowerStage.ON  # a target switches a paused stage on again
        return request

    def require_power(self) -> None:
        """Refused (``estopped``) unless a target would move the actuator."""
        if self.estopped:
            raise self.estopped_error()

    def _power_after(self, command: Any, moves_me: bool) -> PowerStage:
        if moves_me:
            return PowerStage.ON
        after = _POWER_AFTER.get(type(command), self.power)
        # A pause does not undo an e-stop: the actuator still waits for enable.
        if after is PowerStage.PAUSED and self.power is PowerStage.ESTOPPED:
            return PowerStage.ESTOPPED
        return after

    def _moves_me(self, command: Any) -> bool:
        if isinstance(command, schema.GroupMove | schema.GroupFollow):
            return any(target.id == self.device_id for target in command.targets)
        return isinstance(command, schema.Move | schema.Follow)

    def _check_temperatures(self, values: dict[str, int]) -> None:
        limit, rewarm = codec.OVERTEMP_LIMIT, codec.REWARM_TEMPERATURE
        if limit not in values and rewarm not in values:
            return
        try:
            codec.check_temperature_limits(
                min(self._possible(limit, values)), max(self._possible(rewarm, values))
            )
        except EncodeError as exc:
            raise EncodeError(
                f"{self.name}: {exc} (limit must be ≥ rewarm + 5 °C)",
                field=exc.field,
                value=exc.value,
            ) from exc

    def _possible(self, name: str, written: dict[str, int]) -> set[int]:
        """Every value register ``name`` may hold once ``written`` lands."""
        if name in written:
            return {written[name]}
        return {self.table[name], self._planned.get(name, self.table[name])}

    # -- interpreting -----------------------------------------------------------------------

    def apply(self, request: Request, reply: tuple[object, ...], now: float) -> dict[str, Any]:
        if request.expected is None:  # nobody answers it: that it went is all there is (rule 5)
            self._sent(request.frame)
            return {}
        if not reply:
            return {}  # unconfirmed: the actuator may or may not have done it
        result: dict[str, Any] = {}
        for event in reply:
            result.update(self._ON_REPLY[type(event)](self, event))
        if isinstance(request.frame, codec.WriteCommand):
            self._confirm(request.frame)
        return result

    def _sent(self, frame: object) -> None:
        """``frame``, which nobody answers, went: the target it carries this actuator is the
        one it was last sent (rule 5)."""
        for setpoint in frame_setpoints(frame):  # type: ignore[arg-type]
            if setpoint.device_id == self.device_id and setpoint.value is not None:
                self.target_sent_raw = round(setpoint.value)

    def _take_status(self, status: codec.StatusReply) -> dict[str, Any]:
        self.status = status
        self.target_sent_raw = None  # its target is as new as any sent before it (rule 5)
        self._measured = {key: getattr(status, field) for key, field in _STATUS_FIELDS.items()}
        if status.faults != self.faults:
            raised, cleared = status.faults & ~self.faults, self.faults & ~status.faults
            self.faults = status.faults
            self._fault_names = tuple(flag_names(status.faults))
            self.emit(
                "fault",
                faults=list(self._fault_names),
                raised=flag_names(raised),
                cleared=flag_names(cleared),
            )
        return {}

    def _take_read(self, read: codec.ReadReply) -> dict[str, Any]:
        values = codec.register_values(read.index, read.data)
        self._remember(values)
        return {
            "data": read.data.hex(),
            "values": {name: codec.REGISTERS[name].in_unit(raw) for name, raw in values.items()},
        }

    def _take_write(self, _reply: codec.WriteReply) -> dict[str, Any]:
        return {}  # one reserved byte: the write's own frame says what was confirmed

    _ON_REPLY: ClassVar[dict[type, Callable[..., dict[str, Any]]]] = {
        codec.StatusReply: _take_status,
        codec.ReadReply: _take_read,
        codec.WriteReply: _take_write,
    }

    def _confirm(self, write: codec.WriteCommand) -> None:
        values = codec.register_values(write.index, write.data)
        self._remember(values)
        if values.keys() <= set(_TRACKED.values()):  # a limit: in RAM until saved
            self.applied_settings[write.index] = _request(write, idempotent=True)
        if values.get(codec.ID, self.device_id) != self.device_id:
            self.emit("id_changed", old_id=self.device_id, new_id=values[codec.ID])
            self.device_id = values[codec.ID]
            _estop_request(self.device_id)  # ready before its first e-stop

    def _remember(self, values: dict[str, int]) -> None:
        for name in self.table.keys() & values.keys():
            self.table[name] = values[name]
            self._limits = self._limits_of_table()
            if self._planned.get(name) == values[name]:
                del self._planned[name]

    def _limits_of_table(self) -> dict[str, Any]:
        return {
            key: codec.REGISTERS[name].in_unit(self.table[name]) for key, name in _TRACKED.items()
        }

    def telemetry(self, now: float) -> dict[str, Any]:
        return {
            **self._measured,
            "faults": list(self._fault_names),
            "power": self.power.value,
            "enabled": self.power is PowerStage.ON,  # paused and estopped are not driving
            **self._limits,
        }
