"""A ``trajectory_msgs/JointTrajectory`` as the gateway's own trajectory command: the joint
trajectory controller's topic, played by the gateway next to the wire.

Rules of this file:

1. The joints are named by their joint names and moved in their SI units (``"units":
   "joint"``); each point's time is its ``time_from_start``; ``header.stamp`` is when the
   trajectory starts, or now when it is zero or past (the controller's convention), and
   when it is less than ``START_LEAD_S`` ahead: the gateway wants a start it can keep.
2. The interpolation is chosen by the fields present: positions alone are joined by straight
   lines, with velocities on every point by cubics, with accelerations too by quintics. A
   field given on some points only is not used (it cannot shape every segment).
3. Every ROS trajectory plays under one id (``ROS_TRAJECTORY_ID``), so a new one replaces the
   running one; an empty trajectory (no joints or no points) cancels it.
4. A joint the gateway does not have, or a velocity joint (a trajectory moves positions), is
   refused with one line naming it; nothing is played.
5. Pure: a message in, the command's payload out.
"""

from __future__ import annotations

from typing import Any

from busgate.codecs.ros2.messages import seconds_of
from busgate.errors import RefusedError
from busgate.gateway.ros2.commands import JointRef
from busgate.schemas.validation import shown

#: The id of the trajectory ROS plays (rule 3).
ROS_TRAJECTORY_ID = "ros2"
#: A stamp nearer than this starts the trajectory now (rule 1): the play is checked whole
#: first, and a start it cannot keep is refused (``gateway.trajectory.checks.MIN_LEAD_S``).
START_LEAD_S = 0.2


def trajectory_command(
    message: dict[str, Any], joints: dict[str, JointRef], client: str, now: float
) -> dict[str, Any]:
    """The trajectory key's command for ``message`` (a play, or a cancel when it is empty),
    at Unix time ``now``; ``RefusedError`` for a joint it cannot move (rule 4)."""
    names, points = message.get("joint_names") or [], message.get("points") or []
    if not names or not points:
        return {"op": "cancel", "id": ROS_TRAJECTORY_ID, "client": client}
    devices = []
    for name in names:
        joint = joints.get(name)
        if joint is None:
            raise RefusedError("unknown_device", f"no joint '{shown(name)}' on this gateway")
        if joint.type != "position":
            raise RefusedError(
                "bad_command",
                f"joint {name!r} is a velocity joint: a trajectory moves positions; command "
                "its velocity on the joint commands topic",
            )
        devices.append(joint.device)
    fields = [f for f in ("velocities", "accelerations") if all(p.get(f) for p in points)]
    if "velocities" not in fields:
        fields = []  # accelerations alone shape no interpolant (rule 2)
    command: dict[str, Any] = {
        "op": "play",
        "id": ROS_TRAJECTORY_ID,
        "client": client,
        "devices": devices,
        "units": "joint",
        "points": [_point(point, fields) for point in points],
    }
    if "accelerations" in fields:
        command["interpolation"] = "quintic"
    stamp = (message.get("header") or {}).get("stamp") or {}
    start = seconds_of(stamp)
    if start > now + START_LEAD_S:
        command["start_at"] = start
    return command


def _point(point: dict[str, Any], fields: list[str]) -> dict[str, Any]:
    duration = point.get("time_from_start") or {}
    t_s = seconds_of(duration)
    return {"t_s": t_s, "positions": list(point.get("positions") or [])} | {
        name: list(point[name]) for name in fields
    }
