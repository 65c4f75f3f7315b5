"""Special functions for the partial-wave series, by vectorised recurrences.

Sign convention (docs/design.md §4.1): spectra use numpy's forward FFT e^{-i2πft}, so a time-harmonic
field carries e^{+iωt} and an *outgoing* wave is e^{-ikr}. The outgoing radial functions are
therefore the Hankel functions of the second kind:

* spherical  h_n^{(2)}(z) = j_n(z) − i y_n(z),  h_0^{(2)}(z) = i e^{-iz}/z,
* cylindrical H_n^{(2)}(z) = J_n(z) − i Y_n(z) ~ √(2/(πz)) e^{-i(z − nπ/2 − π/4)}.

Upward recurrences are stable for these functions (they are dominated by the growing Y_n / y_n),
which lets a whole array of arguments advance together in the order n.
"""

from __future__ import annotations

import numpy as np
import scipy.special as sp

__all__ = [
    "sph_hankel2_orders",
    "hankel2_orders",
    "legendre_orders",
    "hankel2_0",
    "n_terms",
]


def n_terms(ka_max: float) -> int:
    """Number of partial waves for convergence up to size parameter ka_max (Wiscombe's rule + margin)."""
    ka_max = float(ka_max)
    return int(np.ceil(ka_max + 4.05 * ka_max ** (1.0 / 3.0) + 10))


def sph_hankel2_orders(z: np.ndarray, n_max: int) -> np.ndarray:
    """h_n^{(2)}(z) for n = 0..n_max, order first: shape (n_max+1,) + z.shape, complex128 (z real > 0).

    h_{n+1} = (2n+1)/z h_n − h_{n−1} with h_0 = i e^{-iz}/z, h_1 = e^{-iz}(i/z² − 1/z).
    """
    z = np.asarray(z, dtype=np.float64)
    out = np.empty((n_max + 1,) + z.shape, dtype=np.complex128)
    e = np.exp(-1j * z)
    out[0] = 1j * e / z
    if n_max >= 1:
        out[1] = e * (1j / z**2 - 1.0 / z)
    inv = 1.0 / z
    for n in range(1, n_max):
        out[n + 1] = (2 * n + 1) * inv * out[n] - out[n - 1]
    return out


def hankel2_0(z: np.ndarray) -> np.ndarray:
    """H_0^{(2)}(z) for real z > 0: scipy below z = 25, 3-term Hankel asymptotic above (|err| < 1e-6)."""
    z = np.asarray(z, dtype=np.float64)
    out = np.empty(z.shape, dtype=np.complex128)
    small = z < 25.0
    if np.any(small):
        out[small] = sp.hankel2(0, z[small])
    big = ~small
    if np.any(big):
        zb = z[big]
        out[big] = (
            np.sqrt(2.0 / (np.pi * zb))
            * np.exp(-1j * (zb - np.pi / 4))
            * (1.0 + 1j / (8 * zb) - 9.0 / (128 * zb**2) - 75j / (1024 * zb**3))
        )
    return out


def hankel2_orders(z: np.ndarray, n_max: int) -> np.ndarray:
    """H_n^{(2)}(z) for n = 0..n_max, order first: shape (n_max+1,) + z.shape, complex128 (z real > 0).

    H_{n+1} = (2n/z) H_n − H_{n−1}, seeded with scipy's H_0, H_1.
    """
    z = np.asarray(z, dtype=np.float64)
    out = np.empty((n_max + 1,) + z.shape, dtype=np.complex128)
    out[0] = sp.hankel2(0, z)
    if n_max >= 1:
        out[1] = sp.hankel2(1, z)
    inv = 1.0 / z
    for n in range(1, n_max):
        out[n + 1] = (2 * n) * inv * out[n] - out[n - 1]
    return out


def legendre_orders(x: np.ndarray, n_max: int) -> np.ndarray:
    """P_n(x) for n = 0..n_max, order first: shape (n_max+1,) + x.shape, float64 (Bonnet recurrence)."""
    x = np.asarray(x, dtype=np.float64)
    out = np.empty((n_max + 1,) + x.shape, dtype=np.float64)
    out[0] = 1.0
    if n_max >= 1:
        out[1] = x
    for n in range(1, n_max):
        out[n + 1] = ((2 * n + 1) * x * out[n] - n * out[n - 1]) / (n + 1)
    return out
