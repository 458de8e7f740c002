"""What a simulator received, decoded: the host's frames after a mark, each with its record
(when it started on the wire), and what a frame sets. Shared by the tests that read targets,
ticks and speeds off the wire."""

from __future__ import annotations

from collections.abc import Iterator
from types import ModuleType

from busgate.codecs import ds_servo as ds
from busgate.codecs import inspire_la as la
from busgate.codecs import zlac706_can as zcan
from busgate.codecs.can_frame import CanFrame
from busgate.gateway.sim.recorder import WireRecord


def received(simulator, since: int, codec: ModuleType) -> Iterator[tuple[WireRecord, object]]:
    """Every frame ``simulator`` received after its ``since``-th, decoded by ``codec``."""
    for record in simulator.recorder.received()[since:]:
        decoder = codec.CommandDecoder()
        if "#" in record.wire:  # CAN: id#data
            identifier, data = record.wire.split("#")
            decoder.feed(CanFrame(int(identifier, 16), bytes.fromhex(data)))
        else:
            decoder.feed(bytes.fromhex(record.wire))
        for frame in decoder.events():
            yield record, frame


def tick_targets(frame: object) -> dict[int, int] | None:
    """A follow tick's targets by id (a group follow or SYNC WRITE, or a follow frame without
    reply), else ``None``."""
    if isinstance(frame, la.GroupFollowCommand | ds.SyncWrite):
        return {t.device_id: t.position_raw for t in frame.targets}
    if isinstance(frame, la.FollowCommand) and not frame.reply:
        return {frame.device_id: frame.position_raw}
    return None


def written_speed(frame: object) -> int | None:
    """The raw speed a ZLAC706 CAN write sets, else ``None``."""
    return written(frame, zcan.CanRegister.TARGET_SPEED)


def written(frame: object, register: zcan.CanRegister) -> int | None:
    """The value a ZLAC706 CAN write of ``register`` sets, else ``None``."""
    if isinstance(frame, zcan.Write) and frame.register == register:
        return frame.value
    return None


def no_base(device: str) -> None:
    """``driven_by`` of a gateway with no bases (trajectories on their own): no device is a
    wheel a base drives."""
    return None
