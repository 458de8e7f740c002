"""The ``[ros2]`` table of the config: busgate's face in ROS 2, on rmw_zenoh's wire format.

Rules of this file:

1. The table's presence turns the face on; every key has the default a ROS user expects
   (``robot_joint_states`` and ``robot_joint_commands`` are what ros2_control's topic-based
   system uses), so ``[ros2]`` alone is a working face.
2. Every name is checked by ROS's rules (``busgate.codecs.ros2.rmw_zenoh``) before the gateway
   starts: a name ROS would refuse is refused here, naming the key, never a topic nobody can
   reach.
3. ``node`` defaults to ``busgate_<gateway>`` (``-`` becoming ``_``: ROS node names are
   identifiers); ``client`` is the client id the face's commands act under, in claims and
   events, as any client's.
4. A base (``[[bases]]``) takes ``cmd_vel`` and publishes ``odom`` and the ``tf`` transform
   ``odom_frame`` → ``base_frame``. With several bases, each one's relative names are under
   its name (``<base>/cmd_vel``) and its frames prefixed (``<base>/odom``): ``topic_of``.
5. No two keys of the table come to one name once resolved (``require_distinct_names``, with
   the gateway's name and its bases): two services on one name would both run on each call
   (an e-stop call resetting the e-stop too), and a subscription on a publisher's topic would
   take the gateway's own joint states for commands. The bases' topics of one key may share
   an absolute name (every base's transforms on ``/tf``).
6. ``pose_covariance_diagonal`` and ``twist_covariance_diagonal`` are diff_drive_controller's
   keys, with its defaults (zeros, which a filter such as robot_localization's reads as
   certainty): the diagonal of each base's odometry's pose and twist covariance, to be
   tuned to the robot's odometry as the controller's are.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from busgate.codecs.ros2.rmw_zenoh import (
    DISTROS,
    name_problem,
    namespace_problem,
    node_name_problem,
    resolve,
)
from busgate.schemas.base import ClientId

#: A tf frame id: what tf2 takes (no leading slash).
FRAME_ID = r"^[A-Za-z_][A-Za-z0-9_/]{0,127}$"
#: The topics and services of the face, by key (rule 1's defaults). ``cmd_vel``, ``odom`` and
#: ``tf`` are each base's (rule 4).
TOPIC_DEFAULTS: dict[str, str] = {
    "joint_states": "robot_joint_states",
    "joint_commands": "robot_joint_commands",
    "joint_trajectory": "joint_trajectory",
    "diagnostics": "/diagnostics",
    "estopped": "~/estopped",
    "estop": "~/estop",
    "reset_estop": "~/reset_estop",
    "cmd_vel": "cmd_vel",
    "odom": "odom",
    "tf": "/tf",
}
#: The keys of ``TOPIC_DEFAULTS`` that are each base's.
BASE_TOPICS = ("cmd_vel", "odom", "tf")
#: A variance of an odometry covariance's diagonal (rule 6).
Variance = Annotated[float, Field(ge=0, allow_inf_nan=False)]
#: The six of a diagonal: x, y, z, then rotation about x, y, z (rule 6).
CovarianceDiagonal = Annotated[list[Variance], Field(min_length=6, max_length=6)]


class Ros2Section(BaseModel):
    """``[ros2]``: the ROS 2 face (the rules above)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)

    domain_id: Annotated[int, Field(ge=0, le=232)] = 0
    namespace: str = ""
    node: str | None = None
    client: ClientId = "ros2"
    distro: Literal[DISTROS] = "jazzy"  # type: ignore[valid-type]
    command_timeout_s: Annotated[float, Field(gt=0, le=60)] = 0.5
    joint_states: str = TOPIC_DEFAULTS["joint_states"]
    joint_commands: str = TOPIC_DEFAULTS["joint_commands"]
    joint_trajectory: str = TOPIC_DEFAULTS["joint_trajectory"]
    diagnostics: str = TOPIC_DEFAULTS["diagnostics"]
    estopped: str = TOPIC_DEFAULTS["estopped"]
    estop: str = TOPIC_DEFAULTS["estop"]
    reset_estop: str = TOPIC_DEFAULTS["reset_estop"]
    cmd_vel: str = TOPIC_DEFAULTS["cmd_vel"]
    odom: str = TOPIC_DEFAULTS["odom"]
    tf: str = TOPIC_DEFAULTS["tf"]
    odom_frame: Annotated[str, Field(pattern=FRAME_ID)] = "odom"
    base_frame: Annotated[str, Field(pattern=FRAME_ID)] = "base_link"
    pose_covariance_diagonal: CovarianceDiagonal = [0.0] * 6
    twist_covariance_diagonal: CovarianceDiagonal = [0.0] * 6

    @model_validator(mode="after")
    def _names(self) -> Ros2Section:
        problem = namespace_problem(self.namespace)
        if problem is not None:
            raise ValueError(f"namespace: {problem}")
        if self.node is not None:
            problem = node_name_problem(self.node)
            if problem is not None:
                raise ValueError(f"node: {problem}")
        for key in TOPIC_DEFAULTS:
            problem = name_problem(getattr(self, key))
            if problem is not None:
                raise ValueError(f"{key}: {problem}")
        return self

    def topic_of(self, key: str, base: str, bases: int) -> str:
        """The name of base ``base``'s topic ``key`` (``cmd_vel``, ``odom``, ``tf``), one of
        ``bases`` bases (rule 4); absolute names and ``~/`` names are each base's only with a
        single base."""
        name = getattr(self, key)
        return name if bases == 1 or name.startswith(("/", "~")) else f"{base}/{name}"

    def require_distinct_names(self, gateway: str, bases: list[str]) -> None:
        """Rule 5: ``ValueError`` naming both keys when two come to one name."""
        node = self.node_of(gateway)
        owner: dict[str, str] = {}
        for key in TOPIC_DEFAULTS:
            names = (
                {self.topic_of(key, base, len(bases)) for base in bases}
                if key in BASE_TOPICS
                else {getattr(self, key)}
            )
            for name in names:
                full = resolve(name, self.namespace, node)
                if owner.setdefault(full, key) != key:
                    raise ValueError(
                        f"ros2.{key}: {name!r} is {full}, as ros2.{owner[full]} is: each "
                        "topic and service needs a name of its own"
                    )

    def frame_of(self, key: str, base: str, bases: int) -> str:
        """Base ``base``'s tf frame ``key`` (``odom_frame``, ``base_frame``) (rule 4)."""
        frame = getattr(self, key)
        return frame if bases == 1 else f"{base}/{frame}"

    def node_of(self, gateway: str) -> str:
        """The node's name (rule 3)."""
        return self.node if self.node is not None else f"busgate_{gateway.replace('-', '_')}"
