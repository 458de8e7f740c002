"""The gateway's configuration file (TOML), validated by pydantic.

Rules of this file: everything a running gateway relies on is checked here, before any port
is opened, and every refusal names its key path (``buses[0].devices[1].follow_period_ms``)
and what is allowed. A key no table takes is named with its table and the key it most likely
misspells (``buses[0]: unknown key `baudrat` (did you mean `baudrate`?)``), told once: the
key it misspells is not reported missing as well. Kinds, their protocols per transport, id
ranges and timing limits come from the family registry (``busgate.schemas.families``) and the
codecs it names, so a limit is written down once. Whether a port exists is not checked here:
that is the host's business, and ``busgate check-config`` reports it as a warning. The host is
looked at once: symlinks are resolved (``os.path.realpath``), so that two buses naming one
device file (``/dev/ttyUSB0`` and a udev link to it) are refused instead of fighting over the
port.
"""

from __future__ import annotations

import json
import os
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal, get_args

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from busgate.errors import ConfigError
from busgate.schemas.base import (
    CLIENT_ID_PATTERN,
    CLIENTS_ROOM,
    KEY_PREFIX_FORM,
    KEY_PREFIX_PATTERN,
    NAME_FORM,
    Name,
)
from busgate.schemas.bases import BaseConfig, wheel_problem
from busgate.schemas.endpoints import (
    Endpoint,
    ListenEndpoint,
    ZenohMode,
    clash_at,
    takes_tcp_port,
)
from busgate.schemas.families import FAMILIES, PROTOCOLS, kinds, protocol_of
from busgate.schemas.files import FileRefused, read_text
from busgate.schemas.joints import Joint, JointTable, table_problems, table_warnings
from busgate.schemas.ros2 import Ros2Section
from busgate.schemas.validation import SHOWN_OP_CHARS, closest, cut, message_of, suggestion

KeyPrefix = Annotated[str, Field(pattern=KEY_PREFIX_PATTERN)]

#: The largest config file read: a robot's config is a few KiB.
MAX_CONFIG_BYTES = 1024 * 1024
FOLLOW_PERIOD_MS = (10.0, 50.0)  # the actuators' follow mode: a fixed period of 10–50 ms
#: An unknown key's refusal lists the keys of its table when there are at most this many.
LISTED_KEYS = 6


class Section(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True, allow_inf_nan=False)


#: ``[gateway] workers``: at most this many processes run the buses (``gateway.workers``).
MAX_WORKERS = 64


def workers_value(value: object) -> object:
    """``[gateway] workers`` refused in one line, whatever is wrong with it."""
    if value == "auto" or (type(value) is int and 1 <= value <= MAX_WORKERS):
        return value
    raise ValueError(
        f'"auto" or a whole number of processes from 1 to {MAX_WORKERS}, '
        f"not {json.dumps(value, default=repr)}"  # as TOML spells it: true, "AUTO"
    )


class GatewaySection(Section):
    name: Name
    prefix: KeyPrefix = "busgate"
    #: The processes the buses are split across (docs/workers.md): ``"auto"`` (the default),
    #: one per core, at most one per bus; or a count (``1``: every bus in the gateway's own
    #: process).
    workers: Annotated[
        Literal["auto"] | Annotated[int, Field(ge=1, le=MAX_WORKERS)],
        BeforeValidator(workers_value),
    ] = "auto"

    @field_validator("name")
    @classmethod
    def _not_the_clients_room(cls, name: str) -> str:
        if name == CLIENTS_ROOM:
            raise ValueError(
                f"{CLIENTS_ROOM!r} is where clients hold their liveliness tokens "
                f"(<prefix>/{CLIENTS_ROOM}/<id>): name the gateway otherwise"
            )
        return name


