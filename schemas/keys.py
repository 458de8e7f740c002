"""The key expressions of busgate's API: the one place they are spelt, for the gateway that
declares them and the clients that address them; docs/api.md lists the same keys.

>>> keys = Keys("busgate")
>>> keys.device("gw1", "la1", "cmd"), keys.bus("*", "uart0", "cmd"), keys.estop("*")
('busgate/gw1/dev/la1/cmd', 'busgate/*/bus/uart0/cmd', 'busgate/*/estop')
>>> keys.estop_reset("gw1"), keys.base("gw1", "base", "twist")
('busgate/gw1/estop/reset', 'busgate/gw1/base/base/twist')
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from busgate.errors import CommandError
from busgate.schemas.base import (
    CLIENT_ID_PATTERN,
    CLIENTS_ROOM,
    KEY_PREFIX_FORM,
    KEY_PREFIX_PATTERN,
)

#: A gateway, device or bus name as the config allows it: one chunk of a key, no wildcard
#: (the config's ``Name`` and a client id are the same pattern).
_NAME = re.compile(CLIENT_ID_PATTERN)


@dataclass(frozen=True)
class Keys:
    """Every key of the API under one prefix."""

    prefix: str = "busgate"

    def __post_init__(self) -> None:
        """A prefix is a gateway's ``[gateway] prefix``: a wildcard in it (``*``) would
        address keys of other prefixes than meant, and names nothing to take apart."""
        if not isinstance(self.prefix, str) or not re.fullmatch(KEY_PREFIX_PATTERN, self.prefix):
            raise CommandError(
                f"not a key prefix: {str(self.prefix)[:80]!r} ({KEY_PREFIX_FORM}, as a "
                "gateway's [gateway] prefix)"
            )

    def room(self, gateway: str, room: str, name: str, leaf: str) -> str:
        """A key of one device (room ``dev``), bus (``bus``) or base (``base``)."""
        return f"{self.prefix}/{gateway}/{room}/{name}/{leaf}"

    def device(self, gateway: str, device: str, leaf: str) -> str:
        """``cmd``, ``follow``, ``state``, ``event`` or ``alive`` of a device."""
        return self.room(gateway, "dev", device, leaf)

    def bus(self, gateway: str, bus: str, leaf: str) -> str:
        """``cmd`` or ``stats`` of a bus."""
        return self.room(gateway, "bus", bus, leaf)

    def base(self, gateway: str, base: str, leaf: str) -> str:
        """``cmd``, ``twist`` or ``odom`` of a base (``[[bases]]``: two wheels as one drive)."""
        return self.room(gateway, "base", base, leaf)

    def info(self, gateway: str) -> str:
        return f"{self.prefix}/{gateway}/info"

    def estop(self, gateway: str) -> str:
        return f"{self.prefix}/{gateway}/estop"

    def estop_reset(self, gateway: str) -> str:
        """Where a gateway takes the reset of its e-stop."""
        return f"{self.prefix}/{gateway}/estop/reset"

    def events(self, gateway: str) -> str:
        return f"{self.prefix}/{gateway}/events"

    def joints(self, gateway: str) -> str:
        """Every joint of a gateway, in SI, each time one was read again."""
        return f"{self.prefix}/{gateway}/joints"

    def trajectory(self, gateway: str) -> str:
        """The queryable a gateway plays trajectories on."""
        return f"{self.prefix}/{gateway}/trajectory"

    def feedback(self, gateway: str, trajectory_id: str) -> str:
        """A trajectory's feedback, then its result."""
        return f"{self.prefix}/{gateway}/trajectory/{trajectory_id}/feedback"

    def alive(self, gateway: str) -> str:
        """The liveliness token a gateway holds while it serves."""
        return f"{self.prefix}/{gateway}/alive"

    def client(self, client_id: str) -> str:
        """The liveliness token a client holds: its claims and streams last as long as it."""
        return f"{self.prefix}/{CLIENTS_ROOM}/{client_id}"

    def gateway_of(self, key: str) -> str:
        """The gateway chunk of a key under this prefix."""
        return key[len(self.prefix) + 1 :].split("/", 1)[0]

    def gateway_in(self, key: str, leaf: str) -> str | None:
        """The gateway of a key ``<prefix>/<gateway>/<leaf>`` when it is a name; ``None`` for
        a key of any other shape, with a wildcard for the gateway, or in the clients' room
        (a client named ``alive`` is no gateway ``clients``).

        >>> Keys().gateway_in("busgate/gw1/events", "events"), Keys().gateway_in(
        ...     "busgate/**/events", "events"), Keys().gateway_in("busgate/clients/alive", "alive")
        ('gw1', None, None)
        """
        gateway, slash, found = key.removeprefix(f"{self.prefix}/").partition("/")
        if not (key.startswith(f"{self.prefix}/") and slash and found == leaf):
            return None
        return gateway if is_name(gateway) and gateway != CLIENTS_ROOM else None

    def names_in(self, key: str, room: str, leaf: str) -> tuple[str, str] | None:
        """``(gateway, name)`` of a key ``<prefix>/<gateway>/<room>/<name>/<leaf>`` whose
        gateway and name are names; ``None`` for a key of any other shape, or with a wildcard
        where a name goes (a put on ``busgate/**/state`` reaches every subscriber of states).

        >>> keys = Keys("busgate")
        >>> keys.names_in("busgate/gw1/dev/la1/state", "dev", "state")
        ('gw1', 'la1')
        >>> keys.names_in("busgate/**/state", "dev", "state"), keys.names_in(
        ...     "busgate/*/dev/la1/state", "dev", "state")
        (None, None)
        """
        if not key.startswith(f"{self.prefix}/"):
            return None
        chunks = key[len(self.prefix) + 1 :].split("/")
        if len(chunks) != 4 or chunks[1] != room or chunks[3] != leaf:
            return None
        gateway, name = chunks[0], chunks[2]
        return (gateway, name) if is_name(gateway) and is_name(name) else None


def is_name(name: object) -> bool:
    """Whether ``name`` is one chunk of a key as the config allows names (``check_name``)."""
    return isinstance(name, str) and _NAME.fullmatch(name) is not None
