"""Fault injection shared by every simulator: what happens to a reply on its way out.

Each fault is a rate (0–1) or a set of ids, settable from the command line at start or in
process at any time (``FaultInjector.configure``). Decisions draw from a seeded RNG so a run
can be repeated. Device faults (over-current, stall, …), reboots and unplugs are not here:
they belong to the device models and the link.
"""

from __future__ import annotations

import random
import threading
from dataclasses import dataclass, field, replace


@dataclass(frozen=True)
class FaultConfig:
    """What to do to replies: drop, delay past the host's timeout, corrupt, precede by noise."""

    drop_rate: float = 0.0
    late_rate: float = 0.0
    late_s: float = 0.1
    bad_checksum_rate: float = 0.0
    garbage_rate: float = 0.0
    silent_ids: frozenset[int] = field(default_factory=frozenset)

    def __post_init__(self) -> None:
        for name in ("drop_rate", "late_rate", "bad_checksum_rate", "garbage_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be between 0 and 1")
        if self.late_s < 0:
            raise ValueError("late_s must not be negative")


@dataclass(frozen=True, slots=True)
class ShapedReply:
    """A reply after fault injection: the bytes to send (``None``: nothing) and extra delay."""

    wire: bytes | None
    delay_s: float = 0.0


class FaultInjector:
    """Applies a ``FaultConfig`` to replies; ``configure`` changes it while a simulator runs."""

    def __init__(self, config: FaultConfig | None = None, *, seed: int = 0) -> None:
        self._config = config or FaultConfig()
        self._random = random.Random(seed)
        self._lock = threading.Lock()

    @property
    def config(self) -> FaultConfig:
        return self._config

    def configure(self, **changes: object) -> None:
        """Change some settings, e.g. ``configure(drop_rate=0.1, silent_ids=frozenset({3}))``."""
        with self._lock:
            self._config = replace(self._config, **changes)  # type: ignore[arg-type]

    def shape(
        self, wire: bytes, *, checksummed: bool = True, config: FaultConfig | None = None
    ) -> ShapedReply:
        """Decide the fate of one reply's bytes by ``config`` (by default the present one; a
        server passes the one of the moment the command came in). ``checksummed=False`` (CAN)
        skips corruption."""
        config, chance = config or self._config, self._random.random
        if chance() < config.drop_rate:
            return ShapedReply(None)
        if checksummed and chance() < config.bad_checksum_rate:
            wire = wire[:-1] + bytes([wire[-1] ^ 0xFF])
        if checksummed and chance() < config.garbage_rate:
            wire = self._random.randbytes(self._random.randint(1, 8)) + wire
        delay = config.late_s if chance() < config.late_rate else 0.0
        return ShapedReply(wire, delay)
