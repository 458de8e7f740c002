"""The ROS 2 types busgate speaks, as their ``.msg`` / ``.srv`` text, and that text parsed.

The wire format (``messages``) and the type hash (``type_hash``) are both computed from these
definitions, so there is one source for each type. The texts are ROS 2 Jazzy's, comments
stripped; for these types Iron, Jazzy, Kilted and Lyrical do not differ (tests/
test_ros2_codec.py proves it against rosbags' stores and rosidl's hashes).

Rules of this file:

1. A type is named in full: ``sensor_msgs/msg/JointState``. Inside a definition a field may
   name another package's type (``std_msgs/Header``) or its own package's (``KeyValue``).
2. ``.msg`` semantics: ``char`` is uint8 and ``byte`` an octet of its own kind; a default value
   (``float64 w 1``) is parsed and dropped (it is in neither the wire nor the hash); constants
   (``byte OK=0``) are kept as data and are in neither either.
3. A service ``pkg/srv/Name`` makes four types, as rosidl does: ``Name_Request`` and
   ``Name_Response`` from the two halves of its text, ``Name_Event`` (the introspection
   message) and ``Name`` itself, a struct of the three; only the hash uses the last two.
4. A struct without fields gets the one field ``structure_needs_at_least_one_member`` (uint8),
   as rosidl gives it: an empty request is a zero byte on the wire.
5. A name that is not here, or a definition this file cannot parse, is a programming error:
   ``ValueError``. Nothing here reads the network.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from enum import Enum
from typing import Final

from busgate.codecs.ros2.cdr import PRIMITIVE_SIZES

__all__ = [
    "MESSAGES",
    "PRIMITIVES",
    "SERVICES",
    "TYPE_NAMES",
    "Collection",
    "Constant",
    "Field",
    "FieldType",
    "Struct",
    "struct",
]

#: Each message type's definition.
MESSAGES: Final[dict[str, str]] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "builtin_interfaces/msg/Duration": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "std_msgs/msg/Bool": "bool data\n",
    "sensor_msgs/msg/JointState": (
        "std_msgs/Header header\n"
        "string[] name\n"
        "float64[] position\n"
        "float64[] velocity\n"
        "float64[] effort\n"
    ),
    "trajectory_msgs/msg/JointTrajectory": (
        "std_msgs/Header header\nstring[] joint_names\nJointTrajectoryPoint[] points\n"
    ),
    "trajectory_msgs/msg/JointTrajectoryPoint": (
        "float64[] positions\n"
        "float64[] velocities\n"
        "float64[] accelerations\n"
        "float64[] effort\n"
        "builtin_interfaces/Duration time_from_start\n"
    ),
    "diagnostic_msgs/msg/DiagnosticArray": "std_msgs/Header header\nDiagnosticStatus[] status\n",
    "diagnostic_msgs/msg/DiagnosticStatus": (
        "byte OK=0\n"
        "byte WARN=1\n"
        "byte ERROR=2\n"
        "byte STALE=3\n"
        "byte level\n"
        "string name\n"
        "string message\n"
        "string hardware_id\n"
        "KeyValue[] values\n"
    ),
    "diagnostic_msgs/msg/KeyValue": "string key\nstring value\n",
    "geometry_msgs/msg/Twist": "Vector3  linear\nVector3  angular\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation\n",
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance\n",
    "geometry_msgs/msg/TwistWithCovariance": "Twist twist\nfloat64[36] covariance\n",
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation\n",
    "geometry_msgs/msg/TransformStamped": (
        "std_msgs/Header header\nstring child_frame_id\nTransform transform\n"
    ),
    "nav_msgs/msg/Odometry": (
        "std_msgs/Header header\n"
        "string child_frame_id\n"
        "geometry_msgs/PoseWithCovariance pose\n"
        "geometry_msgs/TwistWithCovariance twist\n"
    ),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms\n",
    "service_msgs/msg/ServiceEventInfo": (
        "uint8 REQUEST_SENT = 0\n"
        "uint8 REQUEST_RECEIVED = 1\n"
        "uint8 RESPONSE_SENT = 2\n"
        "uint8 RESPONSE_RECEIVED = 3\n"
        "uint8 event_type\n"
        "builtin_interfaces/Time stamp\n"
        "char[16] client_gid\n"
        "int64 sequence_number\n"
    ),
}

#: Each service type's definition: the request, ``---``, the response.
SERVICES: Final[dict[str, str]] = {
    "std_srvs/srv/Trigger": "---\nbool success\nstring message\n",
}

#: The primitives a definition may use (``char`` is read as ``uint8``, rule 2).
PRIMITIVES: Final = frozenset({*PRIMITIVE_SIZES, "string"})

_SERVICE_PARTS: Final = ("_Request", "_Response", "_Event", "")
#: Every type name ``struct()`` knows.
TYPE_NAMES: Final = (
    *MESSAGES,
    *(service + part for service in SERVICES for part in _SERVICE_PARTS),
)

_EMPTY_MEMBER: Final = "structure_needs_at_least_one_member"
_SERVICE_EVENT_INFO: Final = "service_msgs/msg/ServiceEventInfo"
_FIELD_NAME: Final = re.compile(r"[a-z][a-z0-9_]*")
#: A field's type: the element, an optional string bound, an optional array suffix.
_TYPE: Final = re.compile(
    r"(?P<element>[A-Za-z][A-Za-z0-9_]*(?:/[A-Za-z][A-Za-z0-9_]*)?)"
    r"(?:<=(?P<string_capacity>[0-9]+))?"
    r"(?P<array>\[(?:<=(?P<bound>[0-9]+)|(?P<size>[0-9]*))\])?"
)


class Collection(Enum):
    """How many values a field holds: one, a fixed array, or a sequence with or without bound."""

    SINGLE = "single"
    FIXED = "fixed"
    BOUNDED = "bounded"
    UNBOUNDED = "unbounded"


@dataclass(frozen=True, slots=True)
class FieldType:
    """A field's type: ``element`` is a primitive (``float64``, ``string``) or a type's full
    name; ``capacity`` the fixed size or bound of an array (else 0); ``string_capacity`` the
    bound of a ``string<=N`` (else 0)."""

    element: str
    collection: Collection = Collection.SINGLE
    capacity: int = 0
    string_capacity: int = 0

    @property
    def nested(self) -> bool:
        """True when the element is a message type, not a primitive."""
        return self.element not in PRIMITIVES


@dataclass(frozen=True, slots=True)
class Field:
    """One field of a struct."""

    name: str
    type: FieldType


@dataclass(frozen=True, slots=True)
class Constant:
    """A constant of a message (``byte OK=0``): its primitive, its name and its value's text."""

    type: str
    name: str
    value: str


