"""What a simulated device is to the servers that carry its frames.

A device model takes decoded command frames and returns reply frames; the server owns the
transport, the wire timing and the faults. Models never sleep and never read a clock: the
server passes ``now`` (``perf_counter`` seconds), so the models are tested with a fake clock.
"""

from __future__ import annotations

from typing import Protocol


class SimDevice(Protocol):
    """A simulated device on a shared bus."""

    #: The id the device answers to now (an Inspire LA's id change takes effect at once).
    device_id: int
    #: Least and greatest time from the end of a command to the start of its reply, seconds.
    turnaround_s: tuple[float, float]

    def accepts(self, command: object) -> bool:
        """True when ``command`` is addressed to this device (its id, or broadcast)."""

    def handle(self, command: object, now: float) -> list[object]:
        """Carry out ``command``; return the reply frames to send (none for broadcast)."""

    def spontaneous(self, now: float) -> list[object]:
        """Frames the device sends unasked by ``now`` (heartbeats, alarm reports)."""

    def reboot(self, now: float) -> None:
        """Power-cycle: registers back to defaults, motion stopped."""

    def inject_fault(self, fault: str, now: float) -> None:
        """Raise a device fault by name (``over_current``, ``stall``, ``over_temperature``,
        ``encoder``, ``under_voltage``, as far as the device has it)."""