class ZenohSection(Section):
    mode: ZenohMode = "peer"
    listen: list[ListenEndpoint] = []
    connect: list[Endpoint] = []
    multicast_scouting: bool = False
    config_file: str | None = None

    @model_validator(mode="after")
    def _check_endpoints(self) -> ZenohSection:
        for index in range(len(self.listen)):
            if clash := clash_at(self.listen, index):
                other, endpoint = clash
                if other == endpoint:
                    raise ValueError(f"listen: {endpoint} is given twice")
                raise ValueError(f"listen: {other} and {endpoint} take the same port")
        if self.mode == "client" and not self.connect and self.config_file is None:
            raise ValueError(
                'connect: a gateway in mode "client" reaches others through a router: name '
                'its endpoint (connect = ["tcp/192.168.1.2:7447"])'
            )
        return self


#: ``HOST:PORT`` (an address to listen on) and an absolute path, as keys' patterns.
HOST_PORT_PATTERN, ABSOLUTE_PATH_PATTERN = r"^[^:\s]+:\d{1,5}$", r"^/[^\x00]*$"
#: What a key of each pattern takes, as a refusal says it (pydantic names the pattern).
PATTERN_FORMS = {
    CLIENT_ID_PATTERN: NAME_FORM,
    KEY_PREFIX_PATTERN: KEY_PREFIX_FORM,
    HOST_PORT_PATTERN: "HOST:PORT (e.g. 127.0.0.1:9100)",
    ABSOLUTE_PATH_PATTERN: "an absolute path",
}


def _port_in_range(listen: str) -> str:
    """``HOST:PORT`` whose port a socket can bind, and is named: as a zenoh listener's
    (``schemas.endpoints`` rule 1), port 0 would be one the system picks, that no scraper
    could be told."""
    port = int(listen.rpartition(":")[2])
    if port == 0:
        raise ValueError(
            "port 0 is one the system picks and tells nobody: name the port Prometheus scrapes"
        )
    if port > 65535:
        raise ValueError(f"the port of {listen} is over 65535")
    return listen


class MetricsSection(Section):
    listen: Annotated[str, Field(pattern=HOST_PORT_PATTERN), AfterValidator(_port_in_range)]


class RecorderSection(Section):
    """The flight recorder: the last ``seconds`` of the gateway's telemetry, commands and
    frames in memory, written to ``dir`` as one MCAP file per incident (an e-stop, a fault
    raised, a bus down, SIGUSR1). The oldest files go once they take more than
    ``max_total_mb``."""

    seconds: Annotated[float, Field(ge=1, le=600)] = 60.0
    dir: Annotated[str, Field(pattern=ABSOLUTE_PATH_PATTERN, max_length=1024)] = (
        "/var/lib/busgate/incidents"
    )
    max_total_mb: Annotated[int, Field(ge=1, le=1_000_000)] = 1024


class DeviceConfig(Section):
    name: Name
    kind: Literal[kinds()]  # type: ignore[valid-type]
    id: int = 1
    poll_hz: Annotated[float, Field(gt=0, le=1000)] = 10.0
    follow_period_ms: Annotated[float, Field(ge=FOLLOW_PERIOD_MS[0], le=FOLLOW_PERIOD_MS[1])] = 20.0
    #: ZLAC706 on CAN: the heartbeat interval set with the vendor tool (0 = no heartbeats);
    #: on any other bus, ignored and warned of (``ignored_keys``).
    heartbeat_ms: Annotated[int, Field(ge=0, le=60_000)] = 0
    #: The device as a joint in SI units: name, unit, calibration, limits (docs/joints.md).
    #: Without it, a joint in the family's raw units limited by the device's own range.
    joint: JointTable | None = None


