"""The SDK's blocking face: ``connect`` → ``Client`` → ``Device``, ``Bus`` and ``Base``.

Its methods are the ones both faces share (``surface.py``, ``devices.py``, ``trajectories.py``,
``bases.py``), each run waiting (``faces.Blocking``): it waits for each future with a timeout,
and every wait names what it waited for when nobody answers. What is this face's own: its
classes, and the ``with`` blocks of a claim, a follow stream, a base's drive stream, a
trajectory and a client. Safe to use from several threads at once (the core is; a ``Follow``
or ``DriveStream`` belongs to the thread that opened it).
"""

from __future__ import annotations

from typing import Self

from busgate.client.bases import DriveStreamBase, MobileBase
from busgate.client.core import DEFAULT_TIMEOUT_S
from busgate.client.devices import BusBase, ClaimBase, DeviceBase, FollowBase, StreamBase
from busgate.client.faces import Blocking, opener
from busgate.client.joints import JointBase, JointFollowBase
from busgate.client.steps import run
from busgate.client.surface import ClientBase, connecting
from busgate.client.trajectories import Handle

__all__ = [
    "DEFAULT_TIMEOUT_S",
    "Base",
    "Bus",
    "Claim",
    "Client",
    "Device",
    "DriveStream",
    "Follow",
    "Joint",
    "JointFollow",
    "Trajectory",
    "connect",
]


class Claim(Blocking, ClaimBase):
    """A claim held by a ``with`` block (``Device.claim``, ``Base.claim``)."""

    def __enter__(self) -> Claim:
        return run(self._taken())

    def __exit__(self, kind: type[BaseException] | None, *exc_info: object) -> None:
        run(self._given_back(kind))


class _Stream(Blocking, StreamBase):
    """A follow stream's ``with`` block: opened on entry, ended on exit."""

    def __enter__(self) -> Self:
        return self._opened()

    def __exit__(self, kind: type[BaseException] | None, *exc_info: object) -> None:
        run(self._ended(kind))


class Follow(_Stream, FollowBase):
    """A follow stream held by a ``with`` block (``Device.follow``)."""


class JointFollow(_Stream, JointFollowBase):
    """A joint's follow stream held by a ``with`` block (``Joint.follow``): targets in SI."""


class Joint(Blocking, JointBase["Device", JointFollow]):
    """One device as a joint, in SI units (``Device.joint``)."""

    _JointFollow = JointFollow


class Device(Blocking, DeviceBase[Claim, Follow, Joint]):
    """One device of one gateway."""

    _Claim, _Follow, _Joint = Claim, Follow, Joint


class Bus(Blocking, BusBase):
    """One bus of one gateway: its group moves and scans."""


class Trajectory(Blocking, Handle):
    """A trajectory a gateway plays for this client (``Client.play``): its ``id``,
    ``gateway``, ``devices``, ``start_at`` and ``end_at`` (wall clock, as telemetry's ``ts``)."""

    def __enter__(self) -> Trajectory:
        return self

    def __exit__(self, exc_type: object, *exc_info: object) -> None:
        self._left(failed=exc_type is not None)


class DriveStream(_Stream, DriveStreamBase):
    """A base's twist stream held by a ``with`` block (``Base.drive_stream``): ``send(linear,
    angular)`` puts a twist; the base is stopped when the block exits."""


class Base(Blocking, MobileBase[Claim, DriveStream]):
    """One base of one gateway: two ZLAC706 wheels driven as one differential drive."""

    _Claim, _DriveStream = Claim, DriveStream


class Client(Blocking, ClientBase[Device, Bus, Trajectory, Joint, Base]):
    """One program's connection to a fleet of gateways."""

    _Device, _Bus, _Trajectory, _Base = Device, Bus, Trajectory, Base

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


connect = opener(connecting, Client)
