"""What a ``sensor_msgs/JointState`` on the commands topic asks of each joint, and when a
velocity joint has waited too long for its next command.

Rules of this file:

1. A joint is named by its joint name; a position joint takes the message's ``position``, a
   velocity joint its ``velocity``. A list as long as ``name`` gives each named joint its
   value, by index (sensor_msgs' rule: every list as long as the names, or empty). A list as
   long as the named joints of its interface gives them their values in order: ros2_control's
   topic-based system writes a joint's command only into the list of its command interface.
   A list of any other length cannot say which value is whose: it moves nothing and is told
   (``Taken.problems``). A NaN or infinite value is no command for that joint; a joint named
   twice takes its last value, one target a joint.
2. A name no joint has is reported once (``unknown`` of the first message that names it),
   then ignored; at most ``UNKNOWN_KEPT`` of them are kept (a peer may send any number, of
   any length), each as a refusal repeats it (``shown``).
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

from busgate.schemas.validation import shown

#: The unknown joint names kept for the log and /diagnostics (rule 2).
UNKNOWN_KEPT = 16


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
class Taken:
    """What one message asks: its targets, the names no joint has (told the first time),
    and what in it cannot be taken (rule 1)."""

    targets: list[Target] = field(default_factory=list)
    unknown: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)


@dataclass(slots=True)
class Commands:
    """The commands topic's messages, joint by joint (the rules above)."""

    joints: dict[str, JointRef]
    timeout_s: float
    unknown: set[str] = field(default_factory=set)
    _moving: dict[str, float] = field(default_factory=dict)  # velocity joint → last command

    def take(self, message: dict[str, Any], now: float) -> Taken:
        """The targets ``message`` sets (the rules above)."""
        names = message.get("name") or []
        taken = Taken()
        known: list[JointRef] = []
        for name in names:
            joint = self.joints.get(name)
            if joint is not None:
                known.append(joint)
            elif len(self.unknown) < UNKNOWN_KEPT and (named := shown(name)) not in self.unknown:
                self.unknown.add(named)
                taken.unknown.append(named)
        for interface in ("position", "velocity"):  # a joint type is its list's name
            values = message.get(interface) or []
            if not values:
                continue
            if len(values) == len(names):
                pairs = [
                    (self.joints[name], value)
                    for name, value in zip(names, values, strict=True)
                    if name in self.joints and self.joints[name].type == interface
                ]
            else:
                mine = [joint for joint in known if joint.type == interface]
                if len(values) != len(mine):
                    taken.problems.append(
                        f"{interface} has {len(values)} values for {len(names)} names, "
                        f"{len(mine)} of them {interface} joints: whose is each? (give every "
                        "name a value, NaN for none)"
                    )
                    continue
                pairs = list(zip(mine, values, strict=True))
            for joint, value in pairs:
                if math.isfinite(value):
                    taken.targets.append(Target(joint, float(value)))
                    if interface == "velocity":
                        self._moving[joint.name] = now
        # A name given twice: its last value (one target a joint, however long the message).
        taken.targets = list({target.joint.name: target for target in taken.targets}.values())
        return taken

    def expired(self, now: float) -> list[JointRef]:
        """The velocity joints whose last command is older than ``timeout_s``: each is due a
        stop, and is not told again until a new command comes (rule 3)."""
        late = [name for name, when in self._moving.items() if now - when > self.timeout_s]
        for name in late:
            del self._moving[name]
        return [self.joints[name] for name in late]

    def forget(self, joints: Iterable[str]) -> None:
        """Joints stopped otherwise (an e-stop), or whose command was refused: no stop is due
        for them."""
        for name in joints:
            self._moving.pop(name, None)