class BusBase(Section):
    name: Name
    devices: Annotated[list[DeviceConfig], Field(min_length=1)]
    #: Reply deadline beyond wire time and the device's stated reply time: USB adapter latency
    #: (1 ms with an FTDI latency timer of 1) and the host's scheduling. Every poll must fit
    #: between two follow ticks with this margin, so it is kept small.
    reply_margin_ms: Annotated[float, Field(ge=0, le=1000)] = 2.0
    #: After a timeout, how long requests that expect a reply wait, so that a late reply is
    #: flushed as stale rather than taken for the next request's answer.
    late_reply_holdoff_ms: Annotated[float, Field(ge=0, le=1000)] = 10.0
    #: SCHED_FIFO priority for the bus thread, when the process is allowed to use it; every
    #: other thread of the gateway's processes then runs at the highest priority a bus asks.
    realtime_priority: Annotated[int, Field(ge=1, le=99)] | None = None

    @property
    def protocol(self) -> str:
        """The wire protocol of the bus's devices (``_check_bus`` made sure there is one)."""
        protocol = protocol_of(self.devices[0].kind, self.transport)  # type: ignore[attr-defined]
        assert protocol is not None
        return protocol.name


def _absolute_port(port: str) -> str:
    """A serial port is named from ``/``: a relative name is the working directory's, which is
    ``/`` under systemd (``ttyUSB0`` would be ``/ttyUSB0``)."""
    if not port.startswith("/"):
        meant = f"/{port}" if port.startswith("dev/") else None if "/" in port else f"/dev/{port}"
        raise ValueError(f"a port is a path from /{f' ({meant}?)' if meant else ''}, not {port!r}")
    return port


class SerialBus(BusBase):
    transport: Literal["serial"]
    port: Annotated[
        str,
        # the schema says what ``_absolute_port`` checks, which refuses in words of its own
        Field(
            min_length=1,
            pattern=r"^[^\x00]+$",
            json_schema_extra={"pattern": ABSOLUTE_PATH_PATTERN},
        ),
        AfterValidator(_absolute_port),
    ]
    baudrate: Annotated[int, Field(ge=1200, le=4_000_000)]
    #: Idle line between exchanges; default per protocol, never below the protocol's minimum.
    min_gap_ms: Annotated[float, Field(ge=0, le=100)] | None = None

    @property
    def device_key(self) -> tuple[str, str]:
        """(key, value) of the device file this bus opens."""
        return "port", self.port

    @property
    def gap_s(self) -> float:
        if self.min_gap_ms is None:
            return PROTOCOLS[self.protocol].timing.default_gap_s
        return self.min_gap_ms / 1000


#: ``can.Bus`` arguments a CAN bus sets from its own keys, never from ``options`` (python-can
#: calls ``bustype`` what is now ``interface``): option key → the bus's key.
OWN_CAN_KEYS = {"interface": "interface", "bustype": "interface", "channel": "channel",
                "bitrate": "bitrate"}  # fmt: skip


#: The largest CAN identifier, an extended (29-bit) one's.
CAN_ID_MAX = 0x1FFFFFFF
CanId = Annotated[int, Field(ge=0, le=CAN_ID_MAX)]


class CanFilter(Section):
    """One of python-can's receive filters (``can.BusABC.set_filters``): a frame passes when
    its identifier ``& can_mask`` is ``can_id & can_mask`` and, when ``extended`` is given,
    its identifier is extended or not as it says."""

    can_id: CanId
    can_mask: CanId
    extended: bool | None = None


def can_filters_value(value: object) -> object:
    """``options.can_filters`` refused in one line when it is not a list of tables (python-can
    took a string, and raised at every frame it read)."""
    if isinstance(value, list) and all(isinstance(item, dict | CanFilter) for item in value):
        return value
    raise ValueError(
        "a list of tables, each with can_id and can_mask (and extended, true or false), as "
        "python-can takes them: can_filters = [{ can_id = 0x581, can_mask = 0x7FF }]"
    )


class CanOptions(BaseModel):
    """A CAN bus's ``options``: further keyword arguments for ``can.Bus`` (e.g.
    ``tty_baudrate`` for slcan), each a value as TOML writes it, but ``can_filters``, a list
    of filters (``CanFilter``)."""

    model_config = ConfigDict(extra="allow", strict=True, frozen=True, allow_inf_nan=False)
    __pydantic_extra__: dict[str, str | int | float | bool] = Field(init=False)
    can_filters: Annotated[list[CanFilter], BeforeValidator(can_filters_value)] | None = None

    def arguments(self) -> dict[str, Any]:
        """What ``can.Bus`` is given: the options as written, each filter a plain dict with
        ``extended`` only when given (python-can tells an absent one from ``false``)."""
        return self.model_dump(exclude_none=True)


