"""Measurements of a multiple-scattering background, for any set of realisations (issue 12).

Every function takes the background as spectra V (n_real, N_f, N_u, N_θ) complex: the transfer function
from transmit θ (direction sines a_θ, (N_θ, 2)) to element u (positions (N_u, 3), array in z = 0) at
frequencies f (Hz, a uniform grid), in this project's conventions (docs/design.md §3–4: spectra
∫ r(t) e^{−i2πft} dt, outgoing waves e^{−ikr}, incident plane wave e^{−ik(a·ρ + c z)}). They apply as
well to the Foldy–Lax reference (bench/foldy_lax_reference.py) as to `fpcore.simulate.medium`.

Spectral weight w(f): the transducer's two-way band S(f) (`waves.Band.spectrum`) when a band is given,
else a Hann bump over the frequencies given, normalised so that 2 ∫ w df = 1 (a pulse of unit peak).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from fpcore.simulate.waves import Band

__all__ = [
    "spectral_weight",
    "time_signal",
    "gate_spectra",
    "time_envelope",
    "frequency_correlation_width",
    "cbs_enhancement",
    "confocal_contrast_slope",
    "confocal_profile",
    "jackknife_se",
]


def _step(freqs: np.ndarray) -> float:
    f = np.asarray(freqs, dtype=np.float64)
    if f.ndim != 1 or f.size < 2:
        raise ValueError(f"freqs: expected at least 2 frequencies, got shape {f.shape}")
    d = np.diff(f)
    if not np.allclose(d, d[0], rtol=1e-6, atol=0):
        raise ValueError("freqs: expected a uniform frequency grid")
    return float(d[0])


def _check(v: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    v = np.asarray(v)
    if v.ndim != 4 or v.shape[1] != np.asarray(freqs).size:
        raise ValueError(f"V: expected shape (n_real, N_f={np.asarray(freqs).size}, N_u, N_θ), got {v.shape}")
    return v


def spectral_weight(freqs: np.ndarray, band: Band | None = None) -> np.ndarray:
    """w(f) ≥ 0 (1/Hz): S(f) of `band`, else a Hann bump over [f_0 − δf, f_last + δf] with 2 Σ w δf = 1."""
    f = np.asarray(freqs, dtype=np.float64)
    if band is not None:
        return band.spectrum(f)
    df = _step(f)
    x = (f - f[0] + df) / (f[-1] - f[0] + 2 * df)
    w = np.sin(np.pi * x) ** 2
    return w / (2 * w.sum() * df)


def time_signal(v: np.ndarray, freqs: np.ndarray, weight: np.ndarray, pad: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Analytic RF signal m(t) = 2 ∫_{f>0} w(f) V(f) e^{i2πft} df on t_j = j/(L δf), L = pad·N_f (one period
    1/δf, carrier removed: |m| is exact). Returns t (L,) and m (n_real, L, N_u, N_θ) complex64; the real
    RF is Re(m e^{i2πf_0 t}), so its mean square is ½⟨|m|²⟩."""
    v = _check(v, freqs)
    df = _step(freqs)
    n_f = v.shape[1]
    n_t = pad * n_f
    x = (v * (2 * df * np.asarray(weight))[None, :, None, None]).astype(np.complex64)
    m = np.fft.ifft(x, n=n_t, axis=1) * n_t
    return np.arange(n_t) / (n_t * df), m.astype(np.complex64)


def _gate(t: np.ndarray, gate: tuple[float, float], taper: float) -> np.ndarray:
    """1 on [t1, t2], cosine flanks of `taper` seconds outside it, 0 beyond."""
    t1, t2 = gate
    if not t2 > t1:
        raise ValueError(f"gate: expected t1 < t2 (seconds), got {gate}")
    g = ((t >= t1) & (t <= t2)).astype(np.float64)
    if taper > 0:
        for edge, sgn in ((t1, -1), (t2, 1)):
            d = sgn * (t - edge)
            on = (d > 0) & (d < taper)
            g[on] = 0.5 + 0.5 * np.cos(np.pi * d[on] / taper)
    return g


