"""The protocol's 32-bit counters: int32 encoder ticks and the uint32 microsecond clock, both wrapping."""

from __future__ import annotations


def wrap_i32(v: int) -> int:
    """An integer as the int32 the board's counter holds (two's complement wrap)."""
    return ((v + 0x80000000) & 0xFFFFFFFF) - 0x80000000


def delta_i32(new: int, old: int) -> int:
    """Signed difference of two int32 tick counters that may have wrapped in between."""
    return wrap_i32(new - old)


def delta_u32(new: int, old: int) -> int:
    """Forward difference of two uint32 clock readings (microseconds), across a wrap."""
    return (new - old) & 0xFFFFFFFF
