"""The LA control table (manual section 3.6) as data, and the rules for reading and writing it.

Rule: every range the schemas, the driver and the simulator use is written here once. An
address that is in no ``Register`` is reserved: it may be read, never written. A write
covers each register it touches whole, and is checked against that register's range; a write
of part of a register (one byte of a u16) is refused, since it cannot be judged (a byte of
the over-current limit would make it 176 mA, under the manual's 300) and the driver could not
know what the register then holds.

The over-temperature limit and the rewarm temperature bound each other
(``overtemp >= rewarm + 5 °C``). Their registers hold the absolute bounds that follow from
the table (rewarm >= 20 °C, overtemp <= 80 °C, hence overtemp >= 25 °C and rewarm <= 75 °C);
``check_temperature_limits`` applies the cross rule when both values are known — within one
write here, otherwise by the caller that knows the device's current values.
"""

from __future__ import annotations

from busgate.codecs.errors import EncodeError
from busgate.codecs.inspire_la.frames import (
    BAUD_RATES,
    MAX_DATA,
    TABLE_SIZE,
    TARGET_INDEX,
    ReadReply,
    WriteCommand,
)
from busgate.codecs.registers import Access, Reading, Register, RegisterMap, require_range

#: Temperatures are stored in tenths of a degree Celsius.
TENTHS_PER_DEGREE = 10
#: The over-temperature limit must stay at least 5 °C above the rewarm temperature.
TEMPERATURE_GAP_RAW = 5 * TENTHS_PER_DEGREE

ID = "id"
BAUD_CODE = "baud_code"
FORCE_ZERO = "force_zero"
OVERCURRENT_LIMIT = "overcurrent_limit"
TARGET_POSITION = "target_position"
OVERTEMP_LIMIT = "overtemp_limit"
REWARM_TEMPERATURE = "rewarm_temperature"

_RW = Access.READ_WRITE
REGISTERS = RegisterMap(
    [
        Register(ID, 2, 1, _RW, minimum=1, maximum=254, default=1,
                 description="device id; in use at once, kept over power-off after save"),
        Register(BAUD_CODE, 12, 1, _RW, minimum=0, maximum=len(BAUD_RATES) - 1, default=3,
                 description="0 19200, 1 57600, 2 115200, 3 921600; after save and power cycle"),
        Register("current_position", 26, 2, Access.READ, unit="stroke units", signed=True,
                 minimum=-20, maximum=2020, description="present position"),
        # "Settable range 1": writing 1 takes the present force reading as zero.
        Register(FORCE_ZERO, 31, 1, _RW, minimum=1, maximum=1, default=0,
                 description="write 1 to zero the force sensor"),
        Register(OVERCURRENT_LIMIT, 32, 2, _RW, unit="mA", minimum=300, maximum=1500,
                 default=1500, description="over-current protection threshold"),
        Register(TARGET_POSITION, TARGET_INDEX, 2, _RW, unit="stroke units", minimum=0,
                 maximum=2000, description="target position (larger is longer)"),
        # The manual gives [-32767, +32768]; a signed 16-bit value ends at 32767.
        Register("force", 76, 2, Access.READ, unit="g", signed=True, minimum=-32767,
                 description="force sensor reading (LAF/LASF only)"),
        Register("force_raw", 78, 2, Access.READ, description="force sensor raw 12-bit ADC value"),
        Register(OVERTEMP_LIMIT, 98, 2, _RW, unit="°C", scale=1 / TENTHS_PER_DEGREE,
                 minimum=250, maximum=800, default=800,
                 description="over-temperature limit, [rewarm + 5, 80] °C"),
        Register(REWARM_TEMPERATURE, 100, 2, _RW, unit="°C", scale=1 / TENTHS_PER_DEGREE,
                 minimum=200, maximum=750, default=600,
                 description="works again below this after over-temperature, [20, limit - 5] °C"),
    ]
)  # fmt: skip


def check_span(index: int, length: int) -> None:
    """Raise ``EncodeError`` unless ``length`` bytes from ``index`` lie in the control table
    and fit one frame.

    >>> check_span(0x62, 2)
    >>> check_span(0xFE, 2)
    Traceback (most recent call last):
    ...
    busgate.codecs.errors.EncodeError: index + length 256 is out of range [1, 255]
    """
    require_range("index", index, 0, TABLE_SIZE - 1)
    require_range("length", length, 1, MAX_DATA)
    require_range("index + length", index + length, 1, TABLE_SIZE)


