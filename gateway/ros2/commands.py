"""What a ``sensor_msgs/JointState`` on the commands topic asks of each joint, and when a
velocity joint has waited too long for its next command.

Rules of this file:

1. A joint is named by its joint name; a position joint takes the message's ``position``, a
   velocity joint its ``velocity`` (``effort`` is never read). The lists are read one of two
   ways. sensor_msgs': every list as long as ``name`` or empty, each named joint's value at
   its index, and no number (NaN) for it in the other type's list: that would be a command
   through an interface it does not have. ros2_control's topic-based system's: each joint's
   command only in its interface's list, in the order of the names, which says whose each
   value is only when every name is a joint of this gateway and each list is as long as the
   named joints of its type (a name of no joint here, or a joint with no command interface
   or another one, would shift values onto joints they were not meant for). A message read
   neither way is refused whole (``Taken.refused``): nothing in it moves. A NaN or infinite
   value is no command for that joint; a joint named twice takes its last value, one target
   a joint.
2. A name no joint has is reported once (``unknown`` of the first message that names it),
   then ignored; at most ``UNKNOWN_KEPT`` of them are kept (a peer may send any number, of
   any length), each as a refusal repeats it (``shown``).
3. A position joint's command is kept: it goes to its target and stays (silence is never a
   stop: ros2_control sends nothing while its command is unchanged). A velocity joint whose
   last command is older than ``timeout_s`` is due a stop (``expired``), once per silence,
   but one that never moved: its command refused and none carried out since its last stop
   (``refused``; one carried out, ``carried_out``, keeps it turning until the stop), and
   none taken since the refused one (its own: another thread takes the next meanwhile).
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
#: The lists a joint's command is in: a joint's type is its list's name.
INTERFACES = ("position", "velocity")


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
    #: When its message was taken (``take``'s ``now``): which command a refusal is of (rule 3).
    taken_at: float = 0.0

    @property
    def follow_fields(self) -> dict[str, float]:
        """The follow payload of this target (``busgate.schemas.api.JointFollow``)."""
        key = "joint" if self.joint.type == "position" else "joint_velocity"
        return {key: self.value}


@dataclass(slots=True)
class Taken:
    """What one message asks: its targets, the names no joint has (told the first time),
    and why it is refused when it is (rule 1: then it has no targets)."""

    targets: list[Target] = field(default_factory=list)
    unknown: list[str] = field(default_factory=list)
    refused: str | None = None


@dataclass(slots=True)
class Commands:
    """The commands topic's messages, joint by joint (the rules above)."""

    joints: dict[str, JointRef]
    timeout_s: float
    unknown: set[str] = field(default_factory=set)
    _moving: dict[str, float] = field(default_factory=dict)  # velocity joint → last command
    _driven: set[str] = field(default_factory=set)  # of those, moved since their last stop

    def take(self, message: dict[str, Any], now: float) -> Taken:
        """The targets ``message`` sets (the rules above)."""
        names = message.get("name") or []
        lists: dict[str, list[float]] = {i: message.get(i) or [] for i in INTERFACES}
        taken = Taken(unknown=self.newly_unknown(names))
        by_index = all(len(values) in (0, len(names)) for values in lists.values())
        taken.refused = (self._misdirected if by_index else self._uncertain)(names, lists)
        if taken.refused is not None:
            return taken
        pairs = (self._by_index if by_index else self._in_order)(names, lists)
        for joint, value in pairs:
            if math.isfinite(value):
                taken.targets.append(Target(joint, float(value), now))
                if joint.type == "velocity":
                    self._moving[joint.name] = now
        # A name given twice: its last value (one target a joint, however long the message).
        taken.targets = list({target.joint.name: target for target in taken.targets}.values())
        return taken

    def newly_unknown(self, names: list[str]) -> list[str]:
        """The names no joint has that no message (a command, a trajectory) named before
        (rule 2)."""
        told = []
        for name in names:
            if name in self.joints or len(self.unknown) >= UNKNOWN_KEPT:
                continue
            if (named := shown(name)) not in self.unknown:
                self.unknown.add(named)
                told.append(named)
        return told

    def _by_index(
        self, names: list[str], lists: dict[str, list[float]]
    ) -> list[tuple[JointRef, float]]:
        """sensor_msgs' reading: each named joint's value at its index in its type's list."""
        return [
            (self.joints[name], value)
            for interface, values in lists.items()
            if values  # else as long as the names
            for name, value in zip(names, values, strict=True)
            if name in self.joints and self.joints[name].type == interface
        ]

    def _misdirected(self, names: list[str], lists: dict[str, list[float]]) -> str | None:
        """sensor_msgs' reading: a number for a joint in the other type's list, a command
        through an interface the joint does not have, as a refusal (rule 1)."""
        wrong = next(
            (
                (self.joints[name], interface)
                for interface, values in lists.items()
                if values  # else as long as the names
                for name, value in zip(names, values, strict=True)
                if name in self.joints
                and self.joints[name].type != interface
                and math.isfinite(value)
            ),
            None,
        )
        if wrong is None:
            return None
        joint, interface = wrong
        return (
            f"{interface} given for {joint.type} joint {joint.name}: a joint takes only its "
            f"type's list (NaN in the other for none)"
        )

    def _uncertain(self, names: list[str], lists: dict[str, list[float]]) -> str | None:
        """Why ros2_control's reading cannot say whose each value is, if it cannot (rule 1)."""
        if not names:
            return f"whose is each value? {_lengths(lists)} for no names (name their joints)"
        strangers = sum(name not in self.joints for name in names)
        if strangers:
            return (
                f"whose is each value? {_lengths(lists)} for {len(names)} names, {strangers} "
                "of them no joint of this gateway (give every name a value, NaN for none)"
            )
        counts = {i: sum(self.joints[name].type == i for name in names) for i in INTERFACES}
        if all(len(lists[i]) == counts[i] for i in INTERFACES):
            return None
        return (
            f"whose is each value? {_lengths(lists)} for {counts['position']} position and "
            f"{counts['velocity']} velocity joints (each joint's command interface must be its "
            "type, or give every name a value, NaN for none)"
        )

    def _in_order(
        self, names: list[str], lists: dict[str, list[float]]
    ) -> list[tuple[JointRef, float]]:
        """ros2_control's reading, once certain: each list's values to the named joints of its
        type, in order."""
        return [
            (joint, value)
            for interface, values in lists.items()
            for joint, value in zip(
                (j for j in map(self.joints.__getitem__, names) if j.type == interface),
                values,
                strict=True,
            )
        ]

    def expired(self, now: float) -> list[JointRef]:
        """The velocity joints whose last command is older than ``timeout_s``: each is due a
        stop, and is not told again until a new command comes (rule 3)."""
        late = [name for name, when in self._moving.items() if now - when > self.timeout_s]
        for name in late:
            del self._moving[name]
            self._driven.discard(name)
        return [self.joints[name] for name in late]

    def carried_out(self, joint: str) -> None:
        """``joint``'s command went to its device: a velocity joint turns until its stop."""
        if joint in self._moving:
            self._driven.add(joint)

    def refused(self, joint: str, taken_at: float | None) -> None:
        """``joint``'s command taken at ``taken_at`` (``None``: the stop's own, no command's)
        was refused: no stop is due for it unless a command carried out since its last stop
        still turns it (rule 3: a refused command after one that was taken forgot the joint,
        which then turned with no end), or one was taken after it (it would forget that
        one's)."""
        if joint in self._driven or taken_at is None:
            return
        if self._moving.get(joint) == taken_at:
            del self._moving[joint]

    def forget(self, joints: Iterable[str]) -> None:
        """Joints stopped otherwise (an e-stop): no stop is due for them."""
        for name in joints:
            self._moving.pop(name, None)
            self._driven.discard(name)


def _lengths(lists: dict[str, list[float]]) -> str:
    """How many values each list has, in words (``position has 1, velocity 0 values``)."""
    position, velocity = (len(lists[i]) for i in INTERFACES)
    return f"position has {position}, velocity {velocity} values"
