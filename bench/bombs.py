"""Hostile image payloads for the fault tests and the soak benchmark: decompression bombs (a
small stream whose header declares a huge image) wrapped in otherwise valid Image messages."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np

from posefuse.service.codec import _pack


def png_bomb(width: int = 20000, height: int = 20000) -> bytes:
    """A valid 8-bit greyscale PNG of width x height zeros: about 1 kB per 2.5 Mpx, so a
    20000x20000 one is ~0.4 MB and decodes to 400 MB (1.2 GB as colour)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data))
            + kind
            + data
            + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
        )

    z = zlib.compressobj(9)
    row = b"\0" * (width + 1)  # filter byte + pixels
    parts = [z.compress(row) for _ in range(height)]
    parts.append(z.flush())
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", b"".join(parts))
        + chunk(b"IEND", b"")
    )


def jpeg_bomb(width: int = 20000, height: int = 20000) -> bytes:
    """A tiny JPEG whose frame header (SOF) is patched to declare width x height: a decoder
    that trusts it allocates the whole image before finding the data short."""
    ok, buf = cv2.imencode(".jpg", np.zeros((8, 8, 3), np.uint8))
    data = bytearray(buf.tobytes())
    i = 2
    while i < len(data):
        marker, length = data[i + 1], int.from_bytes(data[i + 2 : i + 4], "big")
        if marker in (0xC0, 0xC1, 0xC2):
            data[i + 5 : i + 7] = height.to_bytes(2, "big")
            data[i + 7 : i + 9] = width.to_bytes(2, "big")
            return bytes(data)
        i += 2 + length
    raise RuntimeError("no SOF marker in OpenCV's JPEG")


def image_message(
    stream: bytes, encoding: str, stamp_ns: int, declared=(100, 100), frame_id="cam"
) -> bytes:
    """An Image message carrying ``stream`` and declaring ``declared`` (width, height)."""
    return _pack(
        {
            "stamp_ns": int(stamp_ns),
            "frame_id": frame_id,
            "encoding": encoding,
            "width": int(declared[0]),
            "height": int(declared[1]),
            "data": stream,
        }
    )
