"""Hostile but well-formed image streams for the codec and fault tests: small on the wire,
valid to every size check, and expensive to decode for a decoder that trusts them."""

import cv2
import numpy as np


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
    import struct
    import zlib

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
