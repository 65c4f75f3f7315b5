"""Lattice pre-sum kernel: the beamforming sum when the sines lie on one uniform grid (docs/design.md §5).

The sum is the one of every map (docs/design.md §5, `fpcore.kernel.GridTransform`):

    B(r) = Σ_j w_j exp(+i K_j·r),   K_j = k_f (s_o + s_i, c_o + c_i),   j = (f, o, i) in C order,

on a regular grid r = r_c + p·Δ (p = index − N//2 per axis). When, per lateral axis, the output and the
transmit sines lie on lattices of one common step, s_o = a_o + n_o δs and s_i = a_i + n_i δs (n
integers; a symmetric linspace has a half-step offset), a sample's lateral wavenumber is
K_x = k_f (a_o + a_i + m δs) with m = n_o + n_i an integer: all samples of one (f, m_x, m_y) share
their lateral phase exactly and differ only in depth. Hence, exactly,

    B(r) = Σ_f Σ_m e^{i k_f (a + m δs)·(r − r_c)_⊥} D_{f,m}(z − z_c),   D_{f,m}(ζ) = Σ_{(o,i)→m} w̃_j e^{iK_zj ζ},

with the separable ramp w̃_j = w_j e^{iK_j·r_c} = w_j P_fo Q_fi (P_fo = e^{ik_f (s_o, c_o)·r_c}).

1. Depth, the only non-uniform part (type-1 NUFFT per (f, m) row). Each sample is spread with an
   8-tap "exponential of semicircle" kernel φ (as finufft's; table + linear interpolation) onto a fine
   grid of n_z = σN_z wavenumber bins, h = 2π/n_z: b_{f,m}[l] = Σ_j w̃_j φ(u_j − l), u_j = K_zjΔz/h.
   Poisson summation gives D_{f,m}(pΔz) ≈ Σ_l b_{f,m}[l] e^{iphl} / φ̂(ph) for |p| ≤ N_z/2, the error
   ≈ 15 e^{−8π√(1−1/σ)} of the map maximum on speckle (σ from eps: 1.37 for 1e-4, measured ~2e-5).
   Only the bins under each frequency's K_z band are kept: L_f ≈ σN_z k_fΔz (max − min)(c_o + c_i)/2π
   + 8 bins (≈ 20 for the 3D benchmark against N_z = 64) — which is what makes the pre-sum pay.
2. Lateral, on the band bins: either exactly — per frequency a DFT in m with a frequency-dependent
   scale, e^{iθ_f,m p}, θ = k_f (a + m δs) Δ, split into cos/sin for p = ±q (even/odd: half the
   work), y then x — or by a type-1 NUFFT over the (f, m) points shared by all bins (each row spread
   in x (and y) onto σN uniform bins, then the same cos/sin synthesis with 1/φ̂). "auto" takes the
   cheaper: exact for the 3D benchmark, NUFFT for the 2D one (where the pre-sum hardly compresses).
   The exact DFT is taken about the lattice's centre, θ_m = θ_c + θ'_m with θ'_m = (m − (M−1)/2) k_f δs Δ
   symmetric: Σ_m e^{iθ_m p} G_m = e^{iθ_c p} [Σ_j cos(θ'_j q)(G_j + G_{M−1−j}) ± i Σ_j sin(θ'_j q)(G_j −
   G_{M−1−j})] for p = ±q — a butterfly, then half the products (`loops.lateral_sym`), four q per row
   loaded and column blocks kept in cache. Pairs of lattice rows that hold no sample are skipped: a
   fingerprint's angular support leaves ~80 % of the output directions with zero weight (γ's numerator
   and the null level's sum), so ~75 % of the y rows and ~50 % of the x rows. Each frequency is spread
   and transformed in one thread's cache-sized block (`loops.exact_fused`; no (f, m, l) array for all).
3. Depth synthesis: band bins → N_z depths with e^{iphl}/φ̂(ph).

Everything geometric (lattice indices, ramps, fixed-point bin positions, cos/sin tables) is built once
per geometry and grid; per frame only the weights change. The per-frame path is numba code
(`fpcore.kernel_presum_loops`: single precision, AVX-vectorized inner loops) run on a few Python
threads, each on its own frequencies or rows: no BLAS and no numba/OpenMP pool, whose spinning workers
fight over a 2-core machine. A transform holds its buffers: call one instance from one thread at a time.
"""

