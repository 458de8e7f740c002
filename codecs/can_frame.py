"""The codecs' own CAN frame type, so that codecs stay free of python-can.

Only the CAN bus owner converts between ``CanFrame`` and ``can.Message``. The text form is
cansend's: ``<3 hex digit id>#<data hex>``.
"""

from __future__ import annotations

from dataclasses import dataclass

from busgate.codecs.errors import EncodeError

MAX_STANDARD_ID = 0x7FF


@dataclass(frozen=True, slots=True)
class CanFrame:
    """A classic CAN data frame with a standard (11-bit) identifier.

    >>> str(CanFrame(1, bytes.fromhex("00fa0011fffff556")))
    '001#00fa0011fffff556'
    """

    arbitration_id: int
    data: bytes

    def __post_init__(self) -> None:
        if not 0 <= self.arbitration_id <= MAX_STANDARD_ID:
            raise EncodeError(
                f"CAN identifier {self.arbitration_id:#x} is not a standard 11-bit identifier",
                field="arbitration_id",
                value=self.arbitration_id,
            )
        if len(self.data) > 8:
            raise EncodeError(
                f"a classic CAN frame carries at most 8 data bytes, not {len(self.data)}",
                field="data",
                value=self.data.hex(),
            )

    def __str__(self) -> str:
        return f"{self.arbitration_id:03x}#{self.data.hex()}"

    @classmethod
    def parse(cls, text: str) -> CanFrame:
        """Parse cansend's ``id#data`` form; raises ``EncodeError`` when it is not one.

        >>> CanFrame.parse("00A#00FB0019")
        CanFrame(arbitration_id=10, data=b'\\x00\\xfb\\x00\\x19')
        """
        ident, sep, data = text.strip().partition("#")
        try:
            if not sep or not ident:
                raise ValueError("missing '#'")
            return cls(int(ident, 16), bytes.fromhex(data))
        except ValueError as exc:
            raise EncodeError(
                f"not a CAN frame in id#data form: {text!r}", field="frame", value=text
            ) from exc
