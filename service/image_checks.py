"""Checks of a compressed image stream before it is decoded: the image bombs a camera never
sends, refused from the stream's own structure.

- A decompression bomb is a small stream whose header declares a huge image: the size the PNG
  (IHDR) or JPEG (SOF) header declares is read without decoding anything, and checked against
  the message's size (and so the pixel limit the codec checks on it).
- A stream can also cost far more to decode than its size says: a progressive JPEG of
  thousands of scans, thousands of segments, a PNG of tiny chunks, of compressed text, or with
  image data that deflate cannot turn into the declared image. Each is walked by its lengths,
  never decoded, and refused with its own code.

Every refusal is a :class:`~service.errors.DecodeError` of kind ``Image`` with a code for the
counters. :mod:`service.codec` runs these checks; it stays the only module that turns bytes
into messages.
"""

from __future__ import annotations

import re

from posefuse.service.errors import DecodeError

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (baseline, progressive, lossless, arithmetic): the frame size
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


# What a camera's encoder writes, with a wide margin. A progressive JPEG makes the decoder walk
# every block of the image once per scan, whatever the scan holds: libjpeg's progressive
# script writes 10 scans (a baseline image 1, or one per component), so a stream of thousands
# of scans (a few bytes each) costs minutes of CPU for a megabyte on the wire.
MAX_JPEG_SCANS = 64
MAX_JPEG_SEGMENTS = 512  # markers with a length (APPn, DQT, DHT, SOF, SOS, COM, ...) in all
# PNG encoders write image data in chunks of 8 KiB or more (libpng, OpenCV); a stream of tiny
# chunks, or a large share of compressed text and ICC chunks (inflated apart from the image),
# is not a camera's. The image data must be able to fill the declared image (deflate expands
# at most 1032:1) and hold no more than it needs (stored blocks add under 1%).
MAX_PNG_CHUNKS_BASE = 64
PNG_BYTES_PER_CHUNK = 1024  # one chunk more allowed per this many bytes of stream
MAX_PNG_COMPRESSED_ANCILLARY = 64 * 1024  # zTXt, iTXt and iCCP bytes, all together
PNG_MAX_INFLATE_RATIO = 1100
_PNG_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}
# the next marker after a scan's entropy-coded data: 0xFF not followed by a stuffed zero, a
# restart marker or another fill byte
_JPEG_NEXT_MARKER = re.compile(rb"\xff(?=[^\x00\xd0-\xd7\xff])")


def check_decode_cost(data: bytes, encoding: str) -> None:
    """Refuse, before decoding, a JPEG or PNG stream whose structure bounds no decoding cost
    (DecodeError with code ``jpeg_scans``, ``jpeg_segments``, ``png_chunks`` or
    ``png_ratio``): every segment or chunk is walked by its lengths, never decoded. Together
    with the pixel limit this bounds the decoding CPU of one message to that of a few large
    frames."""
    if encoding == "jpeg":
        _check_jpeg_structure(data)
    elif encoding == "png":
        _check_png_structure(data)


