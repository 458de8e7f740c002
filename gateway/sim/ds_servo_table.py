"""The control table of a simulated DS servo: ``TABLE_END`` bytes laid out by the codec's
``REGISTERS`` (big-endian), at the manual's defaults and, where the manual gives none, at what
this model powers up with.

Apart from the servo (``ds_servo.py``), which writes the live values in before a read and
decides what a write sets off: this module only keeps the bytes. Rules of this file:

1. A write stores only the bytes that land in writable registers: bytes for a read-only or
   unknown address, or for an address whose write is an action (the presets), are dropped.
2. A power cycle keeps the saved registers (``SAVED_END``) and puts the rest back at their
   power-up values; a new table is the factory one, id included.
"""

from __future__ import annotations

import builtins
from typing import Final, TypeGuard

from busgate.codecs.ds_servo import ADDRESS_ONLY_WRITES, REGISTERS, TABLE_END
from busgate.codecs.registers import Register

#: Registers the manual gives no initial value ("--"): what this model powers up with. Torque
#: is on, since the manual's own examples move servos without ever writing 0x28. The firmware
#: version is the manual's example v1.28. The target is the shaft's position (set at power-up).
POWER_UP_VALUES: Final = {
    "firmware_version": 0x011C,
    "motor_mode": 0,
    "motor_direction": 0,
    "torque_enable": 1,
    "lock_flag": 0,
    "speed_adjust_16": 0,
}
#: The manual marks 0x03-0x1B saved across power-down, 0x1C-0x1D "?" and nothing from the torque
#: switch on; we keep everything below the torque switch, so a reboot keeps ids and presets.
SAVED_END: Final = REGISTERS["torque_enable"].address


class DsServoTable:
    """One servo's control table, at its factory values."""

    def __init__(self) -> None:
        self._bytes = _factory_bytes()

    def __bytes__(self) -> bytes:
        return bytes(self._bytes)

    def get(self, name: str) -> int:
        register = REGISTERS[name]
        raw = self._bytes[register.address : register.end]
        return int.from_bytes(raw, "big", signed=register.signed)

    def set(self, name: str, value: int) -> None:
        _put(self._bytes, REGISTERS[name], value)

    def read(self, address: int, length: int) -> bytes:
        return bytes(self._bytes[address : address + length])

    def store(self, address: int, data: bytes) -> builtins.set[Register]:
        """Write the bytes that land in writable registers; return the registers written."""
        touched = set()
        for offset, byte in enumerate(data):
            register = REGISTERS.at(address + offset)
            if _takes_data(register):
                self._bytes[address + offset] = byte
                touched.add(register)
        return touched

    def power_cycle(self) -> None:
        """Saved registers stay; the rest are back at their power-up values."""
        self._bytes[SAVED_END:] = _factory_bytes()[SAVED_END:]


def _takes_data(register: Register | None) -> TypeGuard[Register]:
    return (
        register is not None
        and register.access.writable
        and register.address not in ADDRESS_ONLY_WRITES
    )


def _factory_bytes() -> bytearray:
    table = bytearray(TABLE_END)
    for register in REGISTERS:
        value = POWER_UP_VALUES.get(register.name, register.default)
        if value is not None:
            _put(table, register, value)
    return table


def _put(table: bytearray, register: Register, value: int) -> None:
    table[register.address : register.end] = value.to_bytes(
        register.size, "big", signed=register.signed
    )
