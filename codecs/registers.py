"""Register maps as data: name, address, size, access, unit, scale, valid range, default.

Every protocol describes its control table with ``Register`` rows collected in a
``RegisterMap``; encoders, the JSON schemas and the simulators read ranges from here, so a
range is written down once. ``require_range`` is the one place an out-of-range value becomes
an ``EncodeError``.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

from busgate.codecs.errors import EncodeError


class Access(enum.Enum):
    READ = "r"
    WRITE = "w"
    READ_WRITE = "rw"

    @property
    def writable(self) -> bool:
        return self is not Access.READ

    @property
    def readable(self) -> bool:
        return self is not Access.WRITE


@dataclass(frozen=True, slots=True)
class Register:
    """One entry of a control table.

    ``minimum``/``maximum`` bound the value in the unit of the register as stored (raw), and
    ``scale`` converts raw to ``unit`` (``value_in_unit = raw * scale``). ``size`` is in bytes.
    """

    name: str
    address: int
    size: int
    access: Access
    unit: str = ""
    scale: float = 1.0
    minimum: int | None = None
    maximum: int | None = None
    default: int | None = None
    signed: bool = False
    description: str = ""

    @property
    def end(self) -> int:
        """First address after this register."""
        return self.address + self.size

    def check(self, value: int) -> int:
        """Return ``value`` when it fits this register, else raise ``EncodeError``."""
        if self.signed:
            lo, hi = -(1 << (8 * self.size - 1)), (1 << (8 * self.size - 1)) - 1
        else:
            lo, hi = 0, (1 << (8 * self.size)) - 1
        lo = lo if self.minimum is None else self.minimum
        hi = hi if self.maximum is None else self.maximum
        return require_range(self.name, value, lo, hi)


class RegisterMap:
    """The control table of one protocol, looked up by name or by address."""

    def __init__(self, registers: Iterable[Register]) -> None:
        self._by_name: dict[str, Register] = {}
        self._by_address: dict[int, Register] = {}
        for register in registers:
            if register.name in self._by_name:
                raise ValueError(f"register {register.name!r} defined twice")
            self._by_name[register.name] = register
            for address in range(register.address, register.end):
                if address in self._by_address:
                    raise ValueError(f"address {address:#04x} is in two registers")
                self._by_address[address] = register

    def __getitem__(self, name: str) -> Register:
        return self._by_name[name]

    def __iter__(self) -> Iterator[Register]:
        return iter(sorted(self._by_name.values(), key=lambda r: r.address))

    def __len__(self) -> int:
        return len(self._by_name)

    def at(self, address: int) -> Register | None:
        """The register that holds ``address``, or ``None`` for a reserved address."""
        return self._by_address.get(address)

    def covering(self, address: int, length: int) -> list[Register | None]:
        """For each address of ``[address, address + length)``, its register or ``None``."""
        return [self.at(a) for a in range(address, address + length)]

    def touched(self, address: int, length: int) -> set[str]:
        """The names of the registers a write of ``length`` bytes at ``address`` reaches (an
        address-only write, ``length`` 0, reaches the register at ``address``)."""
        return {r.name for r in self.covering(address, max(length, 1)) if r is not None}


def require_range(field: str, value: int, lo: int, hi: int) -> int:
    """Return ``value`` when ``lo <= value <= hi``, else raise ``EncodeError`` naming ``field``.

    >>> require_range("position", 2001, 0, 2000)
    Traceback (most recent call last):
    ...
    busgate.codecs.errors.EncodeError: position 2001 is out of range [0, 2000]
    """
    if isinstance(value, bool) or not isinstance(value, int):
        raise EncodeError(f"{field} must be an integer, not {value!r}", field=field, value=value)
    if not lo <= value <= hi:
        raise EncodeError(f"{field} {value} is out of range [{lo}, {hi}]", field=field, value=value)
    return value