from __future__ import annotations

import math
from functools import partial

import numpy as np

from . import kernel_presum_loops as loops
from .geometry import cosines
from .grid import Grid
from .kernel import default_threads
from .kernel_presum_loops import FRAC, N_TABLE, TAPS, pool, split, u64

__all__ = ["PresumTransform", "lattice"]

_REL_TOL = 1e-9
_MAX_LATTICE = 1 << 14  # largest lattice extent (in steps δs) accepted per axis
_TAPS = TAPS  # taps stored per sample: one AVX vector (`loops.taps8`); the kernel's width is ≤ 8
_BLOCK = 2048  # columns (floats) of the lattice rows transformed together by the exact lateral DFTs (L2-sized)


# ------------------------------------------------------------------------------------------------
# lattice detection


def _as_sines(s: np.ndarray) -> np.ndarray:
    s = np.asarray(s, dtype=np.float64)
    if s.ndim == 1:
        s = np.stack([s, np.zeros_like(s)], axis=1)
    if s.ndim != 2 or s.shape[1] != 2 or s.shape[0] < 1:
        raise ValueError(f"sines: expected shape (N, 2) or (N,), got {s.shape}")
    return s


def _axis_lattice(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float] | None:
    """(δs, a0, b0) with a = a0 + n δs and b = b0 + n' δs (n, n' ≥ 0 integers), or None."""
    tol = _REL_TOL * max(1.0, float(np.max(np.abs(a))), float(np.max(np.abs(b))))
    a0, b0 = float(a.min()), float(b.min())
    d = np.concatenate([a - a0, b - b0])
    pos = d[d > tol]
    if pos.size == 0:  # one value per set
        return 1.0, a0, b0
    dmin, dmax = float(pos.min()), float(d.max())
    for q in range(1, _MAX_LATTICE + 1):  # δs = dmin/q, the largest step that fits
        if dmax * q / dmin > _MAX_LATTICE:
            break
        n = np.rint(d * q / dmin)
        step = float(np.dot(n, d) / np.dot(n, n))  # least-squares step on the integer labels
        if np.all(np.abs(d - n * step) <= tol):
            return step, a0, b0
    return None


def lattice(out_sines: np.ndarray, in_sines: np.ndarray, ndim: int = 3) -> list[tuple[float, float, float]] | None:
    """Per lateral axis (x, then y in 3D): (δs, a_o, a_i) such that every output sine is a_o + n δs and
    every transmit sine a_i + n' δs (n, n' ≥ 0 integers) within 1e-9 relative; None if there is none
    (or it would span more than 16384 steps). 2D (ndim = 2) looks at s_x only."""
    so, si = _as_sines(out_sines), _as_sines(in_sines)
    axes = []
    for d in range(ndim - 1):
        lat = _axis_lattice(so[:, d], si[:, d])
        if lat is None:
            return None
        axes.append(lat)
    return axes


# ------------------------------------------------------------------------------------------------
# the "exponential of semicircle" kernel (as finufft's)


def _kernel_params(eps: float, sigma: float | None) -> tuple[float, float]:
    """(σ, β) of the 8-tap kernel: the smallest oversampling σ whose measured error on speckle-like
    weights, ≈ 15 e^{−8π√(1−1/σ)} of the map maximum, is below eps/3 (σ = 1.37 for eps = 1e-4)."""
    if not 1e-6 <= eps < 1:
        raise ValueError(f"eps: expected 1e-6 ≤ eps < 1, got {eps}")
    root = math.log(45 / eps) / (math.pi * _TAPS)
    need = 1 / (1 - root * root) if root < 1 else math.inf
    if sigma is None:
        sigma = max(1.25, need)
    if not need <= sigma <= 8:
        raise ValueError(f"sigma: expected {need:.3g} ≤ sigma ≤ 8 for eps = {eps:g}, got {sigma}")
    return sigma, 0.97 * math.pi * (1 - 1 / (2 * sigma)) * _TAPS


def _phi(t: np.ndarray, width: int, beta: float) -> np.ndarray:
    """φ(t) = exp(β(√(1 − (2t/w)²) − 1)) on |t| < w/2, else 0."""
    x = 2 * np.asarray(t, dtype=np.float64) / width
    out = np.zeros_like(x)
    inside = np.abs(x) < 1
    out[inside] = np.exp(beta * (np.sqrt(1 - x[inside] ** 2) - 1))
    return out