class CanBus(BusBase):
    transport: Literal["can"]
    interface: Annotated[str, Field(min_length=1)]
    channel: Annotated[str, Field(min_length=1)]
    bitrate: Annotated[int, Field(ge=10_000, le=1_000_000)] = 500_000
    #: Further keyword arguments for ``can.Bus``, none of ``OWN_CAN_KEYS``.
    options: CanOptions = CanOptions()

    @property
    def device_key(self) -> tuple[str, str] | None:
        """(key, value) of the device file this bus opens: slcan and other adapters are named
        by their tty (``/dev/ttyACM0@115200``: the tty, its baud rate after ``@``, as python-can
        reads it); a SocketCAN channel is a socket, no file."""
        path = self.channel.split("@", 1)[0]
        return ("channel", path) if path.startswith("/") else None


Bus = Annotated[SerialBus | CanBus, Field(discriminator="transport")]
#: The values of each tag key that says which kind of table one is (``transport``).
_TAGS = {
    "transport": [get_args(t.model_fields["transport"].annotation)[0] for t in (SerialBus, CanBus)]
}


class Config(Section):
    gateway: GatewaySection
    zenoh: ZenohSection = ZenohSection()
    metrics: MetricsSection | None = None
    recorder: RecorderSection | None = None
    ros2: Ros2Section | None = None
    buses: Annotated[list[Bus], Field(min_length=1)]
    bases: list[BaseConfig] = []

    @model_validator(mode="after")
    def _check_buses(self) -> Config:
        if self.metrics is not None:
            _require_own_metrics_port(self.metrics.listen, self.zenoh.listen)
        _require_unique("buses", [bus.name for bus in self.buses], "bus name")
        _require_unique("buses", [d.name for bus in self.buses for d in bus.devices], "device name")
        for index, bus in enumerate(self.buses):
            _check_bus(f"buses[{index}]", bus)
        _require_distinct_joint_names(self.buses)
        _require_own_device_files(self.buses)
        _check_bases(self.bases, self.buses)
        if self.ros2 is not None:
            self.ros2.require_distinct_names(self.gateway.name, [b.name for b in self.bases])
        return self


def _require_own_metrics_port(metrics: str, zenoh_listen: list[str]) -> None:
    """The metrics endpoint and a zenoh listener cannot share a port: the second to bind
    would find it in use, by the gateway itself."""
    host, _, port = metrics.rpartition(":")
    for endpoint in zenoh_listen:
        if takes_tcp_port(endpoint, host, int(port)):
            raise ValueError(f"metrics.listen: {metrics} is the zenoh listener {endpoint}'s port")


def _require_unique(path: str, names: list[str], what: str) -> None:
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise ValueError(f"{path}: {what} {name!r} is used twice; names must be unique")
        seen.add(name)


def _require_distinct_joint_names(buses: list[SerialBus | CanBus]) -> None:
    """A joint's name names one device: no other device or joint of the gateway has it
    (clients find a device by either)."""
    owner: dict[str, str] = {d.name: d.name for bus in buses for d in bus.devices}
    for bus_index, bus in enumerate(buses):
        for index, device in enumerate(bus.devices):
            name = device.joint.name if device.joint is not None else None
            if name is None or name == device.name:
                continue
            if name in owner:
                raise ValueError(
                    f"buses[{bus_index}].devices[{index}].joint.name: {name!r} already names "
                    f"{'device' if owner[name] == name else 'the joint of'} {owner[name]!r}; "
                    "joint names must be unique"
                )
            owner[name] = device.name


