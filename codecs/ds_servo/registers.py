"""The DS servo control table (manual chapter 3) as data, and the rules for reading and writing it.

Every address, size, access, unit, default and range the manual gives is written here once;
the encoder, the JSON schema and the simulator read them from ``REGISTERS``. Where the manual
gives no range ("valid range: ?") the register keeps the full range of its type: we do
not invent limits. Values are big-endian, as the whole protocol.

Rules for WRITE (``check_write``): a write covers whole, writable, known registers, each value
in its range; the addresses that act on the address alone (store / go to preset) take no data
and stand alone.
"""

from __future__ import annotations

from typing import Final

from busgate.codecs.errors import EncodeError
from busgate.codecs.registers import Access, Reading, Register, RegisterMap, require_range

R, W, RW = Access.READ, Access.WRITE, Access.READ_WRITE

REGISTERS: Final = RegisterMap(
    [
        Register(
            "firmware_version",
            0x03,
            2,
            R,
            description="vA.B: high byte A, low byte B (v1.28 = 0x011C)",
        ),
        Register(
            "servo_id",
            0x05,
            1,
            RW,
            minimum=1,
            maximum=250,
            default=1,
            description="254 is the broadcast id, never a servo's own",
        ),
        Register(
            "stall_protection_time",
            0x06,
            1,
            RW,
            unit="s",
            default=3,
            description="the servo protects itself after stalling this long",
        ),
        Register("min_angle", 0x09, 2, RW, default=0, description="lower position limit"),
        Register("max_angle", 0x0B, 2, RW, default=4095, description="upper position limit"),
        Register("max_torque", 0x10, 2, RW, default=800),
        Register("speed_adjust", 0x12, 1, RW, default=30),
        Register("unload_condition", 0x13, 1, RW, default=0),
        Register(
            "centre_offset",
            0x14,
            2,
            RW,
            signed=True,
            default=0,
            description="positive moves the centre towards 4095, negative towards 0",
        ),
        Register(
            "preset_1",
            0x16,
            2,
            RW,
            default=2048,
            description="write the address alone: stores the present position",
        ),
        Register(
            "preset_2",
            0x18,
            2,
            RW,
            default=2048,
            description="write the address alone: stores the present position",
        ),
        Register(
            "preset_3",
            0x1A,
            2,
            RW,
            default=2048,
            description="write the address alone: stores the present position",
        ),
        Register("motor_mode", 0x1C, 1, RW),
        Register("motor_direction", 0x1D, 1, RW),
        Register("torque_enable", 0x28, 1, RW, description="0 torque off, non-zero on"),
        Register("target_position", 0x2A, 2, RW, minimum=0, maximum=4095),
        Register(
            "move_time",
            0x2C,
            2,
            RW,
            unit="ms",
            default=0,
            description="0 moves at the fastest speed",
        ),
        Register("current", 0x2E, 2, R, unit="mA"),
        # The manual names it "lock flag (e-stop)" and documents no value: see schemas.ds_servo.
        Register("lock_flag", 0x30, 1, RW, description="lock / e-stop flag; values undocumented"),
        Register("present_position", 0x38, 2, R, minimum=0, maximum=4095),
        Register("speed", 0x3A, 2, R, description="unit undocumented"),
        Register("goto_preset_1", 0x3C, 1, W, description="write the address alone"),
        Register("goto_preset_2", 0x3D, 1, W, description="write the address alone"),
        Register("goto_preset_3", 0x3E, 1, W, description="write the address alone"),
        Register("temperature", 0x3F, 1, R, unit="°C"),
        Register("reg_write_pending", 0x40, 1, R, description="a REG WRITE awaits ACTION"),
        Register("speed_adjust_16", 0x41, 2, RW),
    ]
)

#: First address past the control table; reads stay below it.
TABLE_END: Final = max(register.end for register in REGISTERS)

