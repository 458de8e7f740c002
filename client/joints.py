"""A device as a joint, in SI units (docs/joints.md), of either face: ``Device.joint``, each
method written once (``steps.py``) as the device's are (``devices.py``).

Rules of this file:

1. What the joint is (its name, type, unit, calibration and limits) is what its gateway's
   ``info`` said when the device was found (``base.Found.joint``); nothing here converts a
   unit or checks a limit: the gateway does both, and refuses (``out_of_range``, naming the
   joint, the limit and the value) what is beyond one.
2. A joint's values are those of its device's state (``JointState``, from the same reading);
   its commands are its device's, sent the same way (under the device's claim, when this
   client holds one).
3. A joint's command is its type's: a position joint is moved to a position (``move``), a
   velocity joint turned at a velocity (``set_velocity``). Its follow stream carries what its
   family's stream carries (the family's joint declaration says which, as the gateway reads
   it): positions (``{"joint": x}``: Inspire LA, DS servo) or velocities (``{"joint_velocity":
   v}``), or, where the family's stream carries both (ZLAC706: speeds in velocity mode,
   positions in position mode), what the joint's type says; chosen once when the stream is
   opened.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from busgate.client.base import Found, Shared
from busgate.client.devices import StreamBase
from busgate.client.faces import Face, waiting
from busgate.client.messages import JointInfo, JointState
from busgate.client.steps import Steps
from busgate.errors import CommandError
from busgate.schemas.api import JointFollow as JointTarget
from busgate.schemas.joints import JointType, declaration_of

if TYPE_CHECKING:
    from busgate.client.devices import DeviceBase


def follow_field(kind: str, joint_type: JointType | None = None) -> str | None:
    """The field of a joint follow target of a device of ``kind`` whose joint is of
    ``joint_type`` (``None``: its family's first): ``joint`` when it follows positions,
    ``joint_velocity`` when it follows speeds; ``None`` when it has no stream, or the kind is
    not one this SDK knows (rule 3)."""
    declaration = declaration_of(kind)
    if declaration is None:
        return None
    follows = declaration.follows_of(joint_type or declaration.types[0])
    return {"position": "joint", "velocity": "joint_velocity", None: None}[follows]


Device = TypeVar("Device", bound="DeviceBase[Any, Any, Any]")
JointFollow = TypeVar("JointFollow")


class JointBase(Face, Generic[Device, JointFollow]):
    """One device as a joint (``Device.joint``), of either face: ``name``, ``type``
    (``"position"`` or ``"velocity"``), ``unit`` (``"m"``, ``"rad"``, or ``"raw"`` for a
    device without a joint table) and ``info`` (its calibration and limits, a ``JointInfo``),
    as its gateway described them; each is ``None`` (``name``: the device's) when the gateway
    describes no joint (an earlier release). ``device`` is the device it is."""

    _JointFollow: Callable[[Shared, Found, str], JointFollow]

    def __init__(self, device: Device) -> None:
        self.device = device
        info = device._found.joint
        self.info: JointInfo | None = info
        self.name: str = device.name if info is None else info.name
        self.type: str | None = None if info is None else info.type
        self.unit: str | None = None if info is None else info.unit

    def __repr__(self) -> str:
        what = f"{self.type}, {self.unit}" if self.info is not None else "not described"
        return f"<{self._prefix}Joint {self.device.gateway}/{self.name} ({what})>"

    @waiting
    def state(self, timeout: float = 2.0, *, max_age: float = 1.0) -> Steps[JointState]:
        """The joint's latest values in SI (``name``, ``unit``, ``position``, ``velocity``,
        ``effort``; ``None`` where the device cannot know), from its device's latest state:
        one received in the last ``max_age`` seconds, else the next within ``timeout``."""
        telemetry = yield from self.device._latest_state(timeout, max_age)
        joint: JointState = telemetry.joint
        return joint

    @waiting
    def move(self, position: float) -> Steps[dict[str, Any]]:
        """Move a position joint to ``position``, in its unit (``{"op": "joint", "position":
        …}``); the reply's body (``state``, and the joint's values as ``joint``).
        ``OutOfRangeError`` beyond its limits."""
        command = {"op": "joint", "position": position}
        return (yield from self.device._sending(command, None))

    @waiting
    def set_velocity(self, velocity: float) -> Steps[dict[str, Any]]:
        """Turn a velocity joint at ``velocity``, in its unit per second (``{"op": "joint",
        "velocity": …}``); the reply's body. ``OutOfRangeError`` past its ``max_velocity``."""
        command = {"op": "joint", "velocity": velocity}
        return (yield from self.device._sending(command, None))

    def follow(self) -> JointFollow:
        """A follow stream of the joint while the ``with`` block runs: ``set(value)`` is its
        new target in SI, a position where its family's stream carries positions (Inspire
        LA, DS servo), a velocity where it carries speeds, and its type's where it carries
        either (ZLAC706, by its mode; rule 3); the gateway
        holds each within the joint's limits (an event ``limited`` tells the first it held).
        ``CommandError`` when the gateway described no joint, or the kind has no stream."""
        if self.info is None:
            raise CommandError(
                f"gateway {self.device.gateway} describes no joint of {self.device.name}: "
                "its release has no joints"
            )
        field = follow_field(self.device.kind, self.info.type)
        if field is None:
            raise CommandError(f"{self.device.kind} has no follow stream")
        return self._JointFollow(self.device._shared, self.device._found, field)


class JointFollowBase(StreamBase):
    """A joint's follow stream held by a block (``Joint.follow``), of either face."""

    _model = JointTarget

    def __init__(self, shared: Shared, found: Found, field: str) -> None:
        super().__init__(shared, found)
        #: The payload's field each target goes in: ``joint`` or ``joint_velocity``.
        self.field = field

    def set(self, value: float) -> None:
        """The joint's new target in SI, latest winning: a position, or a velocity where the
        stream carries speeds (``field``: ``joint`` or ``joint_velocity``); checked here
        (``BadCommandError``: not a number), put at most every 10 ms. Beyond a limit it is
        held at the limit, not refused."""
        self._put({self.field: value})