def _check_bases(bases: list[BaseConfig], buses: list[SerialBus | CanBus]) -> None:
    """Each base's name, none a device's; its wheels: devices of the gateway, ZLAC706
    velocity joints in rad, in one base only, fast enough for its limits (``schemas.bases``)."""
    devices = {device.name: device for bus in buses for device in bus.devices}
    _require_unique("bases", [base.name for base in bases], "base name")
    taken: dict[str, str] = {}
    for index, base in enumerate(bases):
        if base.name in devices:  # its events and refused puts would read as the device's
            raise ValueError(
                f"bases[{index}].name: {base.name!r} is a device's name too: name the base "
                "otherwise (its events would be taken for the device's)"
            )
        for side in ("left", "right"):
            name = getattr(base, side)
            path = f"bases[{index}].{side}"
            device = devices.get(name)
            if device is None:
                raise ValueError(f"{path}: no device {name!r} in the config's buses")
            if device.kind != "zlac706":
                raise ValueError(
                    f"{path}: {name!r} is a {device.kind}; a base's wheels are zlac706"
                )
            if name in taken:
                raise ValueError(f"{path}: {name!r} is a wheel of base {taken[name]!r} already")
            taken[name] = base.name
            joint = Joint.of(name, FAMILIES[device.kind].schema.JOINT, device.joint)
            if joint.type != "velocity" or joint.unit != "rad":
                raise ValueError(
                    f"{path}: {name!r} must be a velocity joint in rad (a joint table with "
                    'unit = "rad" and its scale, rad a pulse): the base speaks rad/s'
                )
            problem = wheel_problem(base, side, joint)
            if problem is not None:
                raise ValueError(f"bases[{index}]: {problem}")


def _require_own_device_files(buses: list[SerialBus | CanBus]) -> None:
    """One bus per device file, however it is named, and per SocketCAN channel: two would
    share the line unknowingly, each taking the other's replies for its own devices' (or the
    second never opens a file: the first holds it exclusively)."""
    first: dict[str, tuple[str, str]] = {}  # real path: (bus, the name it gave)
    for index, bus in enumerate(buses):
        if bus.device_key is not None:
            key, name = bus.device_key
            real = os.path.realpath(name)
        elif isinstance(bus, CanBus):  # a socket's channel, no file
            key, name = "channel", f"{bus.interface} channel {bus.channel}"
            real = name
        else:
            continue
        if real not in first:
            first[real] = (bus.name, name)
            continue
        other_bus, other_name = first[real]
        raise ValueError(
            f"buses[{index}].{key}: buses {other_bus!r} and {bus.name!r} both open "
            f"{_one_file(real, other_name, name)}; give each bus its own {key}"
        )


def _one_file(real: str, first_name: str, name: str) -> str:
    """The file two buses open, as each named it when the names differ."""
    if first_name != name:
        return f"{real} (as {first_name} and {name})"
    return name if name == real else f"{name} (that is {real})"


