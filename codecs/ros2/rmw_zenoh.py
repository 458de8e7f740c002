"""What rmw_zenoh puts around a ROS 2 payload: keys, liveliness tokens, QoS text, attachment.

A ROS 2 node on rmw_zenoh finds a topic by its data key and lists it by liveliness tokens;
its subscriber drops a sample without the attachment. This file spells all of that as
strings and bytes (the facts from rmw_zenoh's docs/design.md and its sources:
liveliness_utils.cpp, qos.cpp, attachment_helpers.cpp; docs/ros2.md says which), and holds
ROS's name rules, so a gateway can speak to ROS without ROS.

Rules of this file:

1. Pure: strings and bytes in and out, no zenoh, no clock; ``new_gid`` alone draws random
   bytes.
2. A data key is ``<domain>/<fully qualified name without its leading />/<DDS type name>/
   <hash>``; Humble's rmw_zenoh writes ``TypeHashNotSupported`` where later distros write the
   RIHS01 hash (``key_hash``).
3. In a token each component is mangled: every ``/`` becomes ``%``, and an empty (or root)
   enclave or namespace is ``%``.
4. A QoS field equal to rmw_zenoh's default (reliable, volatile, keep last, depth 42,
   infinite durations, automatic liveliness) is left empty in its text.
5. ``read_attachment`` never raises: an attachment of the wrong size or GID length is
   ``None``. What busgate builds itself (keys, tokens, attachments) raises ``ValueError`` on a
   bad argument: that is a programming or configuration error, not network input.
6. Each ``*_problem`` function returns a one-line reason, or ``None`` for a good name.
"""

from __future__ import annotations

import os
import re
import struct
from dataclasses import dataclass
from enum import StrEnum
from typing import Final

from busgate.codecs.ros2.messages import message_type
from busgate.codecs.ros2.type_hash import type_hash

__all__ = [
    "ATTACHMENT_SIZE",
    "COMMANDS",
    "DEFAULT",
    "DISTROS",
    "GID_SIZE",
    "HASH_NOT_SUPPORTED",
    "LIVELINESS_PREFIX",
    "NODE_KIND",
    "SENSOR_DATA",
    "SERVICES",
    "Attachment",
    "EntityKind",
    "Node",
    "Qos",
    "attachment",
    "data_key",
    "entity_token",
    "key_hash",
    "mangle",
    "name_problem",
    "namespace_problem",
    "new_gid",
    "node_name_problem",
    "node_token",
    "read_attachment",
    "resolve",
]

#: The ROS 2 distributions busgate can speak to over rmw_zenoh.
DISTROS: Final = ("humble", "jazzy", "kilted", "rolling")
#: What Humble's rmw_zenoh writes in place of a type hash.
HASH_NOT_SUPPORTED: Final = "TypeHashNotSupported"
#: The first chunk of every liveliness token (hermetic: ``*`` and ``**`` never match it).
LIVELINESS_PREFIX: Final = "@ros2_lv"
#: The kind of a node's own token.
NODE_KIND: Final = "NN"
GID_SIZE: Final = 16
_ATTACHMENT: Final = struct.Struct(f"<qqB{GID_SIZE}s")
#: Sequence number (int64), source timestamp in ns (int64), GID length (one byte), GID.
ATTACHMENT_SIZE: Final = _ATTACHMENT.size
#: rmw_zenoh's default history depth: a depth equal to it is left out of the QoS text.
_RMW_ZENOH_DEFAULT_DEPTH: Final = 42
#: rmw's enum values, as the QoS text writes them when they are not the default.
_BEST_EFFORT: Final = "2"
_TRANSIENT_LOCAL: Final = "1"
_TOKEN: Final = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class EntityKind(StrEnum):
    """The kind of an entity's liveliness token."""

    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE_SERVER = "SS"
    SERVICE_CLIENT = "SC"


