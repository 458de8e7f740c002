"""What mutation testing (``python tools/mutation/run.py codecs``) found tests/test_ros2_codec.py
leaving open in ``busgate.codecs.ros2``, against the same peers where there is one (rosbags'
CDR, constants and RIHS01 hashes, the hashes rosidl generated) and hand-worked bytes where
there is none.

Why the definitions and codecs are parsed afresh here: ``definitions.struct``,
``messages._codec`` and ``type_hash.type_hash`` are cached per process, and mutmut runs each
mutant in a child forked from a process whose caches its clean run already filled, so a test
that only reads a type the clean run had parsed never reaches the parser or the codec builder
at all. Every test of this file empties the three caches first (``parsed_afresh``).

What it pins: each part of a service (request, response, event, the service itself) is the
type rosidl generates, and every type parsed carries the name it was asked by; constants,
array defaults and bounded strings in arrays are parsed as rosbags parses them; every field
missing from a value takes ROS's zero (the bytes rosbags writes for a zero message); fixed
arrays have no count, sequences have one and keep their bound both ways; a sequence of small
elements is read when its bytes are all there; every refusal of ``encode`` names the field,
keeps the value and says in words what was wrong, and so do the CDR writer's and reader's
own errors; ``time_of``/``seconds_of`` at whole seconds, below zero and with parts missing;
the exact reasons of rmw_zenoh's refusals, which the gateway's config checks print. Pure
calls, no session.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Nodetype, Typestore

from busgate.codecs.errors import CdrError, EncodeError
from busgate.codecs.ros2 import messages
from busgate.codecs.ros2 import rmw_zenoh as rz
from busgate.codecs.ros2.cdr import CDR_LE, CdrReader, CdrWriter
from busgate.codecs.ros2.definitions import MESSAGES, SERVICES, TYPE_NAMES, struct
from busgate.codecs.ros2.messages import decode, encode, message_type, seconds_of, time_of
from busgate.codecs.ros2.type_hash import type_hash
from tests.test_ros2_codec import JAZZY, JOINT_STATE, ROSIDL_HASHES, same, to_rosbags

TRIGGER = "std_srvs/srv/Trigger"
EVENT = "std_srvs/srv/Trigger_Event"
SERVICE_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"


@pytest.fixture(autouse=True)
def parsed_afresh() -> Iterator[None]:
    """The caches of parsed definitions, built codecs and hashes emptied before the test (so
    it reaches the parser, see the docstring) and after it (so no made-up type stays)."""

    def clear() -> None:
        struct.cache_clear()
        messages._codec.cache_clear()
        type_hash.cache_clear()

    clear()
    yield
    clear()


def made_up(monkeypatch: pytest.MonkeyPatch, texts: dict[str, str]) -> Typestore:
    """``texts`` (full name: ``.msg`` text) in our definitions and in a rosbags store."""
    store = get_typestore(Stores.ROS2_JAZZY)
    for name, text in texts.items():
        monkeypatch.setitem(MESSAGES, name, text)
        store.register(get_types_from_msg(text, name))
    return store


def rosbags_bytes(store: Typestore, name: str, value: dict[str, Any]) -> bytes:
    return store.serialize_cdr(to_rosbags(store, name, value), name)


# --- services, names ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name", [TRIGGER, TRIGGER + "_Request", TRIGGER + "_Response", EVENT, SERVICE_EVENT_INFO]
)
def test_each_part_of_a_service_is_the_type_rosidl_generates(name: str) -> None:
    # The hash covers every field's name, type id, capacity and nested type: the request's
    # one uint8 placeholder, the event's info and [<=1] request and response, ``char[16]``
    # read as uint8[16] (in ServiceEventInfo, which the event refers to).
    assert type_hash(name) == ROSIDL_HASHES[name]


def test_every_type_parsed_carries_the_name_it_was_asked_by() -> None:
    for name in TYPE_NAMES:
        assert struct(name).name == name
        assert message_type(name).definition.name == name


def test_the_parts_of_a_service_on_the_wire() -> None:
    # An empty request is its placeholder uint8: one zero byte after the header (rule 4).
    request = TRIGGER + "_Request"
    assert encode(request, {}) == CDR_LE + b"\x00"
    assert decode(request, CDR_LE + b"\x07") == {"structure_needs_at_least_one_member": 7}
    # The event, worked by hand: info is event_type (uint8, 1 + 3 padding), stamp (int32,
    # uint32), client_gid (16 bytes, offset 12), padding to 32, sequence_number (int64);
    # then the request sequence (count 0) and the response sequence (count 1, bool, 3
    # padding, string "ok": length 3 with its NUL).
    event = {
        "info": {
            "event_type": 3,
            "stamp": {"sec": 5, "nanosec": 6},
            "client_gid": list(range(16)),
            "sequence_number": -7,
        },
        "request": [],
        "response": [{"success": True, "message": "ok"}],
    }
    wire = (
        CDR_LE
        + bytes.fromhex("03000000 05000000 06000000")
        + bytes(range(16))
        + bytes(4)
        + (-7).to_bytes(8, "little", signed=True)
        + bytes.fromhex("00000000 01000000 01 000000 03000000")
        + b"ok\x00"
    )
    assert encode(EVENT, event) == wire
    assert decode(EVENT, wire) == event
    with pytest.raises(EncodeError) as raised:
        encode(EVENT, {"request": [{}, {}]})
    assert raised.value.field == "request"
    assert str(raised.value) == "request: 2 elements, more than 1"


def test_a_service_text_with_a_second_separator_is_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # An action's three parts are no service: its "response" would hold a '---' line.
    monkeypatch.setitem(SERVICES, "busgate_test/srv/Three", "bool a\n---\nbool b\n---\nbool c\n")
    with pytest.raises(ValueError, match="bad field name"):
        struct("busgate_test/srv/Three_Response")


# --- the .msg syntax against rosbags --------------------------------------------------------


@pytest.mark.parametrize("name", ["diagnostic_msgs/msg/DiagnosticStatus", SERVICE_EVENT_INFO])
def test_constants_are_the_ones_rosbags_reads(name: str) -> None:
    constants, _ = JAZZY.fielddefs[name]
    assert [(c.name, c.type, c.value) for c in struct(name).constants] == [
        (n, t, str(v)) for n, t, v in constants
    ]


CONSTANTS = "busgate_test/msg/Constants"
CONSTANTS_TEXT = 'string GREETING="a=b"\nint32 LIMIT = -3\nint32 x\n'


def test_a_constant_whose_value_holds_an_equals_sign_is_named_as_rosbags_names_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    store = made_up(monkeypatch, {CONSTANTS: CONSTANTS_TEXT})
    constants, _ = store.fielddefs[CONSTANTS]
    ours = struct(CONSTANTS).constants
    assert [(c.name, c.type) for c in ours] == [(n, t) for n, t, _ in constants]
    assert [f.name for f in struct(CONSTANTS).fields] == ["x"]


def test_a_string_constant_value_is_read_without_its_quotes(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    store = made_up(monkeypatch, {CONSTANTS: CONSTANTS_TEXT})
    constants, _ = store.fielddefs[CONSTANTS]
    assert [c.value for c in struct(CONSTANTS).constants] == [str(v) for _, _, v in constants]


EDGES = "busgate_test/msg/Edges"
EDGES_TEXT = (
    "string EMPTY=\"\"\nstring PLAIN=abca\nstring XS=XabX\nstring SINGLE='b'\n"
    'int32 ELEVEN=11\nstring ONE="\nint32 x\n'
)


def test_a_string_constant_loses_only_quotes_around_it_as_rosbags_reads_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # Quotes of either kind that open and close it go; a lone quote, a value whose ends only
    # match, and a number whose ends match stay as written.
    store = made_up(monkeypatch, {EDGES: EDGES_TEXT})
    constants, _ = store.fielddefs[EDGES]
    assert [(c.name, c.value) for c in struct(EDGES).constants] == [
        (n, str(v)) for n, _, v in constants
    ]
    assert [c.value for c in struct(EDGES).constants] == ["", "abca", "XabX", "b", "11", '"']


def test_a_constant_of_a_message_type_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    text = "Part X=1\nint32 y\n"
    with pytest.raises(Exception, match="Could not parse"):
        get_types_from_msg(text, "busgate_test/msg/Refused")
    monkeypatch.setitem(MESSAGES, "busgate_test/msg/Refused", text)
    with pytest.raises(ValueError, match="a constant is of a primitive type, not 'Part X=1'"):
        struct("busgate_test/msg/Refused")


def test_array_defaults_and_bounded_strings_in_arrays_hash_as_rosbags(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    name = "busgate_test/msg/Tags"
    text = "int32[] xs [1, 2]\nfloat64 w 1\nstring<=5[3] fixed_tags\nstring<=6[] tags\n"
    store = made_up(monkeypatch, {name: text})
    assert [f.name for f in struct(name).fields] == ["xs", "w", "fixed_tags", "tags"]
    assert type_hash(name) == store.hash_rihs01(name)
    value = {"xs": [1], "w": 0.5, "fixed_tags": ["a", "", "12345"], "tags": ["123456"]}
    assert encode(name, value) == rosbags_bytes(store, name, value)
    for field, tags in (("fixed_tags", ["123456", "", ""]), ("tags", ["1234567"])):
        with pytest.raises(EncodeError) as raised:
            encode(name, {field: tags})
        bound = 5 if field == "fixed_tags" else 6
        assert (raised.value.field, raised.value.value) == (f"{field}[0]", tags[0])
        assert str(raised.value) == f"{field}[0]: longer than its bound of {bound} bytes"


# --- zero values, arrays and sequences against rosbags --------------------------------------

#: ROS's zero of each primitive rosbags names (rosidl's default-initialised message).
_ZEROS: dict[str, object] = {"bool": False, "float32": 0.0, "float64": 0.0, "string": ""}


def zero_of(store: Typestore, name: str) -> dict[str, Any]:
    """The zero message of ``name``, walked from rosbags' field definitions."""
    _, fields = store.fielddefs[name]
    return {field: _zero_field(store, desc) for field, desc in fields}


