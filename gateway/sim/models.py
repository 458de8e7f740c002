"""Which device model serves which protocol, and how a set of them is made.

Model classes take ``(device_id, **options)``; options a model does not know are refused, so a
typo on the command line is an error rather than a silently ignored flag.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable

from busgate.gateway.sim.device import SimDevice

MODELS: dict[str, str] = {
    "inspire_la": "busgate.gateway.sim.inspire_la:InspireLaDevice",
    "ds_servo": "busgate.gateway.sim.ds_servo:DsServoDevice",
    "zlac706_can": "busgate.gateway.sim.zlac706:Zlac706CanDevice",
    "zlac706_rs232": "busgate.gateway.sim.zlac706:Zlac706Rs232Device",
}


def model_class(protocol: str) -> type:
    module, _, name = MODELS[protocol].partition(":")
    return getattr(importlib.import_module(module), name)


def make_devices(protocol: str, ids: Iterable[int], **options: object) -> list[SimDevice]:
    """One simulated device per id, all of ``protocol``'s model."""
    cls = model_class(protocol)
    return [cls(device_id, **options) for device_id in ids]
