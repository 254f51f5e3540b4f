"""What every compiled (numba) loop of the estimator shares: how a loop is compiled and cached,
and the one array layout its callers pass.

numba compiles a loop once per argument layout, dtype and writeability, so its callers pass
writeable C-contiguous arrays of one dtype (a view such as ``T[:, :3, :3]``, a broadcast or a
read-only array would otherwise compile a second version on first use: seconds in the middle
of a frame). Each module with loops compiles them ahead of the first frame (its own
``compile_kernels``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["as_bool", "as_f64", "as_plain", "compiled"]


def as_plain(x, dtype=None) -> np.ndarray:
    """``x`` as a writeable C-contiguous array of ``dtype`` (its own where None)."""
    out = np.ascontiguousarray(x, dtype=dtype)
    return out if out.flags.writeable else out.copy()


def as_f64(x) -> np.ndarray:
    """``x`` as a writeable C-contiguous float64 array."""
    return as_plain(x, np.float64)


def as_bool(x) -> np.ndarray:
    """``x`` as a writeable C-contiguous bool array."""
    return as_plain(x, np.bool_)


def compiled(fn):
    """``fn`` compiled, kept in numba's disk cache (beside its module, or the user's cache
    folder); where neither can be written, compiled anew in each process instead of failing."""
    try:
        return njit(cache=True, nogil=True)(fn)
    except RuntimeError:  # numba: "cannot cache function ...: no locator available"
        return njit(nogil=True)(fn)
