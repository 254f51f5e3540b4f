"""Hostile image payloads for the fault tests and the soak benchmark: decompression bombs (a
small stream whose header declares a huge image), well-formed streams that are expensive to
decode for a decoder that trusts them (a progressive JPEG scan repeated, a PNG of many tiny
chunks), each wrapped in an otherwise valid Image message by :func:`image_message`."""

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


def _segments(data: bytes):
    """(start, end, marker) of each JPEG segment; a scan's end includes its entropy data."""
    out, i = [], 2
    while i < len(data):
        marker = data[i + 1]
        if marker == 0xD9:
            out.append((i, i + 2, marker))
            break
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        end = i + 2 + length
        if marker == 0xDA:  # entropy-coded data up to the next marker (not a stuffed 0xFF00)
            while not (data[end] == 0xFF and data[end + 1] not in (0x00, *range(0xD0, 0xD8))):
                end += 1
        out.append((i, end, marker))
        i = end
    return out


def progressive_scan_bomb(width: int = 4096, height: int = 4096, repeats: int = 20000) -> bytes:
    """A progressive JPEG of a flat width x height image whose last AC scan is repeated
    ``repeats`` times: under a megabyte, every header true, and each scan makes a decoder walk
    every block of the image again."""
    image = np.full((height, width, 3), 128, np.uint8)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    data = buf.tobytes()
    segs = _segments(data)
    scans = [s for s in segs if s[2] == 0xDA]
    last = scans[-1]
    body = data[last[0] : last[1]]
    eoi = segs[-1][0]
    return data[:eoi] + body * repeats + data[eoi:]


def png_many_chunks(width: int = 64, height: int = 64, chunks: int = 200_000) -> bytes:
    """A valid PNG whose image data is split into ``chunks`` IDAT chunks of a few bytes."""

    def chunk(kind: bytes, payload: bytes) -> bytes:
        crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)

    raw = b"".join(b"\0" + bytes(width * 3) for _ in range(height))
    z = zlib.compress(raw, 9)
    step = max(1, len(z) // chunks)
    idat = b"".join(chunk(b"IDAT", z[k : k + step]) for k in range(0, len(z), step))
    pad = b"".join(chunk(b"tEXt", b"k\0v") for _ in range(max(0, chunks - len(z) // step)))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + pad + idat + chunk(b"IEND", b"")


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