def _phi_hat(xi: np.ndarray, width: int, beta: float) -> np.ndarray:
    """φ̂(ξ) = ∫ φ(t) e^{iξt} dt by Gauss–Legendre quadrature (φ is even)."""
    nodes, wts = np.polynomial.legendre.leggauss(4 * width + 40)
    t = nodes * width / 2
    return np.cos(np.outer(np.asarray(xi, dtype=np.float64), t)) @ (_phi(t, width, beta) * wts * width / 2)


def _kernel_table(width: int, beta: float) -> tuple[np.ndarray, np.ndarray]:
    """T[k, t] = φ(w/2 − 1 + k/N − t), k = 0…N, and its forward differences, for linear interpolation.

    A point at fine position u spreads onto bins l0 + t, l0 = ⌊u⌋ − w/2 + 1, t = 0…w−1, with weight
    φ(u − l0 − t) = φ(w/2 − 1 + frac(u) − t)."""
    x = width / 2 - 1 + np.arange(N_TABLE + 2) / N_TABLE
    tab = _phi(x[:, None] - np.arange(width)[None, :], width, beta)
    return (
        np.ascontiguousarray(tab[:-1], dtype=np.float32),
        np.ascontiguousarray(np.diff(tab, axis=0), dtype=np.float32),
    )


