"""What a ``sensor_msgs/JointState`` on the commands topic asks of each joint, and when a
velocity joint has waited too long for its next command.

Rules of this file:

1. A joint is named by its joint name; a position joint takes the message's ``position``, a
   velocity joint its ``velocity``; a list shorter than ``name``, or a NaN, is "no command"
   for that joint (ros2_control fills what it commands and leaves NaN elsewhere). An infinite
   value is no command either: no limit can make a target of it.
2. A name no joint has is reported once (``unknown`` of the first message that names it),
   then ignored.
3. A position joint's command is kept: it goes to its target and stays (silence is never a
   stop: ros2_control sends nothing while its command is unchanged). A velocity joint whose
   last command is older than ``timeout_s`` is due a stop (``expired``), once per silence.
4. Pure: times are given, nothing is sent from here.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Literal


@dataclass(frozen=True, slots=True)
class JointRef:
    """A joint as the face commands it: its device and what it follows."""

    name: str
    device: str
    type: Literal["position", "velocity"]


@dataclass(frozen=True, slots=True)
class Target:
    """One joint's command from one message, in SI."""

    joint: JointRef
    value: float

    @property
    def follow_fields(self) -> dict[str, float]:
        """The follow payload of this target (``busgate.schemas.api.JointFollow``)."""
        key = "joint" if self.joint.type == "position" else "joint_velocity"
        return {key: self.value}


@dataclass(slots=True)
class Commands:
    """The commands topic's messages, joint by joint (the rules above)."""

    joints: dict[str, JointRef]
    timeout_s: float
    unknown: set[str] = field(default_factory=set)
    _moving: dict[str, float] = field(default_factory=dict)  # velocity joint → last command

    def take(self, message: dict[str, Any], now: float) -> tuple[list[Target], list[str]]:
        """The targets ``message`` sets, and the names in it no joint has, reported for the
        first time (rule 2)."""
        names = message.get("name") or []
        positions, velocities = message.get("position") or [], message.get("velocity") or []
        targets: list[Target] = []
        new_unknown: list[str] = []
        for index, name in enumerate(names):
            joint = self.joints.get(name)
            if joint is None:
                if name not in self.unknown:
                    self.unknown.add(name)
                    new_unknown.append(name)
                continue
            values = positions if joint.type == "position" else velocities
            value = values[index] if index < len(values) else math.nan
            if not math.isfinite(value):
                continue
            targets.append(Target(joint, float(value)))
            if joint.type == "velocity":
                self._moving[joint.name] = now
        return targets, new_unknown

    def expired(self, now: float) -> list[JointRef]:
        """The velocity joints whose last command is older than ``timeout_s``: each is due a
        stop, and is not told again until a new command comes (rule 3)."""
        late = [name for name, when in self._moving.items() if now - when > self.timeout_s]
        for name in late:
            del self._moving[name]
        return [self.joints[name] for name in late]

    def forget(self, joints: Iterable[str]) -> None:
        """Joints stopped otherwise (an e-stop): no stop is due for them."""
        for name in joints:
            self._moving.pop(name, None)
