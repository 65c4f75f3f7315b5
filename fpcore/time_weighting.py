"""Inverse-variance time weighting of a frame: γ's numerator as the matched filter in a fog that decays
(docs/design.md §4.14).

γ's numerator Σ R F* (paper eq. P) is the matched filter of the target's echo in a background that is white
*and stationary* (paper S4: every coefficient of M has the one variance σ_M²). The fog is not stationary in
time: under the interface its energy falls by tens of dB over the record, and a fingerprint's support (tens of
µs of ring-down, its shifted copies and their spectral tails) spans that fall, so the unweighted sum is ruled
by the brightest early samples. For a background of independent samples with a variance v(t) the matched
filter weighs each sample by 1/v(t):

    N_w(r) = Σ_{u,θ,t} R(u, θ, t) F*(u, θ, t; r) / v(t),                                           (W1)

which is eq. P applied to the weighted frame R_w = R/v. The weighting is the data's own: v(t) is the frame's
mean energy over elements and transmits, smoothed over `smooth_s`, the same estimate a time-gain compensation
curve is. Cauchy–Schwarz still bounds γ of R_w by 1, and the local null level of eq. (B1), made from R_w's
own energy, is the weighted statistic's (its energy is 1/v). The fingerprint (a calibration in water) is left as
it is; a confocal image made from R_w is the weighted, time-gain-compensated image. Where a target's own echo rules
v(t) the weighting takes it for background (docs/design.md §4.14 measures the cost).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.ndimage import uniform_filter1d

from .acquisition import Acquisition

__all__ = ["DEFAULT_SMOOTH_S", "variance_envelope", "time_weights", "apply_time_weights", "inverse_variance_weighted"]

#: The smoothing of v(t) (s): longer than a compact target's own echo, so that a target standing out of the
#: background is not taken for it (a 2.4 mm cluster of points over stationary speckle: its PFA 2e-8 with 5 µs,
#: as unweighted, 5e-2 with 2 µs), and shorter than the fog's decay (tests/test_time_weighting.py,
#: docs/design.md §4.14). The spheres' gain does not depend on it from 0.5 to 10 µs.
DEFAULT_SMOOTH_S = 5e-6

#: v(t) is floored at this fraction of its median over the record (−20 dB): the weighting equalises a background
#: down to 20 dB below its typical level, not the silent stretches of a record (zero padding, a noiseless
#: simulation before the first echo), whose rounding residue 1/v would otherwise raise above every echo. The
#: sinking-sphere frames span +30 … −17 dB about their median, inside it.
FLOOR = 1e-2


def variance_envelope(acq: Acquisition, smooth_s: float = DEFAULT_SMOOTH_S) -> np.ndarray:
    """v(t): the frame's energy per sample averaged over elements and transmits, smoothed over `smooth_s`
    (a moving average), floored at FLOOR × its median; float64, one value per time sample."""
    if not (smooth_s >= 0 and np.isfinite(smooth_s)):
        raise ValueError(f"smooth_s: expected a smoothing time >= 0 s, got {smooth_s}")
    power = np.mean(np.square(acq.rf, dtype=np.float64), axis=(0, 1))
    size = max(1, int(round(smooth_s * acq.fs)))
    v = uniform_filter1d(power, size=size, mode="nearest")
    if not float(v.max()) > 0:
        raise ValueError("rf: the frame is identically zero; no time weighting can be made")
    typical = float(np.median(v))
    if typical <= 0:  # more than half the record silent: its loudest level is the only reference left
        typical = float(v.max())
    return np.maximum(v, FLOOR * typical)


def time_weights(acq: Acquisition, smooth_s: float = DEFAULT_SMOOTH_S) -> np.ndarray:
    """The weights 1/v(t) of eq. (W1) for this frame, scaled to a median of 1 (γ does not depend on the scale)."""
    w = 1.0 / variance_envelope(acq, smooth_s)
    return w / float(np.median(w))


def apply_time_weights(acq: Acquisition, weights: np.ndarray) -> Acquisition:
    """`acq` with every trace multiplied by `weights(t)`; the same metadata and truth. With one frame's weights
    applied to each of its parts (a simulated echo, the fog), the weighted frame splits as the frame does: γ's
    numerator is linear in R (paper eq. P)."""
    w = np.asarray(weights)
    if w.shape != (acq.n_samples,):
        raise ValueError(f"weights: expected one per time sample, shape ({acq.n_samples},), got {w.shape}")
    dtype = acq.rf.dtype if np.issubdtype(acq.rf.dtype, np.floating) else np.float64
    return replace(acq, rf=acq.rf * w.astype(dtype)[None, None, :])


def inverse_variance_weighted(acq: Acquisition, smooth_s: float = DEFAULT_SMOOTH_S) -> Acquisition:
    """The frame R_w = R/v(t) of eq. (W1), its weights its own (`time_weights`)."""
    return apply_time_weights(acq, time_weights(acq, smooth_s))
