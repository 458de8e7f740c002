"""The ZLAC706 driver behaviour shared by the CAN and the RS232 driver: planning under the
state machine's rules (``zlac706_state``), the targets a command sets, the state from
acknowledged writes, faults, keep-alive, follow stream, safe stop and telemetry. Each
protocol's module (``zlac706_can``, ``zlac706_rs232``) adds its frames, its registers' roles
and its refresh.
"""

from __future__ import annotations

import abc
import functools
import math
from collections.abc import Iterator, Sequence
from dataclasses import replace
from typing import Any, ClassVar

from busgate.codecs import zlac706_common as common
from busgate.errors import CommandError
from busgate.gateway.bus.request import Request
from busgate.gateway.drivers.base import Deadman, Driver, Effect, Follows, Setpoint
from busgate.gateway.drivers.zlac706_state import (
    RESTORED,
    SETTING,
    Mode,
    Role,
    RoleOf,
    Settings,
    Zlac706State,
    check,
    is_idempotent,
    reboot_jump_pulses,
    role_effect,
)
from busgate.schemas import zlac706 as schema
from busgate.schemas.joints import Quantity
from busgate.schemas.telemetry import flag_names


def fault_names(alarms: common.AlarmFlags) -> list[str]:
    """``["over_current", …]``: the fault bits of an alarm code, by name."""
    return list(_fault_names(int(alarms)))


@functools.lru_cache(maxsize=256)
def _fault_names(code: int) -> tuple[str, ...]:
    """Cached per code: telemetry asks for every heartbeat, and flag arithmetic is slow."""
    return tuple(flag_names(common.AlarmFlags(code).faults))


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


def settings_telemetry(settings: Settings) -> dict[str, Any]:
    """What the telemetry says of the settings the device acknowledged, in named units."""
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
    }


_STOP = schema.Velocity(op="velocity", rpm=0.0)
_NO_TORQUE = schema.Torque(op="torque", current_a=0.0)
_RELEASE = schema.Disable(op="disable")
_ENABLE = schema.Enable(op="enable")


# -- the driver -------------------------------------------------------------------------------


