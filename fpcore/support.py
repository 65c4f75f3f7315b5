"""Products on a fingerprint's angular support: the output directions where its (N_f, N_o, N_i) array is
not zero (~20 % of a full-size frame's). The map kernels skip zero weights (docs/design.md §5), so γ's
numerator (paper eq. P) and the null level's sum (eq. B1 of fpcore.background) only need their weights
there; `SupportProduct` writes them into a kept buffer that stays zero elsewhere, instead of a full-size
product (an 80 MB array) on every map."""

from __future__ import annotations

import numpy as np

__all__ = ["SupportProduct", "angular_support"]


def angular_support(t: np.ndarray) -> np.ndarray:
    """Indices of the output directions (axis 1 of an (N_f, N_o, N_i) array) where `t` is not zero."""
    return np.flatnonzero(np.any(np.asarray(t) != 0, axis=(0, 2)))


class SupportProduct:
    """a ∘ b on a support, zero elsewhere, in one buffer kept between calls (one caller at a time: the
    result is that buffer, overwritten by the next call)."""

    def __init__(self) -> None:
        self._buf: np.ndarray | None = None
        self._support: np.ndarray | None = None

    def __call__(self, a: np.ndarray, support: np.ndarray, b: np.ndarray) -> np.ndarray:
        """The (N_f, N_o, N_i) array equal to a[:, support] · b on `support` and 0 off it; `b` is given on the
        support only, (N_f, support.size, N_i). Only the last support's directions the new one lacks are
        cleared."""
        dtype = np.result_type(a.dtype, b.dtype)
        buf, last = self._buf, self._support
        if buf is None or last is None or buf.shape != a.shape or buf.dtype != dtype:
            buf, last = np.zeros(a.shape, dtype), support
        elif last is not support and not np.array_equal(last, support):
            buf[:, np.setdiff1d(last, support)] = 0
        self._buf, self._support = buf, support
        if support.size == a.shape[1]:
            np.multiply(a, b, out=buf)
        else:
            buf[:, support] = a[:, support] * b
        return buf
