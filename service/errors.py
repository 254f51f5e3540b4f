"""The one error of received bytes that cannot be used, shared by the codec
(:mod:`service.codec`) and the image stream checks it runs before decoding
(:mod:`service.image_checks`)."""

from __future__ import annotations

from posefuse.estimator.core.errors import PosefuseError


class DecodeError(PosefuseError):
    """A message that cannot be used: which kind, why, and a short code for the counters
    (``malformed``; ``too_large`` for a payload or image over the limits, checked before any
    decoding; ``header_mismatch`` for a compressed image whose own header contradicts the
    message's size; ``jpeg_scans``, ``jpeg_segments``, ``png_chunks`` and ``png_ratio`` for a
    stream whose structure no camera writes and whose decoding would cost far more than its
    size says, see :func:`~service.image_checks.check_decode_cost`)."""

    def __init__(self, kind: str, reason: str, code: str = "malformed"):
        self.kind = kind
        self.reason = reason
        self.code = code
        super().__init__(f"{kind}: {reason}")