class Zlac706Driver(Driver):
    """What the CAN and the RS232 driver share: planning under the order rules, the state
    from acknowledged writes, faults, keep-alive, follow stream, safe stop, telemetry."""

    follow_preparation: ClassVar[tuple[str, ...]] = (
        '{"op":"set_mode","mode":"velocity"}',
        '{"op":"enable"}',
    )
    deadman: ClassVar[Deadman | None] = Deadman("velocity", '{"op":"velocity","rpm":0}')
    #: Per protocol: the frames of a command (``frames``), each register's role, the
    #: keep-alive period and the measured values its telemetry carries.
    roles: ClassVar[dict[int, RoleOf]]
    keepalive_period_s: ClassVar[float]
    measured_names: ClassVar[tuple[str, ...]] = ("position", "current_ma", "speed_rpm")
    #: Whether a follow tick can carry a position: a position target is one frame (CAN;
    #: RS232 writes one in two, high half first).
    streams_positions: ClassVar[bool]

    def __init__(self, name: str, device_id: int, **options: Any) -> None:
        super().__init__(name, device_id, **options)
        self.machine = Zlac706State()
        self.measured: dict[str, Any] = dict.fromkeys(self.measured_names)
        self.speed_sent_raw: int | None = None  # the last speed written (``went``)
        # The safe stop's requests (0 rpm, the release), built with the driver rather than
        # when an e-stop comes: its first frames wait for what their bus thread runs before
        # them (docs/performance.md, "An e-stop's frame first"). Speed and enable writes may
        # be repeated whatever the settings, so nothing they depend on changes meanwhile.
        self._zero_speed = self._built(_STOP)
        self._zero_torque = self._built(_NO_TORQUE)
        self._release = self._built(_RELEASE)
        #: The settings ``telemetry`` last told of, and what it said of them: said again only
        #: when they change (every heartbeat makes a state; settings seldom change).
        self._told: tuple[Settings | None, dict[str, Any]] = (None, {})
        #: A speed or a torque was commanded when it went offline: stopped when back.
        self._preset_when_gone = False
        self._position_at: float | None = None  # when the last position was reported

    # -- planning -------------------------------------------------------------------------------

    @staticmethod
    def frames(command: Any, device_id: int) -> list[Any]:
        """The protocol's frames of ``command`` to ``device_id``; each protocol sets it."""
        raise NotImplementedError

    def frames_of(self, command: Any) -> list[object]:
        return self.frames(command, self.device_id)

    def effect(self, frame: object) -> Effect:
        return role_effect(*self._role(frame, self.machine.settings))

    def plan_frames(self, command: Any, frames: Sequence[object]) -> list[Request]:
        """The command's requests, refused (``CommandError``) when the order rules forbid it."""
        requests, changes = [], {}
        for frame, role, value, outlook in self._walk(frames):
            if role is not None:
                check(role, value, outlook)
                changes.update(outlook.change(role, value))
            if role is Role.ENABLE and not value:
                # A preset starts the motor the moment it is enabled (the manual): a disable
                # leaves none behind for whoever enables it next, as a safe stop does.
                requests.extend(self.nothing_preset())
            requests.append(self._request(frame, role, outlook))
        self.machine.planned(changes)
        enabled = changes.get(Role.ENABLE.value)
        if enabled:
            self.estop_latched = False  # the re-enable op: the motor may run again
        elif enabled is False:
            self.switched_off()
        return requests

    def _walk(
        self, frames: Sequence[object]
    ) -> Iterator[tuple[object, Role | None, Any, Settings]]:
        """Each of ``frames`` with its role, its value and the settings it meets: the outlook
        once the writes queued so far and the frames before it have landed (the state is
        left as it is)."""
        outlook = self.machine.expected()
        for frame in frames:
            role, value = self._role(frame, outlook)
            yield frame, role, value, outlook
            if role is not None:
                outlook = replace(outlook, **outlook.change(role, value))

    def setpoints(self, frames: Sequence[object]) -> list[Setpoint]:
        """The position (pulses), speed (rpm) and torque (A) targets ``frames`` write. A
        relative position is judged from the drive's last target and from the position
        measured last (``_places``), and is ``None`` when neither is known or the position
        mode is not; a position's high half
        (RS232) sets nothing until the low half joins it."""
        return [
            Setpoint(self.device_id, *target)
            for _frame, role, value, outlook in self._walk(frames)
            for target in self._targets(role, value, outlook)
        ]

    def _targets(
        self, role: Role | None, value: Any, settings: Settings
    ) -> Iterator[tuple[Quantity, float | None]]:
        """What a write in ``role`` of ``value`` sets, each as ``(quantity, value)``: position
        mode's top speed is a speed too, and a move runs at it (``None`` while not set: the
        drive's own, which ``max_velocity`` may not allow). A speed or a torque other than 0,
        and an origin search (until it finds the index), turn the motor to a position not
        known: refused on a joint held within limits."""
        if role in (Role.SPEED, Role.MAX_SPEED):
            yield "velocity", common.rpm_from_speed_raw(value)
        elif role is Role.TORQUE:
            yield "effort", float(value / common.TORQUE_RAW_PER_A)
        elif role is Role.ONE_SHOT:
            yield "position", None
        elif role is Role.POSITION:
            for place in self._places(value, settings):
                yield "position", place
            yield "velocity", _rpm(settings.max_speed_raw)
        if role in (Role.SPEED, Role.TORQUE) and value:
            yield "position", None  # it turns on, to wherever it is stopped

    def why_positions_are_steps(self) -> str | None:
        relative = self.machine.expected().relative
        if relative is False:
            return None
        now = "relative" if relative else "not known"
        return (
            f"{self.name}'s position mode is {now}: a target would be a step from where it "
            'is; send {"op":"set_position_mode","relative":false} first'
        )

    def _places(self, value: int | None, settings: Settings) -> list[float | None]:
        """Where a position target of ``value`` may send the shaft, each judged against the
        joint's limits: an absolute one to itself; a relative one a step from the drive's
        last target (``Settings.place``: an audit's two steps back to back, each judged from
        the position measured, went past ``max``) and from the position measured last (the
        one base known before a first target): ``[None]`` when neither is known, or the mode
        is not."""
        if settings.relative is False:
            return [value]
        if settings.relative is None or value is None:
            return [None]
        bases = {base for base in (settings.place, self.measured["position"]) if base is not None}
        return [base + value for base in sorted(bases)] or [None]

    def _request(self, frame: object, role: Role | None, settings: Settings) -> Request:
        return Request.of(self.codec, frame, idempotent=is_idempotent(role, settings))

    def went(self, frame: object) -> None:
        """A speed write that went on the wire is the speed the gateway last commanded, which
        the keep-alive repeats: not the last one acknowledged (an ack that came too late must
        not bring back the speed before it, a stop above all), nor one still waiting to go
        (the keep-alive would send it ahead of its command, which may yet be taken out)."""
        role, value = self._role(frame, self.machine.settings)
        if role is Role.SPEED:
            self.speed_sent_raw = value

    def _built(self, command: Any) -> tuple[Request, ...]:
        """``command``'s requests, built once (the safe stop's: ``__init__``)."""
        settings = self.machine.settings
        return tuple(
            self._request(frame, self._role(frame, settings)[0], settings)
            for frame in self.frames(command, self.device_id)
        )

    def _unchecked(self, command: Any) -> list[Request]:
        """Requests the gateway itself sends (safe stop, init): no order rules apply."""
        return list(self._built(command))

    def _role(self, frame: object, settings: Settings) -> tuple[Role | None, Any]:
        register = getattr(frame, "register", None)
        if register is None:
            return None, None  # not a write (the RS232 monitor request)
        entry = self.roles.get(register, SETTING)
        return entry.role, entry.value(frame.value, settings)  # type: ignore[attr-defined]

    def safe_stop(self) -> list[Request]:
        """Nothing preset (``nothing_preset``), then release the motor.

        The queue is dropped on an e-stop, so the writes still in flight are forgotten."""
        self.note_estop()
        self.estop_latched = True
        self.machine.forget_pending()
        return [*self.nothing_preset(), *self._release]

    def nothing_preset(self) -> list[Request]:
        """0 rpm unless the mode is known not to be velocity, 0 A unless it is known not to be
        torque: what leaves the drive nothing to start the motor with at its next enable (the
        manual, 8.1.2 and 8.2.1: enabled, a preset speed turns it in velocity mode, a preset
        torque in torque mode)."""
        if self.machine.settings.mode in (Mode.TORQUE, None):
            return [*self.stale_stream(), *self._zero_torque]
        return self.stale_stream()

    def driving(self) -> bool:
        return self.machine.settings.enabled is True

    def hold_still(self) -> list[Request]:
        """Enabled again: in velocity mode at 0 rpm, written before the enable (a speed
        preset would start the motor at it: the stop wrote 0 rpm, but the enable must not
        hang on that), in position mode holding where it is (no target is written: a target
        moves it)."""
        stop = self.plan(_STOP) if self.machine.expected().mode is Mode.VELOCITY else []
        return stop + self.plan(_ENABLE)

    def stale_stream(self) -> list[Request]:
        """0 rpm: a client that stopped streaming speeds must not leave the wheel turning
        (unless the drive will be in another mode when it goes: the mode changes only while
        the motor is off, and a speed written after it would be ignored)."""
        if self.machine.expected().mode in (Mode.VELOCITY, None):
            return list(self._zero_speed)
        return []

    def keepalive(self, now: float) -> tuple[float, Request] | None:
        settings = self.machine.settings
        if settings.mode is not Mode.VELOCITY or not settings.enabled:
            return None  # asked before every decision of the bus thread: the cheap test first
        if self.commanded_speed_raw or settings.speed_raw:  # a stop not yet acknowledged turns
            return self.keepalive_period_s, self.keepalive_request()
        return None

    @property
    def commanded_speed_raw(self) -> int:
        """The speed the keep-alive repeats: the last one written, else the last one
        acknowledged. While an ack is lost or late the two differ, and the keep-alive goes on
        (a stop too) until the device has taken the last command."""
        if self.speed_sent_raw is None:
            return self.machine.settings.speed_raw or 0
        return self.speed_sent_raw

    @abc.abstractmethod
    def keepalive_request(self) -> Request:
        """What refreshes the device: the speed write (CAN), the monitor request (RS232)."""

    def mirror(self, state: dict[str, Any]) -> None:
        """The mode, the position mode, the power stage, the target and the position its
        worker's driver knows: a follow target is judged by them (speeds in velocity mode,
        positions in absolute position mode from a known place)."""
        told: dict[str, Any] = {}
        if state.get("mode") in tuple(Mode):
            told["mode"] = Mode(state["mode"])
        if state.get("position_mode") in ("relative", "absolute"):
            told["relative"] = state["position_mode"] == "relative"
        if "target" in state:  # where a position stream would start (``follow_target``)
            told["target_position"] = state["target"]
            self.measured["position"] = state.get("position")
        if isinstance(state.get("enabled"), bool):
            told["enabled"] = state["enabled"]
        if told:  # a state that says neither (offline, not yet read) leaves them as they were
            self.machine.settings = replace(self.machine.settings, **told)

    @property
    def follows(self) -> Follows | None:
        """Speeds in velocity mode, positions in absolute position mode where a target is
        one frame (CAN), else nothing: as the drive will be once the writes queued for it
        have landed."""
        outlook = self.machine.expected()
        if outlook.mode is Mode.VELOCITY:
            return "velocity"
        if self.streams_positions and outlook.mode is Mode.POSITION and outlook.relative is False:
            return "position"
        return None

    def unsent(self) -> None:
        # What the writes taken out would have set will not be: judge by what landed (the
        # keep-alive repeats only speeds that went: ``went``).
        self.machine.forget_pending()

    @property
    def turning_on(self) -> bool:
        return self.machine.expected().enabled is True

    def follow_target(self, payload: dict[str, Any]) -> float:
        """The speed of ``{"rpm": R}`` in velocity mode (with the motor enabled when its joint
        has a ``max_acceleration``, but for 0: a stop), or the position of ``{"position":
        P}`` in absolute position mode with the motor enabled (CAN only), once where it holds
        is known (a stream starts there: ``tickers.commanded``)."""
        target = self.follow_payload(payload)
        outlook = self.machine.expected()
        if target.position is None:
            check(Role.SPEED, target.rpm, outlook)
            if self.joint.max_acceleration is not None and target.rpm and not self.turning_on:
                raise CommandError(
                    f"joint {self.joint.name} ramps its speeds at its max_acceleration from "
                    "the speed the motor turns at, and the motor is "
                    f"{'off' if outlook.enabled is False else 'perhaps off (not known)'}: a "
                    "ramp now would leave the drive a speed its enable starts at at once; "
                    "send enable first; nothing was sent"
                )
            self.joint.check_position(None)  # a joint held within limits: turned past them
            return float(target.rpm)
        if not self.streams_positions:
            raise CommandError(
                "a ZLAC706 on RS232 takes a position in two frames, so its follow stream "
                'carries speeds only ({"rpm": R}); send positions as move commands'
            )
        check(Role.POSITION, target.position, outlook)  # position mode, enabled
        if outlook.relative is not False:
            now = "not known" if outlook.relative is None else "relative"
            raise CommandError(
                "a position follow stream needs absolute positions (set_position_mode with "
                f"relative false first): the position mode is {now}, and each target of a "
                "relative stream would move the motor on again"
            )
        if self.machine.settings.target_position is None and self.measured["position"] is None:
            raise CommandError(
                "a position follow stream starts from where the drive holds, which is not "
                "known now (it was enabled when the gateway did not know it was off, or it "
                "has not reported its position yet): its next heartbeat tells; nothing was sent"
            )
        return float(target.position)

    @staticmethod
    def follow_sample(t_s: float, index: int) -> dict[str, Any]:
        return {"rpm": round(300 * math.sin(t_s * math.pi + index))}

    @classmethod
    def follow_request(cls, targets: Sequence[tuple[Driver, float]]) -> Request:
        """The target write of one device (a ZLAC706 frame addresses one node): its position
        when it follows positions, else its speed."""
        if len(targets) != cls.follow_group_limit:
            raise CommandError(f"a ZLAC706 target write carries one device, not {len(targets)}")
        driver, value = targets[0]
        assert isinstance(driver, Zlac706Driver)
        command: schema.Move | schema.Velocity = (
            schema.Move(op="move", position=round(value))
            if driver.follows == "position"
            else schema.Velocity(op="velocity", rpm=value)
        )
        (frame,) = cls.frames(command, driver.device_id)
        return Request.of(cls.protocol_entry().codec, frame, idempotent=True)

    # -- interpreting ---------------------------------------------------------------------------

    def acknowledged(self, frame: object) -> None:
        """The device took the write ``frame``: the state follows. Enabled in position mode,
        the drive takes where the shaft is as its zero (5.1, the control modes: "以驱动器使能
        启动时刻为机械 0 点") and holds there: from off, target and position are 0, whatever
        they were; from not known, neither is known until the drive tells its position."""
        settings = self.machine.settings
        role, value = self._role(frame, settings)
        if role is not None:
            change = settings.change(role, value)
            if role is Role.ENABLE and "place" in change:  # its zero here (``Settings.change``)
                self.measured["position"] = change["place"]  # None: the next reading tells
            self.machine.acknowledged(change)
        if role in (Role.SPEED, Role.TORQUE):  # a fresh target: no old one left to clear
            self._preset_when_gone = False
        if role in RESTORED:
            self.applied_settings[frame.register] = Request.of(  # type: ignore[attr-defined]
                self.codec, frame, idempotent=True
            )

    def take_position(self, raw: int, now: float) -> None:
        """A position reported at ``now``; a jump to 0 from further than the motor turns
        meanwhile means the drive powered up again."""
        before, self.measured["position"] = self.measured["position"], raw
        since, self._position_at = self._position_at, now
        if raw == 0 and before is not None:
            elapsed_s = 0.0 if since is None else max(0.0, now - since)
            if abs(before) > reboot_jump_pulses(elapsed_s):
                self.rebooted(f"position counter back at 0 from {before}")

    def went_offline(self, reason: str) -> None:
        """Offline (no heartbeat or answer, or its bus down): the speed commanded before is
        no longer the gateway's to keep alive. The keep-alive repeats 0 rpm instead, and when
        a speed or a torque had been commanded, the settings restored when the drive is back
        are followed by nothing preset (``restore``): a drive that locked its shaft for want
        of a refresh, or that the gateway could not stop while it was away, must not take its
        old speed up again at the first refresh (docs/wire.md: nothing that moves it is sent
        until a client commands it again)."""
        if self.online:
            turning = self.commanded_speed_raw or self.machine.settings.torque_raw
            self._preset_when_gone = bool(turning)
        super().went_offline(reason)
        self.speed_sent_raw = 0
        # A power cycle is an outage: the first report after it is judged against the fixed
        # bound, not one grown by the time away (``take_position``; a review).
        self._position_at = None

    def restore(self) -> list[Request]:
        """The settings the drive had confirmed, then nothing preset if it was commanded to
        turn when it went (``went_offline``) and has taken no speed or torque since (a
        client's, sent once it was back, or this stop's own: ``acknowledged``)."""
        stop = self.nothing_preset() if self._preset_when_gone else []
        return [*super().restore(), *stop]

    def forget_on_reboot(self) -> None:
        """Power-up: released, every setting at its default until ``restore`` lands."""
        self.machine = Zlac706State()
        self.machine.settings = Settings(enabled=False, run_signal=False)
        self.speed_sent_raw = None

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
        machine = self.machine
        settings = machine.settings
        if self._told[0] is not settings:  # settings are frozen: a change is a new one
            self._told = (settings, settings_telemetry(settings))
        return {
            **self._told[1],
            "measured": self.has_measurements(),
            **self.measured,
            "faults": fault_names(machine.alarms),
        }

    def missed(self, now: float, frame: object = None) -> None:
        # An unanswered write may or may not have landed: stop counting on the queued ones,
        # and the power stage it switched is not known (an enable from there may or may not
        # move position mode's zero).
        self.machine.forget_pending()
        role = None if frame is None else self._role(frame, self.machine.settings)[0]
        if role is Role.ENABLE:
            self.machine.settings = replace(self.machine.settings, enabled=None, run_signal=None)
        elif role is Role.POSITION:  # it may have moved the drive's target, by a step
            self.machine.settings = replace(self.machine.settings, place=None)
        super().missed(now, frame)