#: Store preset n at PRESET_ADDRESSES[n - 1], go to it at GOTO_PRESET_ADDRESSES[n - 1].
PRESET_ADDRESSES: Final = tuple(REGISTERS[f"preset_{n}"].address for n in (1, 2, 3))
GOTO_PRESET_ADDRESSES: Final = tuple(REGISTERS[f"goto_preset_{n}"].address for n in (1, 2, 3))

#: Writing these addresses with no data is the command itself.
ADDRESS_ONLY_WRITES: Final = frozenset(PRESET_ADDRESSES + GOTO_PRESET_ADDRESSES)


def check_read(address: int, length: int) -> None:
    """Raise ``EncodeError`` unless ``[address, address + length)`` lies in the control table.

    >>> check_read(0x38, 2)
    >>> check_read(0x42, 2)
    Traceback (most recent call last):
    ...
    busgate.codecs.errors.EncodeError: length 2 is out of range [1, 1]
    """
    require_range("address", address, 0, TABLE_END - 1)
    require_range("length", length, 1, TABLE_END - address)


def check_write(address: int, data: bytes) -> None:
    """Raise ``EncodeError`` unless writing ``data`` at ``address`` is a write the table allows.

    >>> check_write(0x2A, bytes.fromhex("080003e8"))   # position 2048, 1000 ms
    >>> check_write(0x38, bytes.fromhex("07ff"))
    Traceback (most recent call last):
    ...
    busgate.codecs.errors.EncodeError: present_position (0x38) is read only
    """
    require_range("address", address, 0, 0xFF)
    if address in ADDRESS_ONLY_WRITES:
        if data:
            name = _known(address).name
            raise EncodeError(
                f"{name} is written with its address alone, without data",
                field="data",
                value=data.hex(),
            )
        return
    if not data:
        raise EncodeError(f"a write to {address:#04x} needs data", field="data", value="")
    for register, raw in _split(address, data):
        if not register.access.writable:
            raise EncodeError(
                f"{register.name} ({register.address:#04x}) is read only",
                field="address",
                value=register.address,
            )
        if register.address in ADDRESS_ONLY_WRITES:
            raise EncodeError(
                f"{register.name} is written with its address alone",
                field="address",
                value=register.address,
            )
        register.check(int.from_bytes(raw, "big", signed=register.signed))


def values_from(address: int, data: bytes) -> dict[str, int]:
    """Name the values of the whole registers that READ bytes ``data`` from ``address`` hold.

    >>> values_from(0x38, bytes.fromhex("07ff"))   # manual 2.3.2: present position 0x07FF
    {'present_position': 2047}
    """
    values: dict[str, int] = {}
    for offset in range(len(data)):
        register = REGISTERS.at(address + offset)
        if register is None or register.address != address + offset:
            continue
        raw = data[offset : offset + register.size]
        if len(raw) == register.size:
            values[register.name] = int.from_bytes(raw, "big", signed=register.signed)
    return values


def readings(reply: object) -> list[Reading]:
    """Always ``[]``: a DS reply (``FF F5 id len status data… sum``) carries no address.

    Which registers a READ's bytes hold is known only from the READ that asked for them; the
    host that sent it names them with ``values_from(address, data)``.
    """
    return []


def _known(address: int) -> Register:
    register = REGISTERS.at(address)
    if register is None:
        raise EncodeError(
            f"address {address:#04x} is not in the control table", field="address", value=address
        )
    return register


def _split(address: int, data: bytes) -> list[tuple[Register, bytes]]:
    """Cut ``data`` into the registers it covers from ``address``; whole registers only."""
    parts = []
    offset = 0
    while offset < len(data):
        register = _known(address + offset)
        if register.address != address + offset:
            raise EncodeError(
                f"write at {address + offset:#04x} starts inside {register.name}",
                field="address",
                value=address + offset,
            )
        raw = data[offset : offset + register.size]
        if len(raw) < register.size:
            raise EncodeError(f"write ends inside {register.name}", field="data", value=data.hex())
        parts.append((register, raw))
        offset += register.size
    return parts
