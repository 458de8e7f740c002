"""Register maps as data: name, address, size, access, unit, scale, valid range, default.

Every protocol describes its control table with ``Register`` rows collected in a
``RegisterMap``; encoders, the JSON schemas and the simulators read ranges from here, so a
range is written down once. ``require_range`` is the one place an out-of-range value becomes
an ``EncodeError``. ``Register.reading`` is the one place a raw value read off a wire becomes
a named value in the table's unit (``Reading``); each codec's ``readings(reply)`` says which of
its replies carry a register's address and value.
"""

from __future__ import annotations

import enum
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Final

from busgate.codecs.errors import EncodeError

#: Values in a unit are rounded to this many decimals: 202 × 0.1 is 20.200000000000003 in
#: binary, while the finest step of any table (a ZLAC706 torque step, 0.0032 A) needs four.
UNIT_DECIMALS: Final = 9


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
    ``parts`` names the one-byte fields of a value that packs several (a ramp: accel, decel),
    most significant first; then ``unit`` and ``scale`` apply to each part.
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
    parts: tuple[str, ...] = ()

    @property
    def end(self) -> int:
        """First address after this register."""
        return self.address + self.size

    @property
    def limits(self) -> tuple[int, int]:
        """The raw values it takes: ``minimum`` to ``maximum``, or what its size holds where
        the manual gives no bound."""
        if self.signed:
            lo, hi = -(1 << (8 * self.size - 1)), (1 << (8 * self.size - 1)) - 1
        else:
            lo, hi = 0, (1 << (8 * self.size)) - 1
        lo = lo if self.minimum is None else self.minimum
        hi = hi if self.maximum is None else self.maximum
        return lo, hi

    def check(self, value: int) -> int:
        """Return ``value`` when it fits this register, else raise ``EncodeError``."""
        return require_range(self.name, value, *self.limits)

    def in_unit(self, raw: int) -> int | float | dict[str, int | float] | None:
        """``raw`` in this register's unit; for a packed register each part by name, or
        ``None`` when ``raw`` does not fit its parts.

        >>> Register("limit", 98, 2, Access.READ_WRITE, unit="°C", scale=0.1).in_unit(202)
        20.2
        >>> ramp = Register("ramp", 0x12, 1, Access.WRITE, unit="ms", scale=100,
        ...                 parts=("accel", "decel"))
        >>> ramp.in_unit(0x0A0B), ramp.in_unit(0x10000)
        ({'accel': 1000, 'decel': 1100}, None)
        """
        if not self.parts:
            return self._scaled(raw)
        count = len(self.parts)
        if not 0 <= raw < 1 << 8 * count:
            return None
        return {
            part: self._scaled(raw >> 8 * (count - 1 - i) & 0xFF)
            for i, part in enumerate(self.parts)
        }

    def _scaled(self, raw: int) -> int | float:
        return raw if self.scale == 1 else round(raw * self.scale, UNIT_DECIMALS)

    def reading(self, raw: int) -> Reading:
        """``raw``, as a reply carries it, named and in this register's unit. A value the
        decoder has already named by its code (an ``IntEnum`` member) keeps that name.

        >>> Register("limit", 98, 2, Access.READ_WRITE, unit="°C", scale=0.1).reading(600)
        Reading(register='limit', address=98, raw=600, value=60.0, unit='°C')
        """
        value = raw if isinstance(raw, enum.Enum) else self.in_unit(raw)
        return Reading(self.name, int(self.address), int(raw), value, self.unit or None)


@dataclass(frozen=True, slots=True)
class Reading:
    """One register's value as a reply carries it: the register's name and address, the raw
    value, the value in ``unit`` (a number, a code's name, or a packed register's parts) and
    the unit (``None`` where the table states none: the value is then the raw one)."""

    register: str
    address: int
    raw: int
    value: object
    unit: str | None


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

    def default(self, name: str) -> int:
        """The power-up value of register ``name``; ``KeyError`` when the table gives none."""
        default = self[name].default
        if default is None:
            raise KeyError(f"register {name!r} has no default")
        return default

    def at(self, address: int) -> Register | None:
        """The register that holds ``address``, or ``None`` for a reserved address."""
        return self._by_address.get(address)

    def reading_at(self, address: int, raw: int) -> list[Reading]:
        """A one-value reply's reading: ``[reading]`` of the register that starts at
        ``address``, or ``[]`` when none does (the raw value then stands alone)."""
        register = self.at(address)
        return [] if register is None or register.address != address else [register.reading(raw)]

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