def _cos_sin(theta: np.ndarray, n: int, scale: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """cos(θ_m q)/s_q and sin(θ_m q)/s_q for q = 0 … max(n//2, n − 1 − n//2): (..., Q, M) float32.

    θ: (..., M) phase per unit index. The even/odd split of e^{iθp}, p = q and −q, halves the work."""
    q = np.arange(max(n // 2, n - 1 - n // 2) + 1)
    ph = np.asarray(theta, dtype=np.float64)[..., None, :] * q[:, None]
    inv = 1.0 if scale is None else 1.0 / np.asarray(scale, dtype=np.float64)[:, None]
    return (
        np.ascontiguousarray(np.cos(ph) * inv, dtype=np.float32),
        np.ascontiguousarray(np.sin(ph) * inv, dtype=np.float32),
    )


def _sym_tables(theta: np.ndarray, step: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tables of the exact lateral DFT Σ_m e^{iθ_m p} G_m about the lattice's centre (`loops.lateral_sym`):
    θ_m = θ_c + θ'_m, θ'_m = (m − (M−1)/2)·step (θ' symmetric: pairs m, M−1−m share cos, and sin up to sign).

    theta: (N_f, M) phases per unit index, step: (N_f,) their step. Returns C = cos(θ'_j q) for
    j < (M+1)//2, S = sin(θ'_j q) for j < M//2 and E = (cos, sin)(θ_c q), q = 0 … max(n//2, n − 1 − n//2):
    (N_f, Q, ·) float32."""
    theta = np.asarray(theta, dtype=np.float64)
    m = theta.shape[1]
    q = np.arange(max(n // 2, n - 1 - n // 2) + 1)
    centre = 0.5 * (theta[:, 0] + theta[:, -1])
    half = (np.arange((m + 1) // 2) - (m - 1) / 2)[None, :] * np.asarray(step, dtype=np.float64)[:, None]
    ph = half[:, None, :] * q[None, :, None]
    pc = centre[:, None] * q[None, :]

    def f32(a: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(a, dtype=np.float32)

    return f32(np.cos(ph)), f32(np.sin(ph[..., : m // 2])), f32(np.stack([np.cos(pc), np.sin(pc)], axis=-1))


def _pad(n: int, rows: int = 8) -> int:
    """The smallest row length ≥ n floats, a multiple of 16 (rows on cache lines), at which none of `rows`
    consecutive rows starts within 48 floats of a multiple of 4 KiB from another: the accumulator rows of the
    tile sums (`loops.accumulate_tile`; four cosine then four sine rows) 4 KiB apart alias in the store-to-load
    check and share L1 sets (measured alone: 34–40 GFMA/s with 2048-float rows, 43–45 with 2096)."""
    n = -(-n // 16) * 16
    while any(not 48 <= k * n % 1024 <= 1024 - 48 for k in range(1, rows)):
        n += 16
    return n


def _synthesis(H: np.ndarray, A: np.ndarray, B: np.ndarray, out: np.ndarray, nr: int, c: int, t: int) -> tuple:
    """Arguments of `loops.depth_synthesis` for task t of nr: H (threads, N_x, N_y, 2, nglob) summed over threads."""
    return (H.reshape(H.shape[0], -1, 2, H.shape[-1]), A, B, out, *split(out.shape[0], nr, t))


# ------------------------------------------------------------------------------------------------


class PresumTransform:
    """B(r) = Σ_j w_j e^{iK_j·r} on a regular grid, for sines on one lattice (docs/design.md §5).

    Same result as `GridTransform(wavevectors(freqs, out_sines, in_sines, c0, grid.ndim), grid, eps)`
    when `PresumTransform.applicable(out_sines, in_sines, grid.ndim)`; the module docstring has the math.
    Sines: (N, 2) (s_x, s_y) or (N,) s_x; a 2D grid uses s_x (c still includes s_y).
    lateral: "exact" (per-frequency DFTs), "nufft" (lateral spreading) or "auto" (fewer operations).
    sigma: oversampling of the fine wavenumber grids (default: the smallest meeting eps).
    nthreads: worker threads (default FP_THREADS or the CPU count). Output: complex64, grid-shaped.
    A `fpcore.kernel.Kernel` (its `ramp` is 1: the ramp is applied inside) and `KernelType`.
    Not re-entrant: an instance owns its work buffers (one call at a time per instance).
    """

    def __init__(
        self,
        freqs: np.ndarray,
        out_sines: np.ndarray,
        in_sines: np.ndarray,
        c0: float,
        grid: Grid,
        eps: float = 1e-4,
        nthreads: int | None = None,
        lateral: str = "auto",
        sigma: float | None = None,
    ) -> None:
        if loops.nb is None:
            raise ImportError("PresumTransform needs numba (pip install numba)")
        if lateral not in ("auto", "exact", "nufft"):
            raise ValueError(f"lateral: expected 'auto', 'exact' or 'nufft', got {lateral!r}")
        ndim = grid.ndim
        so, si = _as_sines(out_sines), _as_sines(in_sines)
        if np.any(np.sum(so**2, axis=1) >= 1) or np.any(np.sum(si**2, axis=1) >= 1):
            raise ValueError("sines: every direction must satisfy s_x² + s_y² < 1")
        lat = lattice(so, si, ndim)
        if lat is None:
            raise ValueError(
                "sines: the output and transmit sines are not on one lattice per lateral axis "
                "(integer multiples of a common step δs, up to one offset per set); "
                "use GridTransform"
            )
        freqs = np.asarray(freqs, dtype=np.float64).ravel()
        self.grid = grid
        self.shape = grid.shape
        self.nthreads = max(1, int(nthreads or default_threads()))
        self.n_freq, self.n_out, self.n_in = freqs.size, so.shape[0], si.shape[0]
        self.n_samples = self.n_freq * self.n_out * self.n_in
        sigma, beta = _kernel_params(eps, sigma)
        self.sigma, self.width = sigma, _TAPS
        half = _TAPS // 2
        self._tab, self._dtab = _kernel_table(_TAPS, beta)

        k = 2 * np.pi * freqs / c0
        co, ci = cosines(so), cosines(si)  # c = √(1 − s_x² − s_y²) (docs/design.md §4)
        rc = grid.centre_index_point()
        nl = ndim - 1  # lateral dimensions

        def pairs(z: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(np.stack([z.real, z.imag], axis=-1), dtype=np.float32)

        # separable ramp e^{iK·r_c} = P[f, o] Q[f, i]
        self._P = pairs(np.exp(1j * np.outer(k, so[:, :nl] @ rc[:nl] + co * rc[2])))
        self._Q = pairs(np.exp(1j * np.outer(k, si[:, :nl] @ rc[:nl] + ci * rc[2])))

        # lattice groups: m = n_o + n_i per axis, group g = m_y·M_x + m_x; θ = k_f (s_o + s_i)_m Δ
        lat_shape = self.shape[:-1] + ((1,) if ndim == 2 else ())
        n_o, n_i, M, theta = [], [], [], []
        for d, (ds, a_o, a_i) in enumerate(lat):
            n_o.append(np.rint((so[:, d] - a_o) / ds).astype(np.int64))
            n_i.append(np.rint((si[:, d] - a_i) / ds).astype(np.int64))
            M.append(int(n_o[-1].max() + n_i[-1].max() + 1))
            theta.append(np.outer(k, a_o + a_i + ds * np.arange(M[-1])) * grid.spacing[d])
        if ndim == 2:
            n_o.append(np.zeros(self.n_out, np.int64))
            n_i.append(np.zeros(self.n_in, np.int64))
            M.append(1)
            theta.append(np.zeros((self.n_freq, 1)))
        self._M = mx, my = M[0], M[1]
        self._go = n_o[1] * mx + n_o[0]
        self._gi = n_i[1] * mx + n_i[0]

        # depth: fine grid of n_z = σN_z bins (h = 2π/n_z); u = K_zΔz/h − (w/2 − 1) − start_f, so ⌊u⌋ is
        # a sample's first tap within the band [start_f, start_f + L_f) of its frequency
        dz, nz = grid.spacing[-1], grid.shape[-1]
        self._nfz = nfz = max(math.ceil(sigma * nz), 2 * _TAPS)
        h = 2 * np.pi / nfz
        ua = np.outer(k, co) * (dz / h) - (half - 1)
        ub = np.outer(k, ci) * (dz / h)
        start = np.floor(ua.min(axis=1) + ub.min(axis=1)).astype(np.int64) - 1
        one = float(1 << FRAC)  # fixed point: exact integer sums, cheap floor and fraction
        ua = np.rint((ua - start[:, None]) * one).astype(np.int64)
        ub = np.rint(ub * one).astype(np.int64)
        glen = ((ua.max(axis=1) + ub.max(axis=1)) >> FRAC) + _TAPS
        self._ua, self._ub, self._glen = ua, ub, glen.astype(np.int64)
        self._gbase = np.concatenate([[0], np.cumsum(glen * 2 * mx * my)]).astype(np.int64)
        lo = int(start.min())
        self._nglob = nglob = min(int((start + glen).max()) - lo, nfz)  # folded modulo n_z if longer
        self._lstart = ((start - lo) % nglob).astype(np.int64)
        pz = np.arange(nz) - nz // 2
        Fz = np.exp(1j * h * np.outer(lo + np.arange(nglob), pz)) / _phi_hat(pz * h, _TAPS, beta)[None, :]
        self._A = np.ascontiguousarray(np.stack([Fz.real, Fz.imag], axis=-1).reshape(nglob, 2 * nz), np.float32)
        self._B = np.ascontiguousarray(np.stack([-Fz.imag, Fz.real], axis=-1).reshape(nglob, 2 * nz), np.float32)

        # lateral: exact per-frequency DFTs, or a NUFFT over the (f, m) points. Choose by FMA count, a
        # spreading FMA (scattered rows) weighing as 6 dense ones (measured 2.5 vs 15 GFMA/s per core)
        nx, ny = lat_shape
        qx, qy = nx // 2 + 1, ny // 2 + 1
        nf_lat = [max(math.ceil(sigma * n), 2 * _TAPS) if n > 1 else 1 for n in lat_shape]
        rows = float(np.sum(glen))  # Σ_f L_f
        cost_exact = 4 * rows * mx * (qy * my + qx * ny)
        cost_nufft = 6 * 2 * rows * mx * my * _TAPS**nl + 4 * nglob * nf_lat[0] * (qy * nf_lat[1] + qx * ny)
        self.cost = {"exact": cost_exact, "nufft": cost_nufft}
        self.lateral = min(self.cost, key=lambda k: self.cost[k]) if lateral == "auto" else lateral
        nt = self.nthreads
        self._Cx: np.ndarray  # cos/sin tables of the lateral synthesis (x, y), per branch below
        self._Sx: np.ndarray
        self._Cy: np.ndarray
        self._Sy: np.ndarray
        self._T: np.ndarray  # work buffer: one row per thread (exact lateral) or one flat buffer (NUFFT)
        if self.lateral == "exact":
            steps = [ds for ds, _, _ in lat] + ([0.0] if ndim == 2 else [])
            self._lat = (
                *_sym_tables(theta[1], steps[1] * k * (grid.spacing[1] if ndim == 3 else 0.0), ny),
                *_sym_tables(theta[0], steps[0] * k * grid.spacing[0], nx),
            )
            lmax = int(glen.max())
            self._T = np.zeros((nt, mx * min(2 * loops.SLAB_Q, ny) * 2 * lmax), dtype=np.float32)  # a slab
            self._accs = np.zeros((nt, 2, 4, _pad(max(_BLOCK, 2 * lmax))), dtype=np.float32)
            self._gsize = mx * my * 2 * lmax  # one frequency's block of lattice rows
            self._Hs = np.zeros((nt, 1, nx, ny, 2, nglob), dtype=np.float32)
        else:
            hl = [2 * np.pi / n for n in nf_lat]
            pos = [(theta[d] / hl[d] - (half - 1)) % nf_lat[d] for d in range(nl)]  # ≥ 0, taps wrap
            self._ux = np.ascontiguousarray(pos[0])
            self._uy = np.ascontiguousarray(pos[1]) if ndim == 3 else np.zeros((self.n_freq, 1))
            # synthesis from the fine lateral grids: e^{i p h k} / φ̂(p h), split in cos and sin
            syn = [
                _cos_sin(hh * np.arange(n)[None, :], nn, _phi_hat(np.arange(nn // 2 + 1) * hh, _TAPS, beta))
                for hh, n, nn in zip(hl, nf_lat, lat_shape, strict=False)
            ]
            self._Cx, self._Sx = syn[0][0][0], syn[0][1][0]
            self._Cy, self._Sy = (syn[1][0][0], syn[1][1][0]) if ndim == 3 else _cos_sin(np.zeros(1), 1)
            self._W = np.zeros((nt, nf_lat[1], nf_lat[0], 2, nglob), dtype=np.float32)
            self._T = np.zeros(nf_lat[0] * ny * 2 * nglob, dtype=np.float32)
            self._acc = np.zeros((nt, 4 * nglob * max(nf_lat[0], ny)), dtype=np.float32)
            self._Hs = np.zeros((1, 1, nx, ny, 2, nglob), dtype=np.float32)
        # the frequency blocks of all lattice rows (NUFFT lateral); the exact path keeps one per thread
        self._G = np.zeros(int(self._gbase[-1]) if self.lateral == "nufft" else 0, dtype=np.float32)
        self._Gt = np.zeros((nt, 1, 0), dtype=np.float32)
        self.ramp = np.ones((), dtype=np.complex64)  # the ramp e^{iK·r_c} is applied inside (P, Q)

    @staticmethod
    def supports(out_sines: np.ndarray, in_sines: np.ndarray, ndim: int) -> bool:
        """True when numba is available and the sines lie on one lattice (`applicable`): the `KernelType`
        test of `fpcore.kernel`."""
        return loops.nb is not None and PresumTransform.applicable(out_sines, in_sines, ndim)

    @classmethod
    def for_geometry(
        cls, freqs: np.ndarray, out_sines: np.ndarray, in_sines: np.ndarray, c0: float, grid: Grid, eps: float
    ) -> PresumTransform:
        """`PresumTransform(freqs, out_sines, in_sines, c0, grid, eps)` (the `KernelType` builder)."""
        return cls(freqs, out_sines, in_sines, c0, grid, eps=eps)

    @staticmethod
    def applicable(out_sines: np.ndarray, in_sines: np.ndarray, ndim: int = 3) -> bool:
        """True when, per lateral axis (s_x; and s_y when ndim = 3), every output sine and every transmit
        sine is an integer multiple of one step δs — each set may carry its own constant offset, e.g. a
        symmetric linspace — within 1e-9 relative."""
        try:
            return lattice(out_sines, in_sines, ndim) is not None
        except ValueError:
            return False

    def execute_ramped(self, c: np.ndarray) -> np.ndarray:
        """The same map as `__call__` (this kernel applies the ramp itself: `ramp` is 1)."""
        return self(c)

    def __call__(self, weights: np.ndarray) -> np.ndarray:
        """Map Σ_j w_j e^{iK_j·r} on the grid (complex64, grid shape); weights (N_s,) or (n, N_s) → (n, *shape)."""
        w = np.asarray(weights)
        if w.shape[-1:] != (self.n_samples,) or w.ndim > 2:
            raise ValueError(f"weights: expected shape ({self.n_samples},) or (n, {self.n_samples}), got {w.shape}")
        if w.ndim == 1:
            return self._maps(w[None])[0]
        return np.concatenate([self._maps(row[None]) for row in w])

    def _maps(self, w: np.ndarray) -> np.ndarray:
        """Maps of the weight vectors w (nb, N_s), nb > 1 only on the exact lateral path (`loops.exact_fused`
        spreads and transforms them together, sharing positions, ramp and tables; measured on a full-size
        frame, γ's and the confocal field's weights together cost 7 % more CPU than apart: cache, not work,
        bounds the lateral sums — so `__call__` passes one at a time)."""
        if w.dtype != np.complex128:
            w = w.astype(np.complex64, copy=False)
        w = np.ascontiguousarray(w)
        nb = w.shape[0]
        wr = w.view(w.real.dtype).reshape(nb, self.n_freq, self.n_out, self.n_in, 2)
        nt, nf = self.nthreads, self.n_freq
        nk = min(nf, 4 * nt)  # tasks: frequencies k, k + nk, … (a few per thread, handed out dynamically)
        head = (wr, self._P, self._Q, self._ua, self._ub, self._go, self._gi)  # both paths' weights and geometry
        nx, ny = self._Hs.shape[2:4]
        nz = self.shape[-1]
        out = np.empty((nb, nx * ny, 2 * nz), dtype=np.float32)
        if self.lateral == "exact":
            if self._Gt.shape[1] < nb or self._Gt.shape[2] < self._gsize:
                self._Gt = np.zeros((nt, nb, self._gsize), dtype=np.float32)
            if self._Hs.shape[1] != nb:
                self._Hs = np.zeros((nt, nb, *self._Hs.shape[2:]), dtype=np.float32)
            self._Hs[:] = 0
            pool(
                nt,
                nk,
                loops.exact_fused,
                lambda c, k: (
                    *head,
                    self._glen,
                    self._lstart,
                    self._tab,
                    self._dtab,
                    self._lat,
                    self._Gt[c, :nb],
                    self._T[c],
                    self._accs[c, 0],
                    self._accs[c, 1],
                    self._Hs[c],
                    _BLOCK,
                    k,
                    nk,
                ),
            )
            nr = 4 * nt
            for b in range(nb):
                pool(nt, nr, loops.depth_synthesis, partial(_synthesis, self._Hs[:, b], self._A, self._B, out[b], nr))
            return out.view(np.complex64).reshape(nb, *self.shape)
        pool(
            nt,
            nk,
            loops.spread_depth,
            lambda c, k: (
                *head,
                self._gbase,
                self._glen,
                self._tab,
                self._dtab,
                self._G,
                k,
                nk,
            ),
        )
        self._Hs[:] = 0
        self._W[:] = 0
        pool(
            nt,
            nk,
            loops.spread_lateral,
            lambda c, k: (
                self._G,
                self._gbase,
                self._glen,
                self._lstart,
                self._ux,
                self._uy,
                self._tab,
                self._dtab,
                self._W[c],
                k,
                nk,
            ),
        )
        Ws = (self._W[0] if nt == 1 else self._W.sum(axis=0)).ravel()
        nglob, H, nq = u64(self._nglob), self._Hs[0, 0], 4 * nt
        if ny > 1:
            pool(
                nt,
                nq,
                loops.lat_y,
                lambda c, t: (
                    Ws,
                    u64(0),
                    nglob,
                    self._W.shape[2],
                    self._Cy,
                    self._Sy,
                    ny,
                    *split(self._Cy.shape[0], nq, t),
                    self._T,
                    self._acc[c],
                ),
            )
        pool(
            nt,
            nq,
            loops.lat_x,
            lambda c, t: (
                Ws if ny == 1 else self._T,
                nglob,
                self._Cx,
                self._Sx,
                nx,
                ny,
                *split(self._Cx.shape[0], nq, t),
                H,
                u64(0),
                self._acc[c],
            ),
        )
        Hs = self._Hs.reshape(1, nx * ny, 2, -1)
        nr = 4 * nt
        pool(nt, nr, loops.depth_synthesis, lambda c, t: (Hs, self._A, self._B, out[0], *split(nx * ny, nr, t)))
        return out.view(np.complex64).reshape(nb, *self.shape)
