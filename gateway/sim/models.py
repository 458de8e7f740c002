"""Which device model serves which protocol (the registry's ``simulator``), and how a set of
them is made.

Model classes take ``(device_id, **options)``; options a model does not know are refused, so a
typo on the command line is an error rather than a silently ignored flag.
"""

from __future__ import annotations

from collections.abc import Iterable

from busgate.gateway.drivers.families import SIMULATOR_PARTS, load, require
from busgate.gateway.sim.device import SimDevice
from busgate.schemas.families import PROTOCOLS


def model_class(protocol: str) -> type:
    """The simulator model of ``protocol``, checked for what the servers call (a
    ``FamilyError`` names what it lacks)."""
    entry = PROTOCOLS[protocol]
    owner = f"protocol {protocol}"
    cls = load(entry.simulator, "simulator", owner)
    require(cls, SIMULATOR_PARTS, f"simulator {entry.simulator}", owner)
    return cls


def make_devices(protocol: str, ids: Iterable[int], **options: object) -> list[SimDevice]:
    """One simulated device per id, all of ``protocol``'s model."""
    cls = model_class(protocol)
    return [cls(device_id, **options) for device_id in ids]