def _check_jpeg_structure(data: bytes) -> None:
    kind = "Image"
    i, n, scans, segments = 2, len(data), 0, 0
    while i + 4 <= n:
        if data[i] != 0xFF:
            raise DecodeError(kind, f"JPEG stream: no marker at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0xD9:  # end of image
            return
        if marker in (0x01, *range(0xD0, 0xD8)):  # standalone markers
            i += 2
            continue
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        if length < 2:
            raise DecodeError(kind, f"JPEG stream: segment length {length} at byte {i}")
        segments += 1
        if segments > MAX_JPEG_SEGMENTS:
            raise DecodeError(
                kind, f"JPEG stream: more than {MAX_JPEG_SEGMENTS} segments", "jpeg_segments"
            )
        i += 2 + length
        if marker == 0xDA:
            scans += 1
            if scans > MAX_JPEG_SCANS:
                raise DecodeError(
                    kind,
                    f"JPEG stream: more than {MAX_JPEG_SCANS} scans (no camera writes them)",
                    "jpeg_scans",
                )
            found = _JPEG_NEXT_MARKER.search(data, i)
            if found is None:  # truncated: the decoder says so, at the cost of what is there
                return
            i = found.start()


def _check_png_structure(data: bytes) -> None:
    kind = "Image"
    n = len(data)
    if n < 33 or data[12:16] != b"IHDR":
        raise DecodeError(kind, "data is not a PNG stream (no IHDR header)")
    width = int.from_bytes(data[16:20], "big")
    height = int.from_bytes(data[20:24], "big")
    depth, colour = data[24], data[25]
    if colour not in _PNG_CHANNELS or depth not in (1, 2, 4, 8, 16):
        raise DecodeError(kind, f"PNG stream: colour type {colour}, bit depth {depth}")
    max_chunks = MAX_PNG_CHUNKS_BASE + n // PNG_BYTES_PER_CHUNK
    i, chunks, idat, ancillary = 8, 0, 0, 0
    while i + 12 <= n:
        length = int.from_bytes(data[i : i + 4], "big")
        ctype = data[i + 4 : i + 8]
        chunks += 1
        if chunks > max_chunks:
            raise DecodeError(
                kind, f"PNG stream: more than {max_chunks} chunks for {n} bytes", "png_chunks"
            )
        if ctype == b"IDAT":
            idat += length
        elif ctype in (b"zTXt", b"iTXt", b"iCCP"):
            ancillary += length
            if ancillary > MAX_PNG_COMPRESSED_ANCILLARY:
                raise DecodeError(
                    kind,
                    f"PNG stream: over {MAX_PNG_COMPRESSED_ANCILLARY} bytes of compressed "
                    "text or ICC chunks",
                    "png_chunks",
                )
        i += 12 + length
        if ctype == b"IEND":
            break
    row = 1 + (width * depth * _PNG_CHANNELS[colour] + 7) // 8
    raw = height * row  # the image data, inflated (Adam7 interlacing adds a little)
    if idat * PNG_MAX_INFLATE_RATIO < raw or idat > raw + raw // 50 + 4096:
        raise DecodeError(
            kind,
            f"PNG stream: {idat} bytes of image data for {raw} bytes of {width}x{height} "
            "pixels (deflate cannot make that)",
            "png_ratio",
        )


def compressed_image_size(data: bytes, encoding: str) -> tuple[int, int]:
    """(width, height) a PNG or JPEG stream declares in its own header (IHDR, SOF), read
    without decoding anything; DecodeError when there is no such header.

    A decompression bomb is a small stream whose header declares a huge image: the size is
    checked against the message and the pixel limit before the decoder allocates anything.
    """
    kind = "Image"
    if encoding == "png":
        if len(data) < 24 or data[:8] != _PNG_SIGNATURE or data[12:16] != b"IHDR":
            raise DecodeError(kind, "data is not a PNG stream (no IHDR header)")
        return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    if len(data) < 4 or data[0] != 0xFF or data[1] != 0xD8:
        raise DecodeError(kind, "data is not a JPEG stream (no SOI marker)")
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            raise DecodeError(kind, f"JPEG stream: no marker at byte {i}")
        marker = data[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):  # standalone markers
            i += 2
            continue
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        if marker in _JPEG_SOF:
            if length < 7 or i + 9 > len(data):
                raise DecodeError(kind, "JPEG stream: truncated frame header")
            height = int.from_bytes(data[i + 5 : i + 7], "big")
            width = int.from_bytes(data[i + 7 : i + 9], "big")
            return width, height
        if marker in (0xDA, 0xD9) or length < 2:  # scan data or end before any frame header
            break
        i += 2 + length
    raise DecodeError(kind, "JPEG stream: no frame header (SOF) before the image data")


def check_compressed_image(data: bytes, encoding: str, width: int, height: int) -> None:
    """Refuse, before decoding, a JPEG or PNG stream whose own header declares another size
    than the message's ``width`` x ``height`` (code ``header_mismatch``), or whose structure
    bounds no decoding cost (:func:`check_decode_cost`)."""
    w, h = compressed_image_size(data, encoding)
    if (w, h) != (width, height):
        raise DecodeError(
            "Image",
            f"the {encoding} header says {w}x{h}, the message says {width}x{height}",
            "header_mismatch",
        )
    check_decode_cost(data, encoding)