@dataclass(frozen=True, slots=True)
class Struct:
    """A type, parsed: its full name, its fields in wire order and its constants."""

    name: str
    fields: tuple[Field, ...]
    constants: tuple[Constant, ...] = ()

    @property
    def nested_names(self) -> tuple[str, ...]:
        """The full names of the types its fields use directly, in field order."""
        return tuple(f.type.element for f in self.fields if f.type.nested)


@functools.cache
def struct(name: str) -> Struct:
    """The parsed definition of ``name`` (rule 1); ``ValueError`` for a type not here."""
    if name in MESSAGES:
        return _parse(name, MESSAGES[name])
    for service in SERVICES:
        if name.startswith(service) and name[len(service) :] in _SERVICE_PARTS:
            return _service_part(service, name[len(service) :])
    raise ValueError(f"unknown ROS 2 type {name!r}; known: {', '.join(TYPE_NAMES)}")


def _service_part(service: str, part: str) -> Struct:
    request_text, separator, response_text = SERVICES[service].partition("---\n")
    if not separator:
        raise ValueError(f"the definition of {service} has no '---' line")
    if part == "_Request":
        return _parse(service + part, request_text)
    if part == "_Response":
        return _parse(service + part, response_text)
    if part == "_Event":
        return Struct(
            service + part,
            (
                Field("info", FieldType(_SERVICE_EVENT_INFO)),
                Field("request", FieldType(service + "_Request", Collection.BOUNDED, 1)),
                Field("response", FieldType(service + "_Response", Collection.BOUNDED, 1)),
            ),
        )
    return Struct(
        service,
        tuple(
            Field(field, FieldType(service + suffix))
            for field, suffix in (
                ("request_message", "_Request"),
                ("response_message", "_Response"),
                ("event_message", "_Event"),
            )
        ),
    )


def _parse(name: str, text: str) -> Struct:
    package = name.split("/")[0]
    fields: list[Field] = []
    constants: list[Constant] = []
    for line in text.splitlines():
        line = line.partition("#")[0].strip()
        if not line:
            continue
        type_text, _, rest = line.partition(" ")
        if "=" in rest:
            constant, _, value = rest.partition("=")
            kind = _type(name, package, type_text)
            if kind.nested or kind.collection is not Collection.SINGLE:
                raise ValueError(f"{name}: a constant is of a primitive type, not {line!r}")
            value = value.strip()
            quoted = len(value) > 1 and value[0] in "'\"" and value[-1] == value[0]
            if kind.element == "string" and quoted:
                value = value[1:-1]  # rosidl's quotes are not the value's
            constants.append(Constant(kind.element, constant.strip(), value))
        else:
            field = rest.split(maxsplit=1)[0] if rest.strip() else ""
            if not _FIELD_NAME.fullmatch(field):
                raise ValueError(f"{name}: bad field name in {line!r}")
            fields.append(Field(field, _type(name, package, type_text)))
    if not fields:
        fields.append(Field(_EMPTY_MEMBER, FieldType("uint8")))
    return Struct(name, tuple(fields), tuple(constants))


def _type(name: str, package: str, text: str) -> FieldType:
    match = _TYPE.fullmatch(text)
    if match is None:
        raise ValueError(f"{name}: cannot parse the type {text!r}")
    element = _element(name, package, match["element"])
    string_capacity = int(match["string_capacity"] or 0)
    if string_capacity and element != "string":
        raise ValueError(f"{name}: only a string takes a bound, not {text!r}")
    if match["array"] is None:
        return FieldType(element, string_capacity=string_capacity)
    if match["bound"]:
        return FieldType(element, Collection.BOUNDED, int(match["bound"]), string_capacity)
    if match["size"]:
        return FieldType(element, Collection.FIXED, int(match["size"]), string_capacity)
    return FieldType(element, Collection.UNBOUNDED, string_capacity=string_capacity)


def _element(name: str, package: str, text: str) -> str:
    if text == "char":
        return "uint8"
    if text in PRIMITIVES:
        return text
    if "/" in text:
        other_package, _, type_name = text.partition("/")
        return f"{other_package}/msg/{type_name}"
    if not text[0].isupper():
        raise ValueError(f"{name}: unknown primitive {text!r}")
    return f"{package}/msg/{text}"