@dataclass(frozen=True, slots=True)
class Qos:
    """The QoS busgate uses: reliable or best effort, volatile or transient local, keep last
    ``depth`` samples (deadlines, lifespan and liveliness always at their defaults)."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10

    def __post_init__(self) -> None:
        if self.depth < 1:
            raise ValueError(f"a history depth of {self.depth}: at least 1")

    def text(self) -> str:
        """The compact form rmw_zenoh puts in tokens (rule 4).

        >>> Qos(reliable=False, depth=5).text()
        '2::,5:,:,:,,'
        """
        reliability = "" if self.reliable else _BEST_EFFORT
        durability = _TRANSIENT_LOCAL if self.transient_local else ""
        depth = "" if self.depth == _RMW_ZENOH_DEFAULT_DEPTH else str(self.depth)
        return f"{reliability}:{durability}:,{depth}:,:,:,,"


#: rclcpp's sensor data profile: best effort, keep last 5.
SENSOR_DATA: Final = Qos(reliable=False, depth=5)
#: What ros2_control's topic-based system publishes commands with: reliable, keep last 1.
COMMANDS: Final = Qos(depth=1)
#: rclcpp's default for topics: reliable, volatile, keep last 10.
DEFAULT: Final = Qos()
#: rclcpp's default for services: reliable, volatile, keep last 10.
SERVICES: Final = Qos()


@dataclass(frozen=True, slots=True)
class Node:
    """A ROS node as its tokens name it: ``namespace`` "" or ``/a/b``, ``enclave`` "" or
    ``/name``; ``zid`` the zenoh session's id, ``node_id`` unique within the session."""

    domain_id: int
    zid: str
    node_id: int
    name: str
    namespace: str = ""
    enclave: str = ""


@dataclass(frozen=True, slots=True)
class Attachment:
    """What rmw_zenoh attaches to each sample, request and reply."""

    sequence: int
    timestamp_ns: int
    gid: bytes


def key_hash(type_name: str, distro: str) -> str:
    """The type hash as ``distro``'s rmw_zenoh writes it in keys and tokens (rule 2)."""
    if distro not in DISTROS:
        raise ValueError(f"unknown ROS 2 distribution {distro!r}; known: {', '.join(DISTROS)}")
    message_type(type_name)  # an unknown type fails on Humble too
    return HASH_NOT_SUPPORTED if distro == "humble" else type_hash(type_name)


def data_key(domain_id: int, name: str, type_name: str, distro: str) -> str:
    """The key a topic's samples (or a service's queries) go on; ``name`` fully qualified.

    >>> data_key(0, "/chatter", "std_msgs/msg/Bool", "humble")
    '0/chatter/std_msgs::msg::dds_::Bool_/TypeHashNotSupported'
    """
    _check_domain(domain_id)
    _check_fully_qualified(name)
    dds_name = message_type(type_name).dds_name
    return f"{domain_id}/{name[1:]}/{dds_name}/{key_hash(type_name, distro)}"


def mangle(component: str) -> str:
    """A token component: each ``/`` becomes ``%``; empty (or ``/``) is ``%`` (rule 3).

    >>> mangle("/robot/arm"), mangle("")
    ('%robot%arm', '%')
    """
    return component.replace("/", "%") if component not in ("", "/") else "%"


def node_token(node: Node) -> str:
    """The liveliness token that makes ``node`` appear in ``ros2 node list``."""
    return "/".join((_node_prefix(node, node.node_id, NODE_KIND), mangle(node.name)))


def entity_token(
    node: Node,
    entity_id: int,
    kind: EntityKind,
    topic: str,
    type_name: str,
    distro: str,
    qos: Qos,
) -> str:
    """The liveliness token of a publisher, subscription, service server or client of
    ``node``; ``topic`` is the fully qualified topic (or service) name."""
    _check_fully_qualified(topic)
    dds_name = message_type(type_name).dds_name
    return "/".join(
        (
            _node_prefix(node, entity_id, kind),
            mangle(node.name),
            mangle(topic),
            dds_name,
            key_hash(type_name, distro),
            qos.text(),
        )
    )


def _node_prefix(node: Node, entity_id: int, kind: str) -> str:
    _check_domain(node.domain_id)
    problem = node_name_problem(node.name) or namespace_problem(node.namespace)
    if problem:
        raise ValueError(problem)
    return "/".join(
        (
            LIVELINESS_PREFIX,
            str(node.domain_id),
            node.zid,
            str(node.node_id),
            str(entity_id),
            kind,
            mangle(node.enclave),
            mangle(node.namespace),
        )
    )