def check_write(index: int, data: bytes) -> None:
    """Raise ``EncodeError`` unless writing ``data`` at ``index`` is allowed.

    Reserved and read-only addresses are refused, and so is a write of part of a register;
    every register the write covers must get a value in its range.

    >>> check_write(0x37, bytes.fromhex("1405"))  # target 1300, manual 3.5.2
    >>> check_write(0x1A, bytes.fromhex("e803"))
    Traceback (most recent call last):
    ...
    busgate.codecs.errors.EncodeError: current_position (address 26) is read only
    >>> check_write(0x21, bytes.fromhex("00"))
    Traceback (most recent call last):
    ...
    busgate.codecs.errors.EncodeError: overcurrent_limit is 2 bytes at 32: write them both
    """
    check_span(index, len(data))
    end = index + len(data)
    for address, register in enumerate(REGISTERS.covering(index, len(data)), start=index):
        if register is None:
            raise EncodeError(f"address {address} is reserved", field="index", value=address)
        if not register.access.writable:
            raise EncodeError(
                f"{register.name} (address {address}) is read only", field="index", value=address
            )
        if register.address < index or register.end > end:
            raise EncodeError(
                f"{register.name} is {register.size} bytes at {register.address}: write them both",
                field="index",
                value=address,
            )
    values = register_values(index, data)
    for name, raw in values.items():
        REGISTERS[name].check(raw)
    if OVERTEMP_LIMIT in values and REWARM_TEMPERATURE in values:
        check_temperature_limits(values[OVERTEMP_LIMIT], values[REWARM_TEMPERATURE])


def register_values(index: int, data: bytes) -> dict[str, int]:
    """The raw value of every register that ``data`` at ``index`` covers whole, by name.

    >>> register_values(98, bytes.fromhex("c1025d02"))  # manual 3.7.5: 70.5 °C and 60.5 °C
    {'overtemp_limit': 705, 'rewarm_temperature': 605}
    """
    values = {}
    for register in REGISTERS:
        if index <= register.address and register.end <= index + len(data):
            raw = data[register.address - index : register.end - index]
            values[register.name] = int.from_bytes(raw, "little", signed=register.signed)
    return values


def readings(reply: object) -> list[Reading]:
    """The registers a read reply holds, by name and in their units, in address order.

    Only whole registers are named: bytes at reserved addresses, or half of a two-byte
    register, stay in the reply's ``data`` alone. Any other frame carries no value: ``[]``.

    >>> readings(ReadReply(1, 0x62, bytes.fromhex("5802")))  # manual 3.5.1: 60.0 °C
    [Reading(register='overtemp_limit', address=98, raw=600, value=60.0, unit='°C')]
    >>> readings(ReadReply(1, 0x62, bytes.fromhex("58")))
    []
    """
    if not isinstance(reply, ReadReply):
        return []
    values = register_values(reply.index, reply.data)
    return [REGISTERS[name].reading(raw) for name, raw in values.items()]


def check_temperature_limits(overtemp_raw: int, rewarm_raw: int) -> None:
    """Raise ``EncodeError`` unless the over-temperature limit is ≥ rewarm + 5 °C (raw ×10).

    >>> check_temperature_limits(705, 605)  # manual 3.7.5: 70.5 °C and 60.5 °C
    >>> check_temperature_limits(640, 605)
    Traceback (most recent call last):
    ...
    busgate.codecs.errors.EncodeError: overtemp_limit 640 is below rewarm_temperature 605 + 50
    """
    if overtemp_raw < rewarm_raw + TEMPERATURE_GAP_RAW:
        raise EncodeError(
            f"{OVERTEMP_LIMIT} {overtemp_raw} is below {REWARM_TEMPERATURE} "
            f"{rewarm_raw} + {TEMPERATURE_GAP_RAW}",
            field=OVERTEMP_LIMIT,
            value=overtemp_raw,
        )


def temperature_raw(temp_c: float) -> int:
    """Degrees Celsius to the table's tenths; refuses finer steps than 0.1 °C.

    >>> temperature_raw(70.5)  # manual 3.7.5
    705
    """
    raw = round(temp_c * TENTHS_PER_DEGREE)
    if abs(raw - temp_c * TENTHS_PER_DEGREE) > 1e-6:
        raise EncodeError(
            f"temperature {temp_c} °C is finer than the table's 0.1 °C steps",
            field="temp_c",
            value=temp_c,
        )
    return raw


def baud_code(baudrate: int) -> int:
    """The register 12 code of ``baudrate``.

    >>> baud_code(921600)
    3
    """
    if baudrate not in BAUD_RATES:
        raise EncodeError(
            f"baud rate {baudrate} is not one of {BAUD_RATES}", field="baudrate", value=baudrate
        )
    return BAUD_RATES.index(baudrate)


def register_write(device_id: int, name: str, raw: int) -> WriteCommand:
    """The write command that sets the whole register ``name`` to ``raw``.

    >>> from busgate.codecs.inspire_la import encode
    >>> encode(register_write(1, OVERCURRENT_LIMIT, 1000)).hex(" ")  # manual 3.7.6
    '55 aa 04 01 02 20 e8 03 12'
    """
    register = REGISTERS[name]
    data = register.check(raw).to_bytes(register.size, "little", signed=register.signed)
    return WriteCommand(device_id, register.address, data)
