"""The control table of a simulated Inspire LA actuator: its RAM, and the "flash" that ``save``
writes and a power cycle reads back.

Apart from the actuator (``inspire_la.py``), which decides what a write sets off and supplies
the live registers' values: this module only keeps the bytes and judges writes. Rules of this
file (rule 2 of ``inspire_la.py``):

1. The table is bytes laid out by the codec's ``REGISTERS``, at the manual's defaults (3.6).
2. A write is judged by the codec's rules (``check_write``, each register's range,
   ``check_temperature_limits``) on the whole registers it leaves behind; a refused write
   leaves the table alone and raises nothing.
3. Live registers (position, force) are filled in as a read takes place, never stored.
"""

from __future__ import annotations

from collections.abc import Mapping

from busgate.codecs.errors import EncodeError
from busgate.codecs.inspire_la import (
    ID,
    OVERTEMP_LIMIT,
    REGISTERS,
    REWARM_TEMPERATURE,
    TABLE_SIZE,
    check_temperature_limits,
    check_write,
)
from busgate.codecs.registers import Register

#: Table addresses 0–1 read AA 55 ("table header", manual 3.6).
TABLE_HEADER = b"\xaa\x55"


class InspireLaTable:
    """One actuator's control table, RAM and flash, as it leaves the factory with ``device_id``."""

    def __init__(self, device_id: int) -> None:
        self._flash = _factory_table(device_id)
        self.power_up()

    def power_up(self) -> None:
        """The RAM is read back from flash."""
        self._ram = bytearray(self._flash)

    def save(self) -> None:
        """The RAM is written to flash."""
        self._flash = bytes(self._ram)

    def get(self, name: str) -> int:
        return _get(self._ram, REGISTERS[name])

    def put(self, name: str, value: int) -> None:
        _put(self._ram, REGISTERS[name], value)

    def read(self, index: int, length: int, live: Mapping[str, int]) -> bytes:
        """``length`` bytes from ``index`` of the RAM, with the ``live`` registers filled in."""
        table = bytearray(self._ram)
        for name, value in live.items():
            _put(table, REGISTERS[name], value)
        return bytes(table[index : index + length])

    def write(self, index: int, data: bytes) -> set[str]:
        """Store the write when the manual's rules allow it; return the registers it touched.

        Manual silent on refused writes: the table is left alone and the reply is the usual
        status frame, which carries no error field. A write of part of a register is judged
        by the whole register it leaves behind.
        """
        try:
            check_write(index, data)
            touched = {r for r in REGISTERS.covering(index, len(data)) if r}
            table = bytearray(self._ram)
            table[index : index + len(data)] = data
            for register in touched:
                register.check(_get(table, register))
            check_temperature_limits(
                _get(table, REGISTERS[OVERTEMP_LIMIT]), _get(table, REGISTERS[REWARM_TEMPERATURE])
            )
        except EncodeError:
            return set()
        self._ram = table
        return {register.name for register in touched}


def _factory_table(device_id: int) -> bytes:
    """The manual's defaults (3.6), with the id this actuator was given."""
    table = bytearray(TABLE_SIZE)
    table[0:2] = TABLE_HEADER
    for register in REGISTERS:
        if register.default is not None:
            _put(table, register, register.default)
    _put(table, REGISTERS[ID], REGISTERS[ID].check(device_id))
    return bytes(table)


def _get(table: bytes | bytearray, register: Register) -> int:
    raw = table[register.address : register.end]
    return int.from_bytes(raw, "little", signed=register.signed)


def _put(table: bytearray, register: Register, value: int) -> None:
    table[register.address : register.end] = value.to_bytes(
        register.size, "little", signed=register.signed
    )