def _zero_field(store: Typestore, desc: Any) -> Any:
    node, detail = desc
    if node == Nodetype.BASE:
        return _ZEROS.get(detail[0], 0)
    if node == Nodetype.NAME:
        return zero_of(store, detail)
    element, size = detail
    if node == Nodetype.ARRAY:
        return [_zero_field(store, element) for _ in range(size)]
    return []


KINDS = "busgate_test/msg/Kinds"
KINDS_TEXT = (
    "bool t\nbyte b\nint8 i8\nuint8 u8\nint16 i16\nuint16 u16\nint32 i32\nuint32 u32\n"
    "int64 i64\nuint64 u64\nfloat32 f32\nfloat64 f64\nstring s\nbool[2] flags\n"
    "float32[2] pair\n"
)


@pytest.mark.parametrize("name", [n for n in MESSAGES if n != SERVICE_EVENT_INFO] + [KINDS])
def test_a_missing_field_takes_ros_zero(monkeypatch: pytest.MonkeyPatch, name: str) -> None:
    store = made_up(monkeypatch, {KINDS: KINDS_TEXT}) if name == KINDS else JAZZY
    zero = zero_of(store, name)
    assert encode(name, {}) == rosbags_bytes(store, name, zero)
    decoded = decode(name, encode(name, {}))
    assert decoded is not None and same(decoded, zero)