def _check_bus(path: str, bus: SerialBus | CanBus) -> None:
    kinds_here = {device.kind for device in bus.devices}
    allowed = [kind for kind in kinds() if protocol_of(kind, bus.transport)]
    for index, device in enumerate(bus.devices):
        if device.kind not in allowed:
            raise ValueError(
                f"{path}.devices[{index}].kind: {device.kind} cannot be on a {bus.transport} bus "
                f"(allowed: {', '.join(sorted(allowed))})"
            )
    if len(kinds_here) > 1:
        raise ValueError(f"{path}.devices: one device kind per bus, not {sorted(kinds_here)}")
    protocol = PROTOCOLS[bus.protocol]
    if not protocol.addressed and len(bus.devices) > 1:
        raise ValueError(
            f"{path}.devices: {protocol.name} frames carry no device id, so a port drives one "
            f"device, not several"
        )
    low, high = protocol.device_ids[0], protocol.device_ids[-1]
    ids: set[int] = set()
    for index, device in enumerate(bus.devices):
        if not low <= device.id <= high:
            raise ValueError(f"{path}.devices[{index}].id: {device.id} is outside {low}–{high}")
        if device.id in ids:
            raise ValueError(f"{path}.devices[{index}].id: id {device.id} is used twice on the bus")
        ids.add(device.id)
        if device.joint is not None:
            declaration = FAMILIES[device.kind].schema.JOINT
            for key, problem in table_problems(declaration, device.joint):
                raise ValueError(f"{path}.devices[{index}].joint.{key}: {problem}")
    if isinstance(bus, CanBus):
        for key in sorted(bus.options.arguments().keys() & OWN_CAN_KEYS.keys()):
            raise ValueError(
                f"{path}.options.{key}: set by the bus's own {OWN_CAN_KEYS[key]} key, not in "
                f"options (they pass on to python-can what its interface takes besides)"
            )
    rate, rate_key = (
        (bus.baudrate, "baudrate") if isinstance(bus, SerialBus) else (bus.bitrate, "bitrate")
    )
    if protocol.timing.rates and rate not in protocol.timing.rates:
        rates = ", ".join(str(r) for r in protocol.timing.rates)
        raise ValueError(f"{path}.{rate_key}: {protocol.name} runs at {rates} only, not {rate}")
    if isinstance(bus, SerialBus) and bus.gap_s < protocol.timing.min_gap_s:
        minimum = protocol.timing.min_gap_s * 1000
        raise ValueError(f"{path}.min_gap_ms: {protocol.name} needs at least {minimum:g} ms")


def ignored_keys(config: Config) -> list[str]:
    """A line for each key that is taken but ignored, by its path: of the joint tables
    (``table_warnings``), and a device's ``heartbeat_ms`` on a bus other than CAN (only a
    device on CAN sends heartbeats: its driver is given none). ``busgate run`` and
    ``check-config`` warn of them."""
    return [
        *(
            f"buses[{b}].devices[{d}].joint.{key}: {device.name}: {why}"
            for b, bus in enumerate(config.buses)
            for d, device in enumerate(bus.devices)
            if device.joint is not None
            for key, why in table_warnings(FAMILIES[device.kind].schema.JOINT, device.joint)
        ),
        *(
            f"buses[{b}].devices[{d}].heartbeat_ms: {device.name}: {device.heartbeat_ms} ms is "
            f"ignored: only a device on a CAN bus sends heartbeats, and this one is on a "
            f"{bus.transport} bus"
            for b, bus in enumerate(config.buses)
            if not PROTOCOLS[bus.protocol].can
            for d, device in enumerate(bus.devices)
            if device.heartbeat_ms
        ),
    ]


def parse_config(data: dict[str, Any]) -> Config:
    """Validate a parsed TOML document; raise ``ConfigError`` naming every offending key path
    (one per line; ``path`` holds the first)."""
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        problems = [_describe(error) for error in _told_once(exc.errors(include_url=False))]
        raise ConfigError("\n".join(text for _, text in problems), path=problems[0][0]) from exc


def _told_once(errors: list[Any]) -> list[Any]:
    """``errors`` without the missing keys that an unknown key of their table misspells."""
    misspelt = {
        (*error["loc"][:-1], closest(str(error["loc"][-1]), _keys_at(error["loc"][:-1])))
        for error in errors
        if error["type"] == "extra_forbidden"
    }
    return [e for e in errors if not (e["type"] == "missing" and e["loc"] in misspelt)]


def _describe(error: Any) -> tuple[str, str]:
    """(key path, one line) for a pydantic error; our own checks put the path in the message."""
    if error["type"] == "extra_forbidden":
        return _unknown_key(error["loc"])
    message = message_of(error)
    path = _key_path(error["loc"])
    if error["type"] == "union_tag_not_found":  # pydantic's words name no key a user wrote
        key = error["ctx"]["discriminator"].strip("'")
        message = f"`{key}` is missing: {' or '.join(_TAGS.get(key, ()))} (which kind of table)"
    if error["type"] == "string_pattern_mismatch" and (
        form := PATTERN_FORMS.get(error["ctx"]["pattern"])
    ):
        message = f"must be {form}, not {cut(repr(error['input']), SHOWN_OP_CHARS)}"
    if error["type"] == "union_tag_invalid":  # the key's value, as the user wrote it
        key = error["ctx"]["discriminator"].strip("'")
        path = f"{path}.{key}" if path else key
        tag = cut(repr(error["ctx"]["tag"]), SHOWN_OP_CHARS)
        message = f"must be {' or '.join(_TAGS.get(key, ()))}, not {tag}"
    if not path:
        return message.split(":", 1)[0], message
    return path, f"{path}: {message}"


