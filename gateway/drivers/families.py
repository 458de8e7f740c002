"""The gateway's side of the family registry: what drives each protocol, and a family checked
for every part it must have.

Rules of this file:

1. ``DRIVERS`` is the one table of drivers: a row per protocol of the registry
   (``busgate.schemas.families``), the class itself beside the driver modules (python-can's
   ``BACKENDS`` style), and each class names its protocol (``Driver.protocol``). A family's
   simulator model is registered the same way beside the simulators
   (``busgate.gateway.sim.models.MODELS``).
2. A family missing a part fails with a ``FamilyError`` naming the part, rather than with a
   ``KeyError`` deep in start-up.
"""

from __future__ import annotations

from typing import Any

from busgate.errors import FamilyError
from busgate.gateway.bus.request import LinkTiming
from busgate.gateway.drivers.base import FAMILY_PARTS, Driver
from busgate.gateway.drivers.ds_servo import DsServoDriver
from busgate.gateway.drivers.inspire_la import InspireLaDriver
from busgate.gateway.drivers.zlac706_can import Zlac706CanDriver
from busgate.gateway.drivers.zlac706_rs232 import Zlac706Rs232Driver
from busgate.schemas.config import DeviceConfig
from busgate.schemas.families import PROTOCOLS, Family, WireProtocol
from busgate.schemas.joints import Joint

#: What each part must offer, by the names the gateway uses.
CODEC_PARTS = ("encode", "expected_reply", "CommandDecoder", "ReplyDecoder", "readings",
               "TIMING", "DEVICE_IDS", "ADDRESSED")  # fmt: skip
SCHEMA_PARTS = ("Command", "COMMAND_ADAPTER", "FollowTarget", "TELEMETRY_MODEL", "JOINT")
SIMULATOR_PARTS = ("accepts", "handle", "spontaneous", "reboot", "inject_fault")


#: Each protocol's driver class (rule 1).
DRIVERS: dict[str, type[Driver]] = {
    cls.protocol: cls
    for cls in (InspireLaDriver, DsServoDriver, Zlac706CanDriver, Zlac706Rs232Driver)
}


def require(obj: Any, names: tuple[str, ...], part: str, owner: str) -> None:
    """A ``FamilyError`` naming the first of ``names`` that ``obj`` lacks."""
    missing = [name for name in names if not hasattr(obj, name)]
    if missing:
        raise FamilyError(f"{owner}: its {part} has no {', '.join(missing)}")


def driver_class(protocol: WireProtocol) -> type[Driver]:
    """The driver class of ``protocol``, checked: a concrete ``Driver`` of that protocol with
    every part (rule 2)."""
    owner = f"protocol {protocol.name}"
    cls = DRIVERS.get(protocol.name)
    if cls is None:
        raise FamilyError(f"{owner}: no driver is registered for it (DRIVERS)")
    name = cls.__qualname__
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise FamilyError(f"{owner}: its driver {name} is not a Driver class")
    if getattr(cls, "protocol", None) != protocol.name:
        raise FamilyError(f"{owner}: its driver {name} names another protocol")
    lacking = sorted(getattr(cls, "__abstractmethods__", ())) + [
        part for part in FAMILY_PARTS if not _defines(cls, part)
    ]
    if lacking:
        raise FamilyError(f"{owner}: its driver {name} does not define {', '.join(lacking)}")
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
    try:
        schema = family.schema
    except ImportError as exc:
        raise FamilyError(f"{owner}: its schema module cannot be imported ({exc})") from exc
    require(schema, SCHEMA_PARTS, f"schema module {schema.__name__}", owner)
    if schema.TELEMETRY_MODEL.model_fields["kind"].annotation.__args__ != (family.kind,):
        raise FamilyError(f"{owner}: its telemetry model's kind is not {family.kind!r}")
    for protocol in family.protocols:
        codec = protocol.codec
        require(codec, CODEC_PARTS, f"codec {codec.__name__}", f"protocol {protocol.name}")
        driver_class(protocol)


def make_driver(device: DeviceConfig, protocol: WireProtocol) -> Driver:
    """The driver of a configured device on a bus of ``protocol``."""
    cls = driver_class(protocol)
    options: dict[str, Any] = {
        "follow_period_s": device.follow_period_ms / 1000,
        "joint": Joint.of(device.name, cls.joint_declaration(), device.joint),
    }
    if protocol.can:
        options["heartbeat_ms"] = device.heartbeat_ms
    return cls(device.name, device.id, **options)


def link_timing(protocol: str, rate: int, *, margin_s: float, gap_s: float = 0.0) -> LinkTiming:
    """The timing of a bus of ``protocol`` at ``rate`` (baud, or bit/s on CAN)."""
    entry = PROTOCOLS[protocol]
    return LinkTiming(protocol, entry.timing, entry.can, rate, margin_s, gap_s)
