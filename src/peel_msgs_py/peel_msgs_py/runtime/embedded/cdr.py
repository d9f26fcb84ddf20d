"""CDR (XCDR1, little endian) encoding of the embedded messages, as rmw_cyclonedds sends them.

The 4-byte encapsulation header is ``00 01 00 00`` (CDR_LE), followed by the plain CDR body with
8-byte alignment for 64-bit members relative to the body start; rosbag2 stores exactly these
bytes. Cyclone DDS's Python IDL machinery does the work; this module fixes the options.
"""

from __future__ import annotations

from typing import Any

from cyclonedds.idl._support import Endianness

from ...errors import PeelError


def serialize(msg: Any) -> bytes:
    """Message -> CDR bytes with encapsulation header (XCDR1, little endian)."""
    try:
        return msg.serialize(endianness=Endianness.Little, use_version_2=False)
    except AttributeError:
        raise PeelError(f"{type(msg).__name__} is not a message of the embedded runtime") from None
    except Exception as exc:  # wrong-typed field values
        name = getattr(type(msg), "__rostype__", type(msg).__name__)
        raise PeelError(f"cannot serialize {name}: {exc}") from None


def deserialize(data: bytes | bytearray | memoryview, cls: type[Any]) -> Any:
    """CDR bytes (either endianness, XCDR1 or XCDR2) -> message of class ``cls``."""
    raw = bytes(data)
    name = getattr(cls, "__rostype__", cls.__name__)
    if len(raw) < 4 or raw[0] != 0 or raw[1] not in (0, 1, 6, 7, 8, 9):
        raise PeelError(f"cannot deserialize {name}: missing CDR encapsulation header")
    try:
        return cls.deserialize(raw)
    except Exception as exc:
        raise PeelError(f"cannot deserialize {name}: {type(exc).__name__}") from None