def gate_spectra(
    v: np.ndarray, freqs: np.ndarray, gate: tuple[float, float], taper: float = 1e-6, pad: int = 4
) -> np.ndarray:
    """V restricted to arrival times in `gate` (s): inverse DFT over the band (no weight), multiply by the gate
    (cosine flanks `taper` s wide), DFT back onto the same frequencies. Same shape as V."""
    v = _check(v, freqs)
    df = _step(freqs)
    n_f = v.shape[1]
    n_t = pad * n_f
    t = np.arange(n_t) / (n_t * df)
    y = np.fft.ifft(v, n=n_t, axis=1)
    y *= _gate(t, gate, taper)[None, :, None, None]
    return np.fft.fft(y, axis=1)[:, :n_f].astype(np.complex64)


def time_envelope(
    v: np.ndarray, freqs: np.ndarray, band: Band | None = None, pad: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """Mean-square RF ⟨r²⟩(t) = ½⟨|m(u, θ, t)|²⟩ averaged over elements, transmits and realisations, with m the
    analytic signal of w(f)V(f) (`time_signal`; w = S(f) of `band` or a Hann bump). Returns (t, intensity)
    over one period 1/δf; relative to the incident pulse's peak² when w = S."""
    t, m = time_signal(v, freqs, spectral_weight(freqs, band), pad)
    return t, 0.5 * np.mean(np.abs(m) ** 2, axis=(0, 2, 3))


def energy_before(t: np.ndarray, env: np.ndarray, t_cut: float) -> float:
    """Share of the record's energy Σ⟨r²⟩ that arrives before t_cut (s), from `time_envelope`'s (t, intensity).
    Before the earliest path through the medium it is what the record's period wraps round from late times
    (1/δf) plus whatever a model puts there that no path allows (its precursor)."""
    t, env = np.asarray(t, dtype=np.float64), np.asarray(env, dtype=np.float64)
    if t.shape != env.shape or t.ndim != 1:
        raise ValueError(f"env: expected the shape of t {t.shape}, got {env.shape}")
    total = float(env.sum())
    if not total > 0:
        raise ValueError("env: expected a positive total energy")
    return float(env[t < t_cut].sum()) / total


def frequency_correlation_width(
    v: np.ndarray, freqs: np.ndarray, gate: tuple[float, float], taper: float = 1e-6, central: float = 0.5
) -> dict[str, np.ndarray | float]:
    """Half-width δf_½ of the frequency correlation of the background arriving within `gate` (s).

    C(Δf) = Σ_f ⟨V_g(f) V_g*(f + Δf)⟩ / √(Σ_f ⟨|V_g(f)|²⟩ Σ_f ⟨|V_g(f + Δf)|²⟩), with V_g the gated spectra of
    w(f)V(f) (Hann w over the frequencies given, `gate_spectra`), ⟨⟩ over elements, transmits, realisations,
    and f restricted to the central part of the band where w ≥ `central`·max w. δf_½ is the smallest Δf
    with |C(Δf)| ≤ 1/2 (linear interpolation). For a field whose intensity decays as e^{−t/τ} from the
    gate's start (gate ≫ τ), |C| = (1 + (2πΔfτ)²)^{−1/2} and δf_½ = √3/(2πτ).
    Returns width (Hz), dfs (Hz) and corr (|C|).
    """
    v = _check(v, freqs)
    df = _step(freqs)
    w = spectral_weight(freqs)
    vg = gate_spectra(v * w[None, :, None, None], freqs, gate, taper)
    idx = np.nonzero(w >= central * w.max())[0]
    lo, hi = idx[0], idx[-1]
    n_lag = hi - lo
    corr = np.empty(n_lag)
    p = np.mean(np.abs(vg) ** 2, axis=(0, 2, 3))
    for lag in range(n_lag):
        a = vg[:, lo : hi + 1 - lag]
        b = vg[:, lo + lag : hi + 1]
        num = np.abs(np.mean(a * np.conj(b), axis=(0, 2, 3)).sum())
        corr[lag] = num / np.sqrt(p[lo : hi + 1 - lag].sum() * p[lo + lag : hi + 1].sum())
    dfs = np.arange(n_lag) * df
    below = np.nonzero(corr <= 0.5)[0]
    if below.size == 0:
        width = float("nan")
    else:
        j = below[0]
        width = float(dfs[j - 1] + (corr[j - 1] - 0.5) / (corr[j - 1] - corr[j]) * df)
    return {"width": width, "dfs": dfs, "corr": corr}


def _out_grid(sines: np.ndarray, dim: int, extent: float) -> np.ndarray:
    """Output sines b on the transmit lattice refined 2×, containing every −a, out to max|a| + extent (|b| < 0.95)."""
    s = np.asarray(sines, dtype=np.float64)
    axes = []
    for d in range(dim - 1):
        u = np.unique(np.round(s[:, d], 12))
        step = float(np.min(np.diff(u))) / 2 if u.size > 1 else 0.02
        m = int(np.ceil((np.max(np.abs(u)) + extent) / step))
        axes.append(np.arange(-m, m + 1) * step)
    if dim == 2:
        b = np.stack([axes[0], np.zeros_like(axes[0])], axis=1)
    else:
        yy, xx = np.meshgrid(axes[1], axes[0], indexing="ij")
        b = np.stack([xx.ravel(), yy.ravel()], axis=1)
    return b[np.hypot(b[:, 0], b[:, 1]) < 0.95]  # propagating directions only


def _project(v_f: np.ndarray, k: float, phase: np.ndarray) -> np.ndarray:
    """One frequency's outputs on upgoing plane waves b: R(b, a) = Σ_u V(u, a) e^{+ik b·u} (the conjugate of the
    code's upgoing wave e^{−ik b·u}); v_f (n_real, N_u, N_θ), phase = b·u (N_b, N_u) → (n_real, N_b, N_θ)."""
    return np.matmul(np.exp(1j * k * phase).astype(np.complex64)[None], v_f)


def plane_wave_outputs(
    v: np.ndarray, freqs: np.ndarray, elements: np.ndarray, out_sines: np.ndarray, c0: float
) -> np.ndarray:
    """R(f, b, a) = Σ_u V(f, u, a) e^{+ik b·u} (`_project`) for outputs b in `out_sines`: (n_real, N_f, N_b, N_θ)
    complex64."""
    v = _check(v, freqs)
    k = 2 * np.pi * np.asarray(freqs, dtype=np.float64) / c0
    ph = np.asarray(out_sines, dtype=np.float64)[:, :2] @ np.asarray(elements, dtype=np.float64)[:, :2].T
    out = np.empty((v.shape[0], k.size, ph.shape[0], v.shape[3]), dtype=np.complex64)
    for m in range(k.size):
        out[:, m] = _project(v[:, m], float(k[m]), ph)
    return out


def memory_correlation(r: np.ndarray, sines: np.ndarray, steps: tuple[int, ...] = (1, 2, 4)) -> dict[int, float]:
    """The angular memory effect (Feng, Kane, Lee & Stone, Phys. Rev. Lett. 61, 834 (1988); in reflection, a tilt
    δ of the incident wave tilts the scattered speckle by δ about the specular direction b = a): the correlation
    of the plane-wave matrix under a common tilt of its input and output by m steps of the transmit lattice
    along x,

        C(m) = |Σ R(b + mδ, a + mδ) R*(b, a)| / √(Σ|R(b + mδ, a + mδ)|² Σ|R(b, a)|²),

    over the pairs whose tilted partner is on the lattice, frequencies and realisations. r: (n_real, N_f, N_θ,
    N_θ) with outputs on the transmits' own sines `sines` (N_θ, 2). 1 for a shift-invariant matrix R(b − a);
    ≈ 0 for independent entries (≈ 1/√n for n terms)."""
    r = np.asarray(r)
    s = np.asarray(sines, dtype=np.float64)
    n = s.shape[0]
    if r.ndim != 4 or r.shape[2:] != (n, n):
        raise ValueError(f"r: expected shape (n_real, N_f, {n}, {n}), got {r.shape}")
    ux = np.unique(np.round(s[:, 0], 12))
    if ux.size < 2:
        raise ValueError("sines: expected at least two distinct x sines")
    dx = float(np.min(np.diff(ux)))
    out: dict[int, float] = {}
    for m in steps:
        target = s + np.array([m * dx, 0.0])
        dist = np.linalg.norm(s[None, :, :] - target[:, None, :], axis=2)
        partner = np.argmin(dist, axis=1)
        ok = np.flatnonzero(dist[np.arange(n), partner] < 1e-6 * max(dx, 1e-12))
        if ok.size == 0:
            continue
        a = r[:, :, ok[:, None], ok[None, :]]
        b = r[:, :, partner[ok][:, None], partner[ok][None, :]]
        num = abs(np.sum(b * np.conj(a)))
        out[m] = float(num / np.sqrt(np.sum(np.abs(a) ** 2) * np.sum(np.abs(b) ** 2)))
    return out


def cbs_enhancement(
    v: np.ndarray,
    freqs: np.ndarray,
    elements: np.ndarray,
    sines: np.ndarray,
    c0: float,
    dim: int,
    gate: tuple[float, float] | None = None,
    q_out: float = 0.2,
    bin_width: float | None = None,
    out_sines: np.ndarray | None = None,
) -> dict[str, np.ndarray | float]:
    """Coherent-backscattering cone of the background in the plane-wave basis.

    Outputs are projected onto upgoing plane waves b with R(f, b, a) = Σ_u V(f, u, a) e^{+ik b·u} (the
    conjugate of the code's upgoing wave e^{−ik b·u}); transmit a is specular at b = a and exactly
    retro-reflected at b = −a. P(b, a) = ⟨|R|²⟩ over frequencies and realisations (after the time `gate`,
    if given, to keep multiple scattering). The angular envelope is divided out as a product
    E_out(b) E_in(a) fitted on the pairs outside the cone (|b + a| > q_out): E_out(b) = mean over those a of
    P, E_in(a) = mean over those b of P/E_out. The cone profile is the mean of P/(E_out E_in) in bins of
    |q| = |b + a| (bin_width, default the b step), normalised by its mean outside the cone; the
    enhancement is its value at q = 0 (pairs b = −a exactly; about 2 for reciprocal multiple scattering).
    `enhancement_ladder` divides it instead by the ladder extrapolated to q = 0 from a Gaussian fit of the
    profile over q_out < q < 3 q_out: the cone's height where the envelope is not separable (`flatness`).

    `flatness`: the rms deviation of the profile from 1 outside the cone (|q| > q_out); well above ~0.1 the
    envelope is not separable (e.g. a small array seeing the medium in its far field, where the intensity
    depends on b + a over the whole range) and the enhancement is not a cone height.

    Reciprocity: Q(a', a) = R(−a', a)/c_a (c = cosine; the obliquity of a transmit synthesised by the
    array, bench/foldy_lax_reference.py) is symmetric for a reciprocal medium; `reciprocity` is
    |Σ_{a≠a'} Q Q^T*| / Σ_{a≠a'} |Q|² over frequencies and realisations (1: symmetric; ≈ 0: independent).

    `enhancement_se`, `enhancement_ladder_se`: jackknife standard errors over the realisations (each left out in
    turn; NaN with fewer than 3).
    """
    v = _check(v, freqs)
    if gate is not None:
        v = gate_spectra(v, freqs, gate)
    s = np.asarray(sines, dtype=np.float64)
    b = _out_grid(s, dim, 2 * q_out) if out_sines is None else np.asarray(out_sines, dtype=np.float64)
    k = 2 * np.pi * np.asarray(freqs, dtype=np.float64) / c0
    el = np.asarray(elements, dtype=np.float64)[:, :2]
    ph = b @ el.T  # (N_b, N_u)
    p = np.zeros((v.shape[0], b.shape[0], s.shape[0]))  # per realisation, summed over frequencies
    n_a = s.shape[0]
    # index of −a in b
    ret = np.array([int(np.argmin(np.linalg.norm(b + a[None, :], axis=1))) for a in s])
    exact = np.allclose(b[ret], -s, atol=1e-9)
    qq = np.zeros((n_a, n_a), dtype=np.complex128)
    cos_a = np.sqrt(1.0 - s[:, 0] ** 2 - s[:, 1] ** 2)
    num = 0.0 + 0.0j
    den = 0.0
    for m in range(k.size):
        r = _project(v[:, m], float(k[m]), ph)  # (n_real, N_b, N_θ)
        p += np.abs(r) ** 2
        if exact:
            qq = r[:, ret, :] / cos_a[None, None, :]
            off = ~np.eye(n_a, dtype=bool)
            num += np.sum((qq * np.conj(np.swapaxes(qq, 1, 2)))[:, off])
            den += float(np.sum(np.abs(qq[:, off]) ** 2))
    q = np.linalg.norm(b[:, None, :] + s[None, :, :], axis=2)  # (N_b, N_θ)
    bw = bin_width if bin_width is not None else float(np.min(np.diff(np.unique(np.round(b[:, 0], 12)))))
    total = p.sum(axis=0)
    cone = _cone(total, q, ret, q_out, bw)
    # Jackknife over the realisations (each left out in turn): the enhancements' standard errors.
    n_real = p.shape[0]
    se = {"enhancement": float("nan"), "enhancement_ladder": float("nan")}
    if n_real >= 3:
        loo = [_cone(total - p[r], q, ret, q_out, bw) for r in range(n_real)]
        for key in se:
            x = np.array([c[key] for c in loo])
            se[key] = float(np.sqrt((n_real - 1) / n_real * np.sum((x - x.mean()) ** 2)))
    rec = float(abs(num) / den) if exact and den > 0 else float("nan")
    return {
        **cone,
        "enhancement_se": se["enhancement"],
        "enhancement_ladder_se": se["enhancement_ladder"],
        "reciprocity": rec,
    }


def cbs_ladder_bound(wavelength: float, aperture: float) -> float:
    """|b + a| beyond which `cbs_enhancement`'s profile is the ladder (its q_out): outside the cone and twice the
    aperture's angular resolution λ/D, at least 0.2."""
    return max(0.2, 2 * wavelength / aperture)


def _cone(p: np.ndarray, q: np.ndarray, ret: np.ndarray, q_out: float, bw: float) -> dict[str, Any]:
    """`cbs_enhancement`'s cone from P(b, a) (N_b, N_θ) summed over realisations and frequencies: the envelope
    E_out(b) E_in(a) divided out, the profile in bins of |b + a|, its value at b = −a over the mean outside the
    cone and over the Gaussian ladder's extrapolation to q = 0."""
    n_a = p.shape[1]
    outside = q > q_out
    e_out = np.array([p[i, outside[i]].mean() if outside[i].any() else np.nan for i in range(p.shape[0])])
    ratio = p / e_out[:, None]
    e_in = np.array([np.nanmean(ratio[outside[:, j], j]) for j in range(n_a)])
    pn = ratio / e_in[None, :]
    edges = np.arange(0.0, q.max() + bw, bw) + 0.5 * bw
    edges = np.concatenate([[0.0], edges])
    centres, profile = [], []
    valid = np.isfinite(pn)
    for lo_, hi_ in zip(edges[:-1], edges[1:], strict=True):
        sel = valid & (q >= lo_) & (q < hi_)
        if sel.any():
            centres.append(float(q[sel].mean()))
            profile.append(float(pn[sel].mean()))
    base = float(np.nanmean(pn[valid & outside]))
    prof = np.array(profile) / base
    peak = float(np.nanmean(pn[ret, np.arange(n_a)]) / base)
    qc = np.array(centres)
    flat = float(np.std(prof[qc > q_out])) if np.any(qc > q_out) else float("nan")
    # Over a ladder that depends on q (a small array, which sees the halo's lateral profile through b + a):
    # ln(profile) fitted linearly in q² over q_out < q < 3 q_out (a Gaussian ladder), extrapolated to q = 0.
    fit = (qc > q_out) & (qc < 3 * q_out) & (prof > 0)
    ladder0 = float(np.exp(np.polyfit(qc[fit] ** 2, np.log(prof[fit]), 1)[1])) if fit.sum() >= 3 else float("nan")
    return {
        "enhancement": peak,
        "enhancement_ladder": peak / ladder0,
        "ladder0": ladder0,
        "q": qc,
        "profile": prof,
        "flatness": flat,
    }


def confocal_background(
    v: np.ndarray,
    freqs: np.ndarray,
    elements: np.ndarray,
    sines: np.ndarray,
    c0: float,
    dim: int,
    points: np.ndarray,
    band: Band | None = None,
    per_realisation: bool = False,
) -> np.ndarray:
    """Confocal intensity ⟨|B(r)|²⟩ over realisations at `points` (N_p, 3), by delay-and-sum in the element
    basis, B(r) = Σ_{f,u,θ} w(f) V(f, u, θ) e^{+ik(|u − r| + a_θ·ρ + c_θ z)} — the focusing phase of
    docs/design.md §4.3 (paper eq. confocal, Supplementary S4 eq. mean_intensity) without apodization:
    `focused_background` with the same point in and out. Returns (N_p,), or |B|² of each realisation
    (n_real, N_p) with `per_realisation`."""
    return focused_background(v, freqs, elements, sines, c0, dim, points, points, band, per_realisation)


def focused_background(
    v: np.ndarray,
    freqs: np.ndarray,
    elements: np.ndarray,
    sines: np.ndarray,
    c0: float,
    dim: int,
    points_in: np.ndarray,
    points_out: np.ndarray,
    band: Band | None = None,
    per_realisation: bool = False,
) -> np.ndarray:
    """The focused reflection matrix's intensity ⟨|R(r_in, r_out)|²⟩ over realisations for pairs of points
    (N_p, 3) each: the transmits focused at r_in, the receive at r_out, R = Σ_{f,u,θ} w(f) V(f, u, θ)
    e^{+ik(|u − r_out| + a_θ·ρ_in + c_θ z_in)} (the focused basis of Lambert et al., PNAS 117, 14645 (2020);
    r_in = r_out is the confocal image, `confocal_background`). Returns (N_p,), or (n_real, N_p)."""
    v = _check(v, freqs)
    w = spectral_weight(freqs, band)
    k = 2 * np.pi * np.asarray(freqs, dtype=np.float64) / c0
    p_in, p_out = np.asarray(points_in, dtype=np.float64), np.asarray(points_out, dtype=np.float64)
    if p_in.shape != p_out.shape:
        raise ValueError(f"points_out: expected the shape of points_in {p_in.shape}, got {p_out.shape}")
    el = np.asarray(elements, dtype=np.float64)
    if dim == 2:
        d_out = np.hypot(p_out[:, None, 0] - el[None, :, 0], p_out[:, None, 2] - el[None, :, 2])
    else:
        d_out = np.linalg.norm(p_out[:, None, :] - el[None, :, :], axis=2)
    s = np.asarray(sines, dtype=np.float64)
    c = np.sqrt(1.0 - s[:, 0] ** 2 - s[:, 1] ** 2)
    d_in = p_in[:, :2] @ s.T + p_in[:, 2:3] * c[None, :]  # (N_p, N_θ)
    acc = np.zeros((v.shape[0], p_in.shape[0]), dtype=np.complex128)
    for m in range(k.size):
        e_out = np.exp(1j * k[m] * d_out).astype(np.complex64)
        e_in = (w[m] * np.exp(1j * k[m] * d_in)).astype(np.complex64)
        y = np.matmul(e_out[None], v[:, m])  # (n_real, N_p, N_θ)
        acc += np.sum(y * e_in[None], axis=2)
    return np.abs(acc) ** 2 if per_realisation else np.mean(np.abs(acc) ** 2, axis=0)


def focused_profile(
    v: np.ndarray,
    freqs: np.ndarray,
    elements: np.ndarray,
    sines: np.ndarray,
    c0: float,
    dim: int,
    depth: float,
    separations: np.ndarray,
    half_width: float,
    n_lateral: int = 9,
    band: Band | None = None,
) -> np.ndarray:
    """⟨|R(r_in, r_out)|²⟩ at one depth against the in–out separation Δx along x (`focused_background`),
    averaged over `n_lateral` midpoints in |x| ≤ half_width (y = 0): (N_Δ,). Multiple scattering spreads
    the focused matrix over Δx like its diffuse halo; the confocal image is Δx = 0."""
    xm = np.linspace(-half_width, half_width, n_lateral)
    dx = np.asarray(separations, dtype=np.float64)
    x_in, x_out = (xm[None, :] - dx[:, None] / 2).ravel(), (xm[None, :] + dx[:, None] / 2).ravel()
    zeros, z = np.zeros_like(x_in), np.full_like(x_in, depth)
    p_in, p_out = np.stack([x_in, zeros, z], axis=1), np.stack([x_out, zeros, z], axis=1)
    # every separation's pairs in one pass over the frequencies
    each = focused_background(v, freqs, elements, sines, c0, dim, p_in, p_out, band)
    return each.reshape(dx.size, xm.size).mean(axis=1)


def confocal_profile(
    v: np.ndarray,
    freqs: np.ndarray,
    elements: np.ndarray,
    sines: np.ndarray,
    c0: float,
    dim: int,
    depths: np.ndarray,
    half_width: float,
    n_lateral: int = 9,
    band: Band | None = None,
) -> np.ndarray:
    """|B|² of each realisation (n_real, N_z) at each depth, averaged over `n_lateral` points in |x| ≤ half_width
    (2D, y = 0) or over the n_lateral × n_lateral patch |x|, |y| ≤ half_width (3D) (`confocal_background`)."""
    z = np.asarray(depths, dtype=np.float64)
    x = np.linspace(-half_width, half_width, n_lateral)
    if dim == 3:
        yy, xx, zz = np.meshgrid(x, x, z, indexing="ij")
    else:
        xx, zz = np.meshgrid(x, z, indexing="ij")
        yy = np.zeros_like(xx)
    pts = np.stack([xx.ravel(), yy.ravel(), zz.ravel()], axis=1)
    each = confocal_background(v, freqs, elements, sines, c0, dim, pts, band, per_realisation=True)
    return each.reshape(each.shape[0], -1, z.size).mean(axis=1)


def confocal_contrast_slope(
    v: np.ndarray,
    freqs: np.ndarray,
    elements: np.ndarray,
    sines: np.ndarray,
    c0: float,
    dim: int,
    depths: np.ndarray,
    echo: np.ndarray,
    fit: tuple[float, float],
    half_width: float,
    n_lateral: int = 9,
    band: Band | None = None,
) -> dict[str, np.ndarray | float]:
    """d ln C_I/dz with C_I(z) = echo(z)/I_M(z) (paper main text eq. ball, Supplementary S4 eq. contrast_confocal).

    echo(z): confocal intensity of a reference point reflector at depth z seen through the medium (any
    scale), e.g. |⟨ψ⟩(z)|⁴ from the coherent wave (paper S1) or the model's e^{−2z/ℓ_ext};
    I_M(z): the background's confocal intensity averaged at each depth over `n_lateral` points in
    |x| ≤ half_width (2D), or over the n_lateral × n_lateral patch |x|, |y| ≤ half_width (3D: the speckle
    cells of both lateral axes; `confocal_profile`). The slope is the least-squares line of ln C_I over the
    depths within `fit` = (z1, z2) (m, absolute depths below the array); the paper's law C_I ∝ e^{−z/ℓ_s}
    gives slope = −1/ℓ_s. Returns slope (1/m), its jackknife standard error over the realisations
    `slope_se` (leave one out: √((n−1)/n Σ (s_i − s̄)²); NaN for one realisation), depths, ci, background,
    echo, and `each`, the per-realisation background profiles (`slope_over` refits them on other depths).
    """
    z = np.asarray(depths, dtype=np.float64)
    e = np.asarray(echo, dtype=np.float64)
    if e.shape != z.shape:
        raise ValueError(f"echo: expected one value per depth ({z.size}), got shape {e.shape}")
    each = confocal_profile(v, freqs, elements, sines, c0, dim, z, half_width, n_lateral, band)
    bg = each.mean(axis=0)
    ci = e / bg
    sel = (z >= fit[0]) & (z <= fit[1])
    if sel.sum() < 3:
        raise ValueError(f"fit: expected at least 3 depths in {fit}, got {int(sel.sum())}")

    def fitted(background: np.ndarray) -> float:
        return float(np.polyfit(z[sel], np.log(e[sel] / background[sel]), 1)[0])

    return {
        "slope": fitted(bg),
        "slope_se": jackknife_se(fitted, each),
        "depths": z,
        "ci": ci,
        "background": bg,
        "echo": e,
        "each": each,
    }


def slope_over(ci: dict, fit: tuple[float, float]) -> tuple[float, float]:
    """(slope, jackknife standard error) of ln C_I refitted over the depths within `fit` = (z1, z2), from a
    `confocal_contrast_slope` result: the law's rate over another depth range (the exact one is a depth mean)."""
    z, e, each = ci["depths"], ci["echo"], ci["each"]
    sel = (z >= fit[0]) & (z <= fit[1])
    if sel.sum() < 3:
        raise ValueError(f"fit: expected at least 3 depths in {fit}, got {int(sel.sum())}")

    def fitted(background: np.ndarray) -> float:
        return float(np.polyfit(z[sel], np.log(e[sel] / background[sel]), 1)[0])

    return fitted(each.mean(axis=0)), jackknife_se(fitted, each)


def jackknife_se(statistic: Callable[[np.ndarray], float], each: np.ndarray) -> float:
    """Jackknife standard error of statistic(mean of `each` over its first axis, the realisations): with s_i
    the statistic of the mean leaving realisation i out, √((n−1)/n Σ (s_i − s̄)²) (Efron's delete-one
    jackknife); NaN for one realisation."""
    x = np.asarray(each, dtype=np.float64)
    n = x.shape[0]
    if n < 2:
        return float("nan")
    total = x.sum(axis=0)
    loo = np.array([statistic((total - x[i]) / (n - 1)) for i in range(n)])
    return float(np.sqrt((n - 1) / n * np.sum((loo - loo.mean()) ** 2)))
