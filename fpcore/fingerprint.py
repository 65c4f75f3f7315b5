"""Fingerprint operators F_θθ(r0, f): from a calibration acquisition or from a numerical model.

Calibration pipeline (paper, Methods "Fingerprint operator based on a calibration measurement";
docs/design.md §4.4):

1. time gate after the ballistic echo of the target's front face (paper eq. specular_filter):
   R0'(u, θ, t) = R0(u, θ, t) H(t − τ_in(θ, r0) − τ_out(u, r0) − δt), δt ≈ 1/Δf, with
   τ_out = |u − (x0, y0, z0 − d/2)|/c0 and τ_in = [x0 s_x + y0 s_y + (z0 − d/2) c]/c0;
2. SVD at each frequency, keep σ_p ≥ threshold·σ_1 (paper: 0.4) and whiten (paper eqs. svd, finger):
   F(r0, f) = Σ_{p ≤ N_S} U_p V_p^†;
3. output projection to plane waves F_θθ = P_θu F_uθ (paper, Methods "Virtual shift");
4. angular filter A(θ, r0): drop plane-wave components whose ray through the target misses the array
   (paper Supplementary S2, Fig. S9).

Numerical fingerprints (paper, Methods "Numerical computation"; docs/design.md §4.5): for a reflectivity
Γ(q) on points r', F_θθ(o, i, f) = Σ_{r'} Γ(r') e^{-iK·r'}, K = k(s_o + s_i, c_o + c_i) — the plane-wave
form of G Γ Gᵀ P†. A straight mirror of length L along t̂ centred at r_c has the closed form
F = L sinc(K·t̂ L / 2π) e^{-iK·r_c} (np.sinc(x) = sin πx / πx).

Virtual shift (paper eq. BF; docs/design.md §4.6): F(r) = S ∘ F(r0) ∘ S with S = P(θ, Δr) = e^{-ik(s·Δρ + cΔz)}
(the sign that makes γ computed on R = R0 peak at r0 with numpy's FFT; tests/test_fingerprint.py).
The shift is applied without apodization, so ‖F(r)‖ = ‖F(r0)‖: the angular filter A is applied at r0
only. `angular_mask` exposes A(θ, r) for callers that tile the field of view.

Motion-aware fingerprints (paper, Discussion: "the fingerprint could be parameterised by the target's
velocity"): transmits fire in sequence, so a target moving at v is at r + v τ_j when transmit j
insonifies it (τ_j relative to the sequence's middle). Its echo to transmit j is the fingerprint
shifted by δ_j = v τ_j on both ends — the same virtual shift as above, applied per transmit column:
F_v(f, o, j) = e^{-ik(s_o·δρ_j + c_o δz_j)} F(f, o, j) e^{-ik(s_j·δρ_j + c_j δz_j)}. Motion during one
echo's reception (tens of µs) and the Doppler scaling of the band (v/c0 ≲ 1e-3) are neglected.
`moving_fingerprint` builds F_v; a set of them over velocities is a `Dictionary` whose per-pixel
argmax estimates v (see bench/validate_motion.py).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .acquisition import Acquisition, PlaneWaveData, Probe, Spectrum, to_plane_waves
from .geometry import cosines, from_xyz, mirror_direction
from .kernel import wavevectors

__all__ = [
    "Fingerprint",
    "time_gate",
    "whiten",
    "angular_mask",
    "from_calibration",
    "point_fingerprint",
    "mirror_fingerprint",
    "check_geometry",
    "moving_fingerprint",
    "motion_ramp",
]

_TOKENS = itertools.count(1)  # Fingerprint.token


@dataclass
class Fingerprint:
    """F_θθ(r0, f): complex (N_f, N_o, N_i) in the plane-wave basis at both ends.

    provenance: "calibration" or "model:<kind>"; state: the parameters q (size, orientation, …);
    n_s: effective rank N_S (mean over frequency of the kept singular values); singular_values:
    normalised σ_p/σ_1 per frequency for calibration fingerprints. token: an identity unique within the
    process and never reused (unlike ``id``), on which caches (`Imager` templates) key: treat the arrays
    as immutable and build a new Fingerprint (e.g. ``dataclasses.replace``) to change one.
    """

    data: np.ndarray
    freqs: np.ndarray
    out_sines: np.ndarray
    in_sines: np.ndarray
    c0: float
    r0: np.ndarray
    name: str = "target"
    provenance: str = "model"
    state: dict[str, Any] = field(default_factory=dict)
    n_s: float = 1.0
    singular_values: np.ndarray | None = None
    n_t: float | None = None
    token: int = field(default_factory=lambda: next(_TOKENS), init=False, repr=False, compare=False)

    @property
    def norm2(self) -> float:
        """Σ_f ‖F(f)‖²_F (the γ normalisation; docs/design.md §4.7)."""
        return float(np.vdot(self.data, self.data).real)

    def centred_conj(self, ndim: int) -> np.ndarray:
        """conj(F(r0)) e^{-iK·r0}, flattened (f, o, i): γ_num(r) = |Σ R · this · e^{iK·r}| (paper S7)."""
        K = wavevectors(self.freqs, self.out_sines, self.in_sines, self.c0, ndim)
        r0 = from_xyz(self.r0, ndim)
        return (np.conj(self.data).ravel() * np.exp(-1j * (K @ r0))).astype(np.complex64)

    def shifted(self, r: np.ndarray) -> np.ndarray:
        """F_θθ(r) = S(Δr) ∘ F(r0) ∘ S(Δr), S = e^{-ik(s·Δρ + cΔz)} (paper eq. BF, no apodization)."""
        dr = np.asarray(r, dtype=float) - self.r0
        k = 2 * np.pi * self.freqs / self.c0
        ramp_out = np.exp(-1j * k[:, None] * _path(self.out_sines, dr)[None, :, 0])
        ramp_in = np.exp(-1j * k[:, None] * _path(self.in_sines, dr)[None, :, 0])
        return (ramp_out[:, :, None] * self.data * ramp_in[:, None, :]).astype(np.complex64)


def _path(sines: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """s·Δρ + cΔz of each direction (N_s,) for each shift (M, 3) or (3,): (N_s, M) — the extra path of
    the plane wave s when the target moves by the shift (paper eq. BF's phase, over k)."""
    d = np.atleast_2d(np.asarray(shifts, dtype=float))
    c = cosines(sines)
    return sines[:, :1] * d[None, :, 0] + sines[:, 1:2] * d[None, :, 1] + c[:, None] * d[None, :, 2]


def motion_ramp(fp: Fingerprint, velocity: np.ndarray, transmit_times: np.ndarray) -> np.ndarray:
    """F_v / F, (N_f, N_o, N_i) complex: the phase of the per-transmit virtual shift δ_j = v τ_j (module doc)
    on the outgoing and incoming paths, for ``fp``'s geometry (:func:`moving_fingerprint`)."""
    v = np.asarray(velocity, dtype=float).reshape(3)
    tau = np.asarray(transmit_times, dtype=float).reshape(-1)
    if tau.size != fp.in_sines.shape[0]:
        raise ValueError(f"transmit_times: expected {fp.in_sines.shape[0]} values (one per transmit), got {tau.size}")
    k = 2 * np.pi * fp.freqs / fp.c0
    delta = tau[:, None] * v[None, :]  # (N_i, 3): where the target is when transmit j fires
    path = _path(fp.out_sines, delta) + np.diagonal(_path(fp.in_sines, delta))[None, :]  # (N_o, N_i)
    return np.exp(-1j * k[:, None, None] * path[None])


def moving_fingerprint(fp: Fingerprint, velocity: np.ndarray, transmit_times: np.ndarray) -> Fingerprint:
    """F_v: ``fp`` for a target moving at ``velocity`` (m/s, (v_x, v_y, v_z)) while the transmits fire
    at ``transmit_times`` (s, one per transmit, relative to the time the position refers to) — the
    per-transmit virtual shift δ_j = v τ_j of the module doc. state gains ``velocity_m_s``."""
    v = np.asarray(velocity, dtype=float).reshape(3)
    data = (fp.data * motion_ramp(fp, v, transmit_times)).astype(np.complex64)
    state = dict(fp.state, velocity_m_s=[float(x) for x in v])
    return Fingerprint(
        data,
        fp.freqs,
        fp.out_sines,
        fp.in_sines,
        fp.c0,
        fp.r0,
        name=fp.name,
        provenance=fp.provenance,
        state=state,
        n_s=fp.n_s,
        singular_values=fp.singular_values,
        n_t=fp.n_t,
    )


def check_geometry(fp: Fingerprint, pw: PlaneWaveData) -> None:
    """Raise ValueError naming the field if fp does not match the acquisition's plane-wave geometry."""
    if fp.data.shape != pw.data.shape:
        raise ValueError(
            f"fingerprint '{fp.name}': shape (N_f, N_o, N_i) = {fp.data.shape} does not match "
            f"the acquisition's {pw.data.shape} (band, output directions or plane waves differ)"
        )
    if not np.allclose(fp.freqs, pw.freqs, rtol=1e-9, atol=1e-3):
        raise ValueError(
            f"fingerprint '{fp.name}': frequencies differ from the acquisition's "
            "(same band, n_freq and sampling expected)"
        )
    if not np.allclose(fp.in_sines, pw.in_sines, atol=1e-9):
        raise ValueError(f"fingerprint '{fp.name}': transmit sines differ from the acquisition's sequence")
    if not np.allclose(fp.out_sines, pw.out_sines, atol=1e-9):
        raise ValueError(f"fingerprint '{fp.name}': output sines differ from the processor's")
    if abs(fp.c0 - pw.c0) > 1e-6 * pw.c0:
        raise ValueError(f"fingerprint '{fp.name}': c0 = {fp.c0} m/s, acquisition has {pw.c0} m/s")


def time_gate(acq: Acquisition, r0: np.ndarray, diameter: float, dt: float, taper: float = 0.0) -> Acquisition:
    """R0' = R0 · H(t − τ_in(θ, r0) − τ_out(u, r0) − δt) (paper eq. specular_filter).

    taper > 0 replaces the Heaviside step by a raised-cosine ramp of that duration (s) ending at the
    gate time; taper = 0 is the paper's hard gate.
    """
    r0 = np.asarray(r0, dtype=float)
    front = np.array([r0[0], r0[1], r0[2] - diameter / 2])
    u = acq.probe.positions
    tau_out = np.linalg.norm(u - front[None, :], axis=1) / acq.c0
    s = acq.sequence.sines
    c = np.sqrt(1 - s[:, 0] ** 2 - s[:, 1] ** 2)
    tau_in = (front[0] * s[:, 0] + front[1] * s[:, 1] + front[2] * c) / acq.c0
    t_gate = tau_out[:, None] + tau_in[None, :] + dt
    t = acq.times
    arg = t[None, None, :] - t_gate[:, :, None]
    if taper > 0:
        mask = np.clip((arg + taper) / taper, 0.0, 1.0)
        mask = 0.5 - 0.5 * np.cos(np.pi * mask)
    else:
        mask = (arg >= 0).astype(np.float32)
    return Acquisition(
        acq.rf * mask.astype(np.float32),
        acq.fs,
        acq.t0,
        acq.c0,
        acq.probe,
        acq.sequence,
        acq.frame_index,
        acq.timestamp,
        dict(acq.truth),
    )


def whiten(spec: Spectrum, threshold: float = 0.4) -> tuple[Spectrum, np.ndarray, np.ndarray]:
    """F(f) = Σ_{σ_p ≥ threshold σ_1} U_p V_p^† at each frequency (paper eqs. svd, finger).

    Returns the whitened spectrum, N_S(f) (kept singular values per frequency) and σ_p/σ_1 (N_f, r).
    """
    if not 0 < threshold <= 1:
        raise ValueError(f"svd_threshold: expected 0 < threshold <= 1, got {threshold}")
    u, s, vh = np.linalg.svd(spec.data, full_matrices=False)
    s1 = s[:, :1]
    rel = np.divide(s, s1, out=np.zeros_like(s), where=s1 > 0)
    keep = rel >= threshold
    n_s = keep.sum(axis=1)
    data = np.matmul(u * keep[:, None, :].astype(u.dtype), vh).astype(np.complex64)
    return Spectrum(data, spec.freqs, spec.c0, spec.probe, spec.sequence), n_s, rel


def angular_mask(sines: np.ndarray, r: np.ndarray, probe: Probe, margin: float = 0.0) -> np.ndarray:
    """A(θ, r) ∈ {0, 1}: 1 if the ray through r along θ meets the array (paper S2, Fig. S9).

    The ray along direction (s, c) through r = (ρ, z) crosses the array plane at ρ − z s/c (stationary
    phase of P_θu). margin widens the array on each side (e.g. the target radius).
    """
    s = np.asarray(sines, dtype=float)
    c = cosines(s)
    foot = np.asarray(r, dtype=float)[None, :2] - np.asarray(r)[2] * s / c[:, None]
    lo = probe.positions[:, :2].min(axis=0) - probe.pitch / 2 - margin
    hi = probe.positions[:, :2].max(axis=0) + probe.pitch / 2 + margin
    ok = (foot[:, 0] >= lo[0]) & (foot[:, 0] <= hi[0])
    if not probe.is_linear:
        ok &= (foot[:, 1] >= lo[1]) & (foot[:, 1] <= hi[1])
    return ok


def _aligned_energy(acq: Acquisition, point: np.ndarray) -> np.ndarray:
    """Σ over channels of the RF energy against time after the ballistic delay of `point` (τ_in + τ_out),
    on a buffer of 4 n_t samples whose index 2 n_t is that delay."""
    point = np.asarray(point, dtype=float)
    tau_out = np.linalg.norm(acq.probe.positions - point[None, :], axis=1) / acq.c0
    s = acq.sequence.sines
    tau_in = (point[0] * s[:, 0] + point[1] * s[:, 1] + point[2] * cosines(s)) / acq.c0
    shift = np.rint((tau_out[:, None] + tau_in[None, :] - acq.t0) * acq.fs).astype(int)
    n_t = acq.n_samples
    start = np.clip(2 * n_t - shift, 0, 3 * n_t).ravel()
    rf = acq.rf.reshape(-1, n_t)
    energy = np.zeros(4 * n_t)
    for a in range(0, rf.shape[0], 2048):
        e = rf[a : a + 2048].astype(np.float64) ** 2
        cols = start[a : a + 2048, None] + np.arange(n_t)[None, :]
        energy += np.bincount(cols.ravel(), weights=e.ravel(), minlength=4 * n_t)
    return energy


def effective_duration(acq: Acquisition, r0: np.ndarray, diameter: float) -> float:
    """Δt of the target echo: participation-ratio width of its energy envelope after aligning every
    channel on the front-face ballistic delay (paper: N_T ∼ Δf Δt, main text after eq. G)."""
    r0 = np.asarray(r0, dtype=float)
    energy = _aligned_energy(acq, np.array([r0[0], r0[1], r0[2] - diameter / 2]))
    total = energy.sum()
    if total <= 0:
        return 0.0
    return float(total**2 / (energy**2).sum() / acq.fs)


def first_arrival_diameter(acq: Acquisition, r0: np.ndarray, threshold_db: float = -20.0) -> float:
    """The diameter d that puts the time gate's front face r0 − d/2 at the echo's measured first arrival.

    A calibration is the target alone in water, so the first echo in the record is the target's nearest
    part: every channel aligned on r0's delay, energies summed and smoothed over one carrier period, the
    first echo is the peak of that profile within one pulse length (1/Δf) of its first rise above
    `threshold_db` of the global peak (its arrival time t_first: the pulse's centre, as for the
    ballistic delays). At normal incidence a front face d/2
    before r0 arrives d/c0 earlier (two ways), so d = −c0 t_first (≥ 0). Used when the diameter is
    unknown instead of d = 0, which cuts away everything of the target before its centre.
    """
    energy = _aligned_energy(acq, r0)
    if energy.max() <= 0:
        return 0.0
    width = max(int(round(acq.fs / max(acq.probe.centre_frequency, 1.0))), 1)
    smooth = np.convolve(energy, np.ones(width) / width, mode="same")
    i = int(np.nonzero(smooth >= smooth.max() * 10 ** (threshold_db / 10))[0][0])
    pulse = max(int(round(acq.fs / max(acq.probe.bandwidth, 1.0))), 1)  # one pulse length, 1/Δf
    i += int(np.argmax(smooth[i : i + pulse]))  # the first echo's peak, within one pulse of its rise
    t_first = (i - 2 * acq.n_samples) / acq.fs
    return float(max(-acq.c0 * t_first, 0.0))


def from_calibration(
    acq: Acquisition,
    r0: np.ndarray,
    out_sines: np.ndarray,
    band: tuple[float, float],
    n_freq: int | None = None,
    diameter: float | None = 0.0,
    svd_threshold: float = 0.4,
    gate_dt: float | None = None,
    angular_filter: bool = True,
    name: str = "target",
    gate: bool = True,
    whiten_modes: bool = True,
) -> Fingerprint:
    """Fingerprint from a calibration acquisition of the target alone at r0 (paper, Methods).

    band/n_freq/out_sines must be those the processor uses on the frames (checked at use).
    gate_dt defaults to 1/Δf (paper: δt ∼ 1/Δf). diameter None: measured from the calibration itself
    (`first_arrival_diameter`), so the gate sits after the echo's first arrival rather than at r0;
    gate=False keeps the whole record. whiten_modes=False keeps the time-filtered matrix itself, F = R0′
    (paper S2, Fig. S7a: every mode at its own singular value) instead of its whitened modes (eq. finger);
    N_S is counted at `svd_threshold` either way. Returns F_θθ(r0, f) with N_S and N_T filled in.
    """
    r0 = np.asarray(r0, dtype=float)
    if r0.shape != (3,):
        raise ValueError(f"r0: expected (x, y, z) in metres, got {r0}")
    if diameter is None:
        diameter = first_arrival_diameter(acq, r0)
    f_min, f_max = band
    dt = 1.0 / (f_max - f_min) if gate_dt is None else gate_dt
    gated = time_gate(acq, r0, diameter, dt) if gate else acq
    spec = gated.spectrum(f_min, f_max, n_freq)
    white, n_s_f, rel = whiten(spec, svd_threshold)
    pw = to_plane_waves(white if whiten_modes else spec, out_sines)
    data = pw.data
    if angular_filter:
        a_out = angular_mask(pw.out_sines, r0, acq.probe, margin=diameter / 2)
        a_in = angular_mask(pw.in_sines, r0, acq.probe, margin=diameter / 2)
        data = data * (a_out[None, :, None] & a_in[None, None, :])
    n_t = (f_max - f_min) * effective_duration(gated, r0, diameter)
    return Fingerprint(
        np.ascontiguousarray(data, dtype=np.complex64),
        pw.freqs,
        pw.out_sines,
        pw.in_sines,
        pw.c0,
        r0,
        name=name,
        provenance="calibration",
        state={
            "diameter_m": diameter,
            "svd_threshold": svd_threshold,
            "gate_dt_s": dt,
            "gate": "front" if gate else "none",
            "modes": "whitened" if whiten_modes else "R0' (not whitened)",
        },
        n_s=float(np.mean(n_s_f)),
        singular_values=rel.astype(np.float32),
        n_t=float(n_t),
    )


def point_fingerprint(
    freqs: np.ndarray,
    out_sines: np.ndarray,
    in_sines: np.ndarray,
    c0: float,
    r0: ArrayLike = (0.0, 0.0, 0.0),
    name: str = "point",
) -> Fingerprint:
    """Point reflector at r0: F = e^{-iK·r0} (Γ = δ(r − r0); paper, Methods "Numerical computation")."""
    r0 = np.asarray(r0, dtype=float)
    K3 = wavevectors(freqs, out_sines, in_sines, c0, 3)
    data = np.exp(-1j * (K3 @ r0)).reshape(len(freqs), len(out_sines), len(in_sines))
    return Fingerprint(
        data.astype(np.complex64),
        np.asarray(freqs, float),
        np.asarray(out_sines, float),
        np.asarray(in_sines, float),
        c0,
        r0,
        name=name,
        provenance="model:point",
    )


def mirror_response(K3: np.ndarray, length: float, alpha: float, azimuth: float = 0.0) -> np.ndarray:
    """∫_{-L/2}^{L/2} e^{-iK·l t̂} dl = L sinc(K·t̂ L / 2π) for a segment centred at the origin."""
    return sinc_segment(K3 @ mirror_direction(alpha, azimuth).astype(K3.dtype), length)


def sinc_segment(kt: np.ndarray, length: float) -> np.ndarray:
    """L sin(K_t L/2)/(K_t L/2): the segment integral as a function of the projection K_t = K·t̂."""
    x = kt * kt.dtype.type(length / 2)
    out = np.sin(x)
    zero = x == 0
    np.divide(out, x, out=out, where=~zero)
    out[zero] = 1.0
    out *= kt.dtype.type(length)
    return out


def mirror_fingerprint(
    freqs: np.ndarray,
    out_sines: np.ndarray,
    in_sines: np.ndarray,
    c0: float,
    length: float,
    alpha: float,
    r0: ArrayLike = (0.0, 0.0, 0.0),
    azimuth: float = 0.0,
    name: str = "mirror",
) -> Fingerprint:
    """Straight mirror (uniform reflectivity segment) of length L, orientation α, centred at r0.

    Closed form of P Γ Pᵀ for Γ on a segment (docs/design.md §4.5): F = L sinc(K·t̂ L/2π) e^{-iK·r0}.
    """
    r0 = np.asarray(r0, dtype=float)
    K3 = wavevectors(freqs, out_sines, in_sines, c0, 3)
    data = mirror_response(K3, length, alpha, azimuth) * np.exp(-1j * (K3 @ r0))
    return Fingerprint(
        data.reshape(len(freqs), len(out_sines), len(in_sines)).astype(np.complex64),
        np.asarray(freqs, float),
        np.asarray(out_sines, float),
        np.asarray(in_sines, float),
        c0,
        r0,
        name=name,
        provenance="model:mirror",
        state={"length_m": length, "alpha_rad": alpha, "azimuth_rad": azimuth},
        n_s=1.0,
    )
