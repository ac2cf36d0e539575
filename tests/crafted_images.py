"""Image files written byte by byte, for inputs no image library would write: a decompression bomb's header."""

from __future__ import annotations

import struct
import zlib

__all__ = ["png_claiming"]


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png_claiming(width: int, height: int, padding: int = 32 << 10) -> bytes:
    """A PNG of about `padding` bytes whose header says width x height RGB, 8 bits: its one IDAT chunk holds a
    single compressed row, so a reader that trusts the header allocates the whole image before it finds out.
    The padding (a text chunk) gets it past OpenImageIO's own guard, which refuses a header that claims more
    than some multiple of the file's size."""
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)  # 8-bit RGB, deflate, no filter/interlace
    row = zlib.compress(b"\0" * (1 + 3 * min(width, 4096)))
    text = _chunk(b"tEXt", b"Comment\0" + b"x" * padding)
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + text + _chunk(b"IDAT", row)
            + _chunk(b"IEND", b""))