def attachment(sequence: int, timestamp_ns: int, gid: bytes) -> bytes:
    """The 33 bytes to attach to a sample, request or reply.

    >>> len(attachment(1, 0, bytes(16)))
    33
    """
    if len(gid) != GID_SIZE:
        raise ValueError(f"a GID of {len(gid)} bytes, not {GID_SIZE}")
    try:
        return _ATTACHMENT.pack(sequence, timestamp_ns, GID_SIZE, gid)
    except struct.error as error:
        raise ValueError(f"sequence {sequence} or timestamp {timestamp_ns}: {error}") from error


def read_attachment(data: bytes | bytearray | memoryview | None) -> Attachment | None:
    """The attachment in ``data``, or ``None`` when it is missing or not rmw_zenoh's."""
    if data is None or len(data) != ATTACHMENT_SIZE:
        return None
    sequence, timestamp_ns, gid_size, gid = _ATTACHMENT.unpack(data)
    if gid_size != GID_SIZE:
        return None
    return Attachment(sequence, timestamp_ns, gid)


def new_gid() -> bytes:
    """A fresh random GID for a publisher, subscription, server or client."""
    return os.urandom(GID_SIZE)


def resolve(name: str, namespace: str, node: str) -> str:
    """The fully qualified form of a topic or service ``name`` used by ``node`` in
    ``namespace``; ``ValueError`` when one of them breaks ROS's rules.

    >>> resolve("~/joint_trajectory", "/robot", "ctrl"), resolve("x", "", "n")
    ('/robot/ctrl/joint_trajectory', '/x')
    """
    problem = name_problem(name) or namespace_problem(namespace) or node_name_problem(node)
    if problem:
        raise ValueError(problem)
    if name.startswith("/"):
        return name
    prefix = namespace.rstrip("/")
    if name == "~":
        return f"{prefix}/{node}"
    if name.startswith("~/"):
        return f"{prefix}/{node}/{name[2:]}"
    return f"{prefix}/{name}"


def name_problem(name: str) -> str | None:
    """Why ``name`` is not a valid topic or service name (absolute, relative or ``~``)."""
    if not name:
        return "a topic name must not be empty"
    if name == "~":
        return None
    body = name.removeprefix("~/") if name.startswith("~/") else name.removeprefix("/")
    return _tokens_problem(f"topic name {name!r}", body)


#: The longest node name ROS 2 takes (rmw's ``RMW_NODE_NAME_MAX_NAME_LENGTH``).
MAX_NODE_NAME = 255


def node_name_problem(name: str) -> str | None:
    """Why ``name`` is not a valid node name (letters, digits, ``_``; no leading digit; at
    most ``MAX_NODE_NAME`` characters)."""
    if not name:
        return "a node name must not be empty"
    if len(name) > MAX_NODE_NAME:
        return f"node name {name[:40]!r}… is {len(name)} characters, over ROS 2's {MAX_NODE_NAME}"
    return _token_problem(f"node name {name!r}", name)


def namespace_problem(namespace: str) -> str | None:
    """Why ``namespace`` is not a valid namespace ("" and "/" are the root)."""
    if namespace in ("", "/"):
        return None
    if not namespace.startswith("/"):
        return f"namespace {namespace!r} must start with '/'"
    return _tokens_problem(f"namespace {namespace!r}", namespace[1:])


def _tokens_problem(what: str, body: str) -> str | None:
    if not body or body.endswith("/"):
        return f"{what} must not end with '/'"
    for token in body.split("/"):
        if not token:
            return f"{what} must not contain '//'"
        problem = _token_problem(what, token)
        if problem:
            return problem
    return None


def _token_problem(what: str, token: str) -> str | None:
    if _TOKEN.fullmatch(token):
        return None
    if "~" in token:
        return f"{what}: '~' may only start a name, as '~' or '~/'"
    if token[0].isdigit():
        return f"{what}: {token!r} starts with a digit"
    return f"{what}: {token!r} has a character other than letters, digits and '_'"


def _check_domain(domain_id: int) -> None:
    if domain_id < 0:
        raise ValueError(f"a ROS domain id of {domain_id}: at least 0")


def _check_fully_qualified(name: str) -> None:
    problem = name_problem(name)
    if problem or not name.startswith("/"):
        raise ValueError(problem or f"{name!r} is not fully qualified (it must start with '/')")
