"""REP 2016 type hashes (``RIHS01_<sha256>``), computed from ``definitions`` as rosidl does.

rmw_zenoh puts the hash in every data key and liveliness token (Jazzy on): a peer whose hash
differs sees another topic. So the hash is computed here from the same definitions the wire
format uses, and tests/test_ros2_codec.py checks it against rosbags and against values rosidl
generated.

Rules of this file:

1. What is hashed is rosidl's type description without default values:
   ``{"type_description": T, "referenced_type_descriptions": [...]}``, T being
   ``{"type_name", "fields": [{"name", "type": {"type_id", "capacity", "string_capacity",
   "nested_type_name"}}]}``; the referenced types are every type reachable from T, each once,
   sorted by name. Constants are not in it.
2. Serialised with ``json.dumps``' defaults (separators ``", "`` and ``": "``, ASCII), hashed
   with SHA-256, printed in lowercase hex after ``RIHS01_``.
3. ``type_id`` is rosidl's ``FieldType``: the element's code, plus 48 for a fixed array, 96
   for a bounded sequence, 144 for an unbounded one. A ``.msg`` ``char`` is uint8 (3), never
   rosidl's char (13): ``definitions`` already reads it so.
4. Each hash is computed once per process (cached).
"""

from __future__ import annotations

import functools
import hashlib
import json
from typing import Final

from busgate.codecs.ros2.definitions import Collection, Field, FieldType, struct

__all__ = ["RIHS01_PREFIX", "type_description", "type_hash"]

RIHS01_PREFIX: Final = "RIHS01_"

#: rosidl's FieldType codes of the elements ``definitions`` allows.
_ELEMENT_IDS: Final[dict[str, int]] = {
    "int8": 2,
    "uint8": 3,
    "int16": 4,
    "uint16": 5,
    "int32": 6,
    "uint32": 7,
    "int64": 8,
    "uint64": 9,
    "float32": 10,
    "float64": 11,
    "bool": 15,
    "byte": 16,
    "string": 17,
}
_NESTED_ID: Final = 1
_BOUNDED_STRING_ID: Final = 21
_COLLECTION_OFFSETS: Final[dict[Collection, int]] = {
    Collection.SINGLE: 0,
    Collection.FIXED: 48,
    Collection.BOUNDED: 96,
    Collection.UNBOUNDED: 144,
}


@functools.cache
def type_hash(name: str) -> str:
    """``RIHS01_<64 hex>`` of a message or service type (``ValueError`` for an unknown one).

    >>> type_hash("builtin_interfaces/msg/Time")[:23]
    'RIHS01_b106235e25a4c5ed'
    """
    text = json.dumps(type_description(name))
    return RIHS01_PREFIX + hashlib.sha256(text.encode()).hexdigest()


def type_description(name: str) -> dict[str, object]:
    """The structure that is hashed (rule 1), for ``name`` and every type it refers to."""
    referenced = sorted(_reachable(name) - {name})
    return {
        "type_description": _description(name),
        "referenced_type_descriptions": [_description(other) for other in referenced],
    }


def _reachable(name: str) -> set[str]:
    found = {name}
    pending = [name]
    while pending:
        for nested in struct(pending.pop()).nested_names:
            if nested not in found:
                found.add(nested)
                pending.append(nested)
    return found


def _description(name: str) -> dict[str, object]:
    return {"type_name": name, "fields": [_field(field) for field in struct(name).fields]}


def _field(field: Field) -> dict[str, object]:
    return {"name": field.name, "type": _field_type(field.type)}


def _field_type(field_type: FieldType) -> dict[str, object]:
    if field_type.nested:
        element_id = _NESTED_ID
    elif field_type.string_capacity:
        element_id = _BOUNDED_STRING_ID
    else:
        element_id = _ELEMENT_IDS[field_type.element]
    return {
        "type_id": element_id + _COLLECTION_OFFSETS[field_type.collection],
        "capacity": field_type.capacity,
        "string_capacity": field_type.string_capacity,
        "nested_type_name": field_type.element if field_type.nested else "",
    }