SHAPES = "busgate_test/msg/Arrays"
ARRAYS = {
    SHAPES: (
        "uint8[2] pair\nfloat64[3] triple\nint32[<=2] few\nstring[] names\n"
        "Part[2] two_parts\nPart[<=2] some_parts\nPart[] parts\n"
    ),
    "busgate_test/msg/Part": "int8 x\nstring label\n",
}


def test_fixed_arrays_have_no_count_and_sequences_have_one_as_rosbags(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    store = made_up(monkeypatch, ARRAYS)
    part = {"x": -1, "label": "p"}
    value = {
        "pair": [1, 2],
        "triple": [0.5, 1.5, 2.5],
        "few": [7],
        "names": ["a", "bc"],
        "two_parts": [part, {"x": 3, "label": ""}],
        "some_parts": [part],
        "parts": [part] * 3,
    }
    wire = encode(SHAPES, value)
    assert wire == rosbags_bytes(store, SHAPES, value)
    assert decode(SHAPES, wire) == value
    # The fixed uint8[2] comes first, with no count: its two bytes right after the header.
    assert wire[4:6] == b"\x01\x02"
    for field, bad in (("few", [1, 2, 3]), ("some_parts", [part] * 3), ("pair", [1])):
        with pytest.raises(EncodeError) as raised:
            encode(SHAPES, {field: bad})
        assert (raised.value.field, raised.value.value) == (field, bad)
    with pytest.raises(EncodeError) as raised:
        encode(SHAPES, {"two_parts": [part]})
    assert str(raised.value) == "two_parts: 1 elements, not 2"


def test_a_sequence_longer_than_its_bound_is_not_read(monkeypatch: pytest.MonkeyPatch) -> None:
    made_up(monkeypatch, ARRAYS)
    one = encode(SHAPES, {"few": [5]})
    # ``few`` follows pair (2 bytes), padding (6) and triple (24): its count is at 36.
    assert one[36:44] == bytes.fromhex("01000000 05000000")
    three = one[:36] + bytes.fromhex("03000000 05000000 06000000 07000000") + one[44:]
    assert decode(SHAPES, three) is None
    two = one[:36] + bytes.fromhex("02000000 05000000 06000000") + one[44:]
    assert decode(SHAPES, two) == decode(SHAPES, encode(SHAPES, {"few": [5, 6]}))


def test_a_sequence_of_small_fixed_arrays_is_read_when_its_bytes_are_there(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    pairs = "busgate_test/msg/Pairs"
    texts = {pairs: "Pair[] pairs\n", "busgate_test/msg/Pair": "uint8[2] xy\n"}
    store = made_up(monkeypatch, texts)
    value = {"pairs": [{"xy": [1, 2]}, {"xy": [3, 4]}, {"xy": [5, 6]}]}
    # Three elements of two bytes each: six bytes after the count, fewer than 3 x 4.
    wire = CDR_LE + bytes.fromhex("03000000 010203040506")
    assert rosbags_bytes(store, pairs, value) == wire
    assert decode(pairs, wire) == value


# --- encode's refusals: the field, the value, the reason ------------------------------------

ODOMETRY = "nav_msgs/msg/Odometry"
BOOL = "std_msgs/msg/Bool"


@pytest.mark.parametrize(
    ("name", "value", "field", "bad", "reason"),
    [
        (BOOL, {"dat": True}, "", {"dat": True}, "the message: unknown fields ['dat']"),
        (JOINT_STATE, {"header": []}, "header", [], "header: [] is not a dict"),
        (BOOL, {"data": 1}, "data", 1, "data: 1 is not a bool"),
        (JOINT_STATE, {"name": [1]}, "name[0]", 1, "name[0]: 1 is not a string"),
        (JOINT_STATE, {"name": "hip"}, "name", "hip", "name: 'hip' is not a list"),
        (
            ODOMETRY,
            {"pose": {"covariance": [0.0] * 35}},
            "pose.covariance",
            [0.0] * 35,
            "pose.covariance: 35 elements, not 36",
        ),
    ],
)
def test_a_refusal_names_the_field_keeps_the_value_and_says_why(
    name: str, value: dict[str, Any], field: str, bad: object, reason: str
) -> None:
    with pytest.raises(EncodeError) as raised:
        encode(name, value)
    assert (raised.value.field, raised.value.value, str(raised.value)) == (field, bad, reason)


@pytest.mark.parametrize(
    ("value", "field", "bad", "reason"),
    [
        (
            {"header": {"stamp": {"sec": 2**31}}},
            "header.stamp.sec",
            2**31,
            "header.stamp.sec: 2147483648 does not fit a int32: ",
        ),
        ({"name": ["\ud800"]}, "name[0]", "\ud800", "name[0]: '\\ud800' is not valid Unicode: "),
        # An array of numbers is named whole (messages rule 2), with the whole list.
        (
            {"position": [0.0, "1"]},
            "position",
            [0.0, "1"],
            "position: an element does not fit a float64: ",
        ),
    ],
)
def test_a_refusal_by_the_cdr_writer_carries_its_reason_through(
    value: dict[str, Any], field: str, bad: object, reason: str
) -> None:
    with pytest.raises(EncodeError) as raised:
        encode(JOINT_STATE, value)
    assert (raised.value.field, raised.value.value) == (field, bad)
    assert str(raised.value).startswith(reason) and len(str(raised.value)) > len(reason)


def test_the_cdr_writer_refuses_with_the_value() -> None:
    for call, bad in (
        (lambda: CdrWriter().primitive("bool", 1), 1),
        (lambda: CdrWriter().primitive("int32", 2**31), 2**31),
        (lambda: CdrWriter().string("\ud800"), "\ud800"),
    ):
        with pytest.raises(EncodeError) as raised:
            call()
        assert raised.value.value == bad


# --- the CDR reader's own errors ------------------------------------------------------------


def test_a_payload_of_the_header_alone_is_read_to_its_end() -> None:
    reader = CdrReader(CDR_LE)
    assert reader.remaining == 0
    reader.finish()
    with pytest.raises(CdrError) as raised:
        reader.primitive("uint32")
    assert str(raised.value) == "4 bytes needed at offset 4, the payload ends first"
    with pytest.raises(CdrError) as raised:
        CdrReader(CDR_LE[:3])
    assert str(raised.value) == "not a little-endian CDR payload"


def test_a_count_is_refused_when_the_bytes_left_cannot_hold_its_elements() -> None:
    payload = CDR_LE + bytes.fromhex("03000000") + bytes(16)
    with pytest.raises(CdrError) as raised:
        CdrReader(payload).count(8)  # 3 float64 need 24 bytes
    assert str(raised.value) == "a count of 3 does not fit the 16 bytes left"
    assert CdrReader(payload).count(5) == 3  # 15 bytes fit


@pytest.mark.parametrize(
    ("body", "read", "reason"),
    [
        ("02000000 6f6b", CdrReader.string, "a string at offset 8 lacks its NUL terminator"),
        ("02000000 ff00", CdrReader.string, "a string at offset 8 is not UTF-8"),
        ("02", lambda reader: reader.primitive("bool"), "a bool byte of 2"),
        ("00000000", CdrReader.finish, "4 bytes left after the last field"),
    ],
)
def test_the_cdr_reader_says_what_was_wrong(body: str, read: Any, reason: str) -> None:
    with pytest.raises(CdrError) as raised:
        read(CdrReader(CDR_LE + bytes.fromhex(body)))
    assert str(raised.value) == reason


# --- time ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("seconds", "time"),
    [
        (3.0, {"sec": 3, "nanosec": 0}),
        (2.5, {"sec": 2, "nanosec": 500_000_000}),
        # builtin_interfaces keeps nanosec in [0, 1e9): -0.25 s is -1 s + 0.75 s.
        (-0.25, {"sec": -1, "nanosec": 750_000_000}),
    ],
)
def test_time_of_and_seconds_of(seconds: float, time: dict[str, int]) -> None:
    assert time_of(seconds) == time
    assert seconds_of(time) == seconds


def test_a_time_missing_a_part_reads_it_as_zero() -> None:
    assert seconds_of({"sec": 2}) == 2.0
    assert seconds_of({"nanosec": 500_000_000}) == 0.5
    assert seconds_of({}) == 0


# --- rmw_zenoh's reasons -------------------------------------------------------------------


def _reason(call: Any, *args: Any) -> str:
    with pytest.raises(ValueError) as raised:
        call(*args)
    return str(raised.value)


def test_key_and_token_refusals_say_why() -> None:
    assert _reason(rz.Qos, True, False, 0) == "a history depth of 0: at least 1"
    assert _reason(rz.key_hash, JOINT_STATE, "iron") == (
        "unknown ROS 2 distribution 'iron'; known: humble, jazzy, kilted, rolling"
    )
    assert _reason(rz.data_key, -1, "/x", JOINT_STATE, "jazzy") == (
        "a ROS domain id of -1: at least 0"
    )
    assert _reason(rz.data_key, 0, "x", JOINT_STATE, "jazzy") == (
        "'x' is not fully qualified (it must start with '/')"
    )
    # Fully qualified, but not a name: refused for what is wrong with it.
    assert _reason(rz.data_key, 0, "/a//b", JOINT_STATE, "jazzy") == (
        "topic name '/a//b' must not contain '//'"
    )
    gid = bytes(16)
    assert _reason(rz.attachment, 1, 0, gid[:15]) == "a GID of 15 bytes, not 16"
    assert _reason(rz.attachment, 2**63, 0, gid).startswith(
        "sequence 9223372036854775808 or timestamp 0: "
    )


def test_name_refusals_say_why() -> None:
    assert rz.name_problem("") == "a topic name must not be empty"
    assert rz.node_name_problem("") == "a node name must not be empty"
    assert rz.name_problem("/x/a b") == (
        "topic name '/x/a b': 'a b' has a character other than letters, digits and '_'"
    )
    assert rz.namespace_problem("/a b") == (
        "namespace '/a b': 'a b' has a character other than letters, digits and '_'"
    )
    assert _reason(rz.resolve, "x", "robot", "n") == "namespace 'robot' must start with '/'"


def test_resolve_strips_only_a_trailing_slash_of_the_namespace() -> None:
    assert rz.resolve("x", "/boX", "n") == "/boX/x"
    assert rz.resolve("~", "/X", "n") == "/X/n"
