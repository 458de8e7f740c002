"""Each base in ROS 2: ``cmd_vel`` (``geometry_msgs/Twist``) in, ``odom``
(``nav_msgs/Odometry``) and the ``tf`` transform odom → base_link out, what Nav2 and
ros2_control's diff_drive_controller users expect of a base.

Rules of this file:

1. A ``cmd_vel`` is a twist of the base's stream under the face's client (``Bases.stream``):
   ``linear.x`` and ``angular.z``, held ``cmd_timeout_s`` (the diff_drive_controller's
   ``cmd_vel_timeout``), then ramped to 0. The other components are not a differential
   drive's; a non-finite value makes no command. A refusal moves nothing and is logged once,
   until a twist is taken again.
2. Odometry goes out as the base's is published (``Bases`` rule 5), stamped with the time the
   wheels were read: the pose in ``odom_frame``, the twist in ``base_frame``, with the same
   pose as one transform on ``tf``; their covariances are the config's diagonals
   (``Ros2Section`` rule 6).
3. Names and frames of several bases are each base's (``Ros2Section.topic_of``).
"""

from __future__ import annotations

import functools
import logging
import math
from typing import Any

from busgate.codecs.ros2 import rmw_zenoh
from busgate.codecs.ros2.messages import time_of
from busgate.gateway.base.bases import Bases
from busgate.gateway.base.kinematics import Twist
from busgate.gateway.ros2.node import Ros2Node, Ros2Publisher
from busgate.schemas.payload import MAX_PAYLOAD
from busgate.schemas.ros2 import Ros2Section

log = logging.getLogger(__name__)

TWIST = "geometry_msgs/msg/Twist"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"


class BaseTopics:
    """The ROS topics of every base of the gateway (the rules above)."""

    def __init__(self, node: Ros2Node, section: Ros2Section, bases: Bases) -> None:
        self.section = section
        self.bases = bases
        self._refused: dict[str, str] = {}  # base → its last refusal told (rule 1)
        self._pose_covariance = covariance(section.pose_covariance_diagonal)  # rule 2
        self._twist_covariance = covariance(section.twist_covariance_diagonal)
        self._out: dict[str, tuple[Ros2Publisher, Ros2Publisher, str, str]] = {}
        count = len(bases.bases)
        for name in bases.bases:
            node.subscription(
                section.topic_of("cmd_vel", name, count),
                TWIST,
                rmw_zenoh.DEFAULT,
                functools.partial(self._cmd_vel, name),
                MAX_PAYLOAD,
            )
            self._out[name] = (
                node.publisher(section.topic_of("odom", name, count), ODOMETRY, rmw_zenoh.DEFAULT),
                node.publisher(section.topic_of("tf", name, count), TF_MESSAGE, rmw_zenoh.DEFAULT),
                section.frame_of("odom_frame", name, count),
                section.frame_of("base_frame", name, count),
            )

    def _cmd_vel(self, name: str, message: dict[str, Any]) -> None:
        linear, angular = message["linear"]["x"], message["angular"]["z"]
        if not (math.isfinite(linear) and math.isfinite(angular)):
            return
        refused = self.bases.stream(name, Twist(linear, angular), self.section.client)
        if refused is None:
            self._refused.pop(name, None)
            return
        why = refused["error"]["message"]
        if self._refused.get(name) != why:
            self._refused[name] = why
            log.warning("ros2: cmd_vel for base %s refused: %s", name, why)

    def odometry(self, name: str, odometry: dict[str, Any]) -> None:
        """A base's odometry as published (rule 2)."""
        out = self._out.get(name)
        if out is None:
            return
        odom, tf, odom_frame, base_frame = out
        header = {"stamp": time_of(odometry["ts"]), "frame_id": odom_frame}
        position = {"x": odometry["x"], "y": odometry["y"], "z": 0.0}
        theta = odometry["theta"]
        rotation = {"x": 0.0, "y": 0.0, "z": math.sin(theta / 2), "w": math.cos(theta / 2)}
        odom.publish(
            {
                "header": header,
                "child_frame_id": base_frame,
                "pose": {
                    "pose": {"position": position, "orientation": rotation},
                    "covariance": self._pose_covariance,
                },
                "twist": {
                    "twist": {
                        "linear": {"x": odometry["linear"], "y": 0.0, "z": 0.0},
                        "angular": {"x": 0.0, "y": 0.0, "z": odometry["angular"]},
                    },
                    "covariance": self._twist_covariance,
                },
            }
        )
        tf.publish(
            {
                "transforms": [
                    {
                        "header": header,
                        "child_frame_id": base_frame,
                        "transform": {"translation": position, "rotation": rotation},
                    }
                ]
            }
        )


def covariance(diagonal: list[float]) -> list[float]:
    """The 6×6 covariance, row by row, of ``diagonal``'s six variances and nothing else.

    >>> covariance([1, 2, 3, 4, 5, 6])[:8], covariance([1, 2, 3, 4, 5, 6])[35]
    ([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0], 6.0)
    """
    size = len(diagonal)
    return [
        float(diagonal[row]) if row == column else 0.0
        for row in range(size)
        for column in range(size)
    ]
