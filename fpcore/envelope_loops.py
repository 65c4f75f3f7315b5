"""Envelope spectra Ê of plane-wave data (eq. B1 of fpcore.background; docs/design.md §4.9): by FFT
(`envelope_spectrum`, any array) and by frequency autocorrelation (`envelope_columns`, a frame's directions).

For a band record R_f on uniformly spaced bins f = 0 … N_f − 1, the spectrum of its energy envelope |a(t)|²
(a the band's analytic signal on a periodic axis of 2N_f samples, `envelope_spectrum`) is the
autocorrelation of the band itself, exactly:

    Ê(m) = Σ_{f=0}^{N_f−1−m} R_{f+m} R_f*,   m = 0 … N_f − 1,

(Wiener–Khinchin on the DFT: |a|² = a a* is a product in time, a correlation in frequency; 2N_f > 2(N_f − 1)
leaves no wrapped term). Per output direction that is N_f²/2 complex products, read from one cache-sized
block of directions: cheaper than two strided FFTs of 2N_f samples and their gathers, and only the
directions a fingerprint's angular support asks for are read and written (the others keep what they hold).
"""

from __future__ import annotations

from functools import partial

import numpy as np
import scipy.fft as sfft

from .kernel import default_threads
from .kernel_presum_loops import _jit, nb, pool, split

__all__ = ["envelope_columns", "envelope_spectrum"]


def envelope_spectrum(data: np.ndarray) -> np.ndarray:
    """Ê(ν, o, i) for ν = m δf, m = 0 … N_f − 1: the spectrum of |a(t)|², a the band's analytic signal.

    data: (N_f, N_o, N_i) on uniformly spaced frequencies (the time axis is periodic, 1/δf, like γ's).
    The band is moved to baseband first (|a|² does not change); |a|² has bandwidth 2(N_f − 1)δf, so a
    time axis of 2 N_f samples holds it without aliasing.
    """
    n_f = data.shape[0]
    n_t = 2 * n_f
    flat = np.asarray(data).reshape(n_f, -1)  # transforms along the first axis: no transposed copies
    a = sfft.ifft(flat, n=n_t, axis=0, workers=-1)
    e = a.real**2 + a.imag**2
    e *= n_t  # scale: Σ_t |a|² = Σ_f |R_f|² (Parseval)
    spec = sfft.rfft(e, axis=0, workers=-1)[:n_f]  # |a|² is real: ν ≥ 0 is all there is
    return spec.reshape(data.shape).astype(np.complex64, copy=False)


_BLOCK_O = 8  # output directions per block: N_f × 8 N_i complex values (≈ 140 kB for 89 × 8 × 25), in L2

if nb is not None:

    @partial(_jit, fastmath=False)  # IEEE: a direction's values do not depend on its place in a block
    def _autocorr(R, cols, e, Xr, Xi, Er, Ei, c0, c1):  # pragma: no cover
        """e[m, o, i] = Σ_f R[f + m, o, i] R*[f, o, i] for o = cols[c0:c1] (R, e: (N_f, N_o, N_i, 2) float32
        re/im pairs; Xr … Ei: this thread's (N_f, ≥ 8 N_i) and (≥ 8 N_i,) work planes)."""
        nf, _, ni, _ = R.shape
        for c in range(c0, c1, _BLOCK_O):
            nbk = min(_BLOCK_O, c1 - c)
            w = nbk * ni
            for f in range(nf):
                for b in range(nbk):
                    o = cols[c + b]
                    for i in range(ni):
                        Xr[f, b * ni + i] = R[f, o, i, 0]
                        Xi[f, b * ni + i] = R[f, o, i, 1]
            for m in range(nf):
                er = Er[:w]
                ei = Ei[:w]
                er[:] = 0
                ei[:] = 0
                for f in range(nf - m):
                    ar = Xr[f + m]
                    ai = Xi[f + m]
                    br = Xr[f]
                    bi = Xi[f]
                    for t in range(w):
                        er[t] += ar[t] * br[t] + ai[t] * bi[t]
                        ei[t] += ai[t] * br[t] - ar[t] * bi[t]
                for b in range(nbk):
                    o = cols[c + b]
                    for i in range(ni):
                        e[m, o, i, 0] = er[b * ni + i]
                        e[m, o, i, 1] = ei[b * ni + i]


def envelope_columns(data: np.ndarray, cols: np.ndarray, out: np.ndarray, nthreads: int | None = None) -> None:
    """out[:, o] = Ê(·, o, ·) (module doc) for the output directions o in `cols`, in place; data and out:
    C-contiguous complex64 (N_f, N_o, N_i); nthreads: default FP_THREADS or the CPU count. Without numba, the
    FFT route (`envelope_spectrum`) on those columns."""
    if data.dtype != np.complex64 or out.dtype != np.complex64 or out.shape != data.shape:
        raise ValueError(
            f"data, out: expected complex64 arrays of one shape, got {data.dtype} {data.shape}, {out.dtype} {out.shape}"
        )
    cols = np.ascontiguousarray(cols, dtype=np.int64)
    if cols.size == 0:
        return
    if nb is None or not (data.flags.c_contiguous and out.flags.c_contiguous):
        out[:, cols] = envelope_spectrum(data[:, cols])
        return
    nf, _, ni = data.shape
    R = data.view(np.float32).reshape(*data.shape, 2)
    e = out.view(np.float32).reshape(*out.shape, 2)
    nt = max(1, min(nthreads or default_threads(), cols.size))
    width = _BLOCK_O * ni
    X = np.empty((nt, 2, nf, width), np.float32)
    E = np.empty((nt, 2, width), np.float32)
    ntasks = min(cols.size, 4 * nt)
    pool(
        nt,
        ntasks,
        _autocorr,
        lambda s, t: (R, cols, e, X[s, 0], X[s, 1], E[s, 0], E[s, 1], *split(cols.size, ntasks, t)),
    )
