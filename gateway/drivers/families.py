"""The gateway's side of the family registry: each protocol's driver loaded, and a family
checked for every part it must have.

The registry (``busgate.schemas.families``) names a family's parts by import path. Here they
are loaded on first use and checked, so that a family missing a part fails with a message
naming the part and where it was looked for, rather than with a ``KeyError`` deep in start-up.
A simulator model is checked where simulators are made (``busgate.gateway.sim.models``).
"""

from __future__ import annotations

import functools
import importlib
from typing import Any

from busgate.gateway.bus.request import LinkTiming
from busgate.gateway.drivers.base import FAMILY_PARTS, Driver
from busgate.schemas.config import DeviceConfig
from busgate.schemas.families import PROTOCOLS, Family, WireProtocol


class FamilyError(Exception):
    """A registered family lacks a part, or a part is not what the registry needs."""


#: What each part must offer, by the names the gateway uses.
CODEC_PARTS = ("encode", "expected_reply", "CommandDecoder", "ReplyDecoder", "readings",
               "TIMING", "DEVICE_IDS", "ADDRESSED")  # fmt: skip
SCHEMA_PARTS = ("Command", "COMMAND_ADAPTER", "FollowTarget", "TELEMETRY_MODEL")
SIMULATOR_PARTS = ("accepts", "handle", "spontaneous", "reboot", "inject_fault")


def load(path: str, part: str, owner: str) -> Any:
    """The object at ``module:name`` (or the module at ``module``), or a ``FamilyError``
    naming ``part`` of ``owner``."""
    module_name, _, name = path.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise FamilyError(f"{owner}: its {part} {path} cannot be imported ({exc})") from exc
    if not name:
        return module
    try:
        return getattr(module, name)
    except AttributeError:
        raise FamilyError(f"{owner}: its {part} {path} does not exist") from None


def require(obj: Any, names: tuple[str, ...], part: str, owner: str) -> None:
    """A ``FamilyError`` naming the first of ``names`` that ``obj`` lacks."""
    missing = [name for name in names if not hasattr(obj, name)]
    if missing:
        raise FamilyError(f"{owner}: its {part} has no {', '.join(missing)}")


@functools.cache
def driver_class(protocol: WireProtocol) -> type[Driver]:
    """The driver class of ``protocol``, checked: a concrete ``Driver`` with every part."""
    owner = f"protocol {protocol.name}"
    cls = load(protocol.driver, "driver", owner)
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise FamilyError(f"{owner}: its driver {protocol.driver} is not a Driver class")
    lacking = sorted(getattr(cls, "__abstractmethods__", ())) + [
        part for part in FAMILY_PARTS if not _defines(cls, part)
    ]
    if lacking:
        raise FamilyError(
            f"{owner}: its driver {protocol.driver} does not define {', '.join(lacking)}"
        )
    return cls


def _defines(cls: type[Driver], name: str) -> bool:
    """Whether ``cls`` or a base below ``Driver`` defines ``name`` (rather than inheriting the
    default, or an abstract declaration of it)."""
    for base in cls.__mro__[: cls.__mro__.index(Driver)]:
        if name in vars(base):
            return not getattr(getattr(cls, name), "__isabstractmethod__", False)
    return False


def check_family(family: Family) -> None:
    """Load every part of ``family`` and check it; ``FamilyError`` names the first missing."""
    owner = f"family {family.kind}"
    schema = load(family.schema_module, "schema module", owner)
    require(schema, SCHEMA_PARTS, f"schema module {family.schema_module}", owner)
    if schema.TELEMETRY_MODEL.model_fields["kind"].annotation.__args__ != (family.kind,):
        raise FamilyError(f"{owner}: its telemetry model's kind is not {family.kind!r}")
    for protocol in family.protocols:
        codec = load(protocol.codec_module, "codec", f"protocol {protocol.name}")
        require(codec, CODEC_PARTS, f"codec {protocol.codec_module}", f"protocol {protocol.name}")
        driver_class(protocol)


def make_driver(device: DeviceConfig, protocol: WireProtocol) -> Driver:
    """The driver of a configured device on a bus of ``protocol``."""
    options: dict[str, Any] = {"follow_period_s": device.follow_period_ms / 1000}
    if protocol.can:
        options["heartbeat_ms"] = device.heartbeat_ms
    return driver_class(protocol)(device.name, device.id, **options)


def link_timing(protocol: str, rate: int, *, margin_s: float, gap_s: float = 0.0) -> LinkTiming:
    """The timing of a bus of ``protocol`` at ``rate`` (baud, or bit/s on CAN)."""
    entry = PROTOCOLS[protocol]
    return LinkTiming(protocol, entry.timing, entry.can, rate, margin_s, gap_s)