def _unknown_key(loc: tuple[int | str, ...]) -> tuple[str, str]:
    """(key path, one line) for a key its table does not take: ``buses[0]: unknown key
    `baudrat` (did you mean `baudrate`?)``, or the table's keys when none is close and they
    are few."""
    table, key = _key_path(loc[:-1]), str(loc[-1])
    line = f"unknown key `{key}`{suggestion(key, _keys_at(loc[:-1]), listed=LISTED_KEYS)}"
    return _key_path(loc), f"{table}: {line}" if table else line


def _keys_at(loc: tuple[int | str, ...]) -> list[str]:
    """The keys of the table at pydantic location ``loc`` (``('buses', 0, 'serial')``: a
    serial bus's), read from the models: a key leads to its value's tables (a list's items, a
    union's members), a union's tag to the member it names."""
    tables: list[type[BaseModel]] = [Config]
    for part in loc:
        if isinstance(part, str):
            tables = [inner for table in tables for inner in _tables_under(table, part)]
    return [key for table in tables for key in table.model_fields]


def _tables_under(table: type[BaseModel], part: str) -> list[type[BaseModel]]:
    """Where ``part`` of a location leads from ``table``: its key's tables, or ``table`` itself
    when ``part`` is its tag (a field that is ``Literal[part]``, as ``transport``)."""
    if part in table.model_fields:
        return _tables_in(table.model_fields[part].annotation)
    tagged = any(get_args(field.annotation) == (part,) for field in table.model_fields.values())
    return [table] if tagged else []


def _tables_in(annotation: Any) -> list[type[BaseModel]]:
    """The models in a field's type (``list[DeviceConfig]``, ``SerialBus | CanBus`` …)."""
    if isinstance(annotation, type):
        return [annotation] if issubclass(annotation, BaseModel) else []
    return [table for arg in get_args(annotation) for table in _tables_in(arg)]


def load_config(path: str | Path) -> Config:
    """Read and validate a TOML config file; each line of a refusal names the file
    (``gw.toml: buses[0].baudrate: …``), as a compiler's do: the journal's reader may not know
    which one the unit was given."""
    try:
        text = read_text(path, MAX_CONFIG_BYTES, "a config")
    except FileRefused as exc:
        raise ConfigError(str(exc), path="") from exc
    if not text.strip():
        raise ConfigError(f"{path} is empty: a config names its gateway and buses", path="")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}", path="") from exc
    except RecursionError as exc:
        raise ConfigError(f"{path} is not valid TOML: nested too deeply", path="") from exc
    except ValueError as exc:  # an integer of thousands of digits: Python's own limit
        too_long = f"{path}: a number of thousands of digits: not a config"
        raise ConfigError(too_long, path="") from exc
    try:
        return parse_config(data)
    except ConfigError as exc:
        lines = (f"{path}: {line}" for line in str(exc).splitlines())
        raise ConfigError("\n".join(lines), path=exc.path) from exc.__cause__


def _key_path(loc: tuple[int | str, ...]) -> str:
    """``('buses', 0, 'serial', 'baudrate')`` → ``buses[0].baudrate`` (drops union tags)."""
    path = ""
    for part in loc:
        if isinstance(part, int):
            path += f"[{part}]"
        elif part in _TAGS["transport"] and path.endswith("]"):
            continue
        else:
            path += f".{part}" if path else part
    return path
