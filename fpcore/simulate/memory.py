"""The angular memory effect of the multiple-scattering background (docs/design.md §6.5).

Physics. A path entering the medium at ρ_in and leaving it at ρ_out contributes e^{−ik a·ρ_in + ik o·ρ_out}
to the plane-wave matrix T(o, a) (transmit sine a, upgoing output sine o; `diffuse` module doc). A common
tilt δ of input and output multiplies it by e^{−ik δ·d}, d = ρ_in − ρ_out, so over the paths of one age

    ⟨T(o + δ, a + δ) T*(o, a)⟩ / ⟨|T(o, a)|²⟩ = ⟨e^{−ik δ·d}⟩ = exp(−k² |δ|² D_eff(τ))        (M1)

(the memory effect, Feng, Kane, Lee & Stone, Phys. Rev. Lett. 61, 834 (1988), here in reflection), while
pairs whose difference o − a differs are uncorrelated (distinct paths). d is Gaussian, of variance 2D's per
axis after a path s = vτ (D' = ℓ_s/d in d dimensions); seen through the array's beams, whose footprints
(a_g² per axis, `diffuse.HaloGeometry`) bound both endpoints, D_eff = D's a_g²/(a_g² + 4D's) — the same
bound as the coherent-backscattering cone, which is (M1) between a path and its reversed partner:
T(o, a) and T(−a, −o) lie on one line o − a = const, q = o + a apart, and 1 + exp(−k²q² D_eff) follows.

Construction. White noise on a box of lattice indices is correlated along the lines of a common tilt
(u = c + slope·v in two of its axes: v the transmit's lattice index, u the output's grid index), line by
line, with the symmetric square root of the Toeplitz matrix exp(−β (n − n')²) of (M1) at each time sample
(β = k_c² δ² D_eff(τ(t)), δ one step along the line, τ the age of a normally incident path at that time):
each entry keeps unit variance and neighbours n steps apart have correlation exp(−β n²) exactly (a Gaussian
Toeplitz matrix is positive semi-definite at any length, `gaussian_roots`). The time axis is last. In the
reciprocal block only whole transmit steps are correlated, and its envelopes are divided by the energy gain
of the correlation within a transmit's beam (`block_kernel`, `block_energy_gain`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .reciprocity import array_factor

__all__ = [
    "MemoryKernel",
    "block_energy_gain",
    "block_kernel",
    "correlate_lines",
    "effective_spread",
    "gaussian_roots",
    "grid_kernel",
    "lattice_steps",
]


def effective_spread(tau: np.ndarray, ls: float, v: float, dim: int, a_g2: float) -> np.ndarray:
    """D_eff(τ) = D's a_g²/(a_g² + 4D's) (m²) of (M1), D's = (ℓ_s/d) v τ; 0 for τ ≤ 0."""
    dps = (ls / dim) * v * np.maximum(np.asarray(tau, dtype=np.float64), 0.0)
    return dps * a_g2 / (a_g2 + 4.0 * dps)


def gaussian_roots(beta: np.ndarray, n: int) -> np.ndarray:
    """Symmetric square roots R (len(beta), n, n) float32 of C_kl = exp(−β (k − l)²), R R = C (eigenvalues
    clipped at 0: C is positive semi-definite, all ones when β = 0)."""
    b = np.maximum(np.asarray(beta, dtype=np.float64), 0.0)
    lag2 = (np.arange(n)[:, None] - np.arange(n)[None, :]).astype(np.float64) ** 2
    cov = np.exp(-b[:, None, None] * lag2[None, :, :])
    w, vec = np.linalg.eigh(cov)
    root = (vec * np.sqrt(np.maximum(w, 0.0))[:, None, :]) @ np.transpose(vec, (0, 2, 1))
    return root.astype(np.float32)


def correlate_lines(
    noise: np.ndarray, u_axis: int, v_axis: int, slope: int, roots: list[np.ndarray], stride: int = 1
) -> np.ndarray:
    """Correlate `noise` (time axis last) along the lines u = c + slope·v of its axes (u_axis, v_axis): the
    entries of a line whose v are ≡ r (mod `stride`), in order of v, are mixed by `roots[n]` (n_t, n, n) for
    n such entries (module doc); the residues r are independent. Returns a new array; single entries are
    copied as they are."""
    arr = np.moveaxis(noise, (u_axis, v_axis), (0, 1))
    n_u, n_v = arr.shape[:2]
    out = arr.copy()
    for c in range(min(0, -slope * (n_v - 1)), max(n_u, n_u - slope * (n_v - 1))):
        for r in range(stride):
            v = np.arange(r, n_v, stride)
            u = c + slope * v
            ok = (u >= 0) & (u < n_u)
            n = int(ok.sum())
            if n < 2:
                continue
            sub = arr[u[ok], v[ok]]  # (n, …, n_t)
            rest = sub.shape[1:-1]
            flat = np.moveaxis(sub.reshape(n, -1, sub.shape[-1]), -1, 0)  # (n_t, n, m)
            mixed = np.matmul(roots[n], flat)
            out[u[ok], v[ok]] = np.moveaxis(mixed, 0, -1).reshape((n, *rest, sub.shape[-1]))
    return np.moveaxis(out, (0, 1), (u_axis, v_axis))


@dataclass(frozen=True)
class MemoryKernel:
    """White noise on a box of lattice indices, correlated along its common-tilt lines (`correlate_lines`),
    then read at `index` (arrays that broadcast to the wanted table's shape)."""

    shape: tuple[int, ...]  # the box, time axis excluded
    lines: tuple[tuple[int, int, int, int, tuple[np.ndarray, ...]], ...]  # (u_axis, v_axis, slope, stride, roots)
    index: tuple[np.ndarray, ...]

    def draw(self, white: Callable[[tuple[int, ...]], np.ndarray]) -> np.ndarray:
        """The correlated noise at `index` (…, n_t), from `white(shape)` (complex, time axis last)."""
        box = white(self.shape)
        for u_axis, v_axis, slope, stride, roots in self.lines:
            box = correlate_lines(box, u_axis, v_axis, slope, list(roots), stride)
        return box[self.index]


def _roots_up_to(beta: np.ndarray, n_max: int) -> tuple[np.ndarray, ...]:
    """gaussian_roots for every line length 0…n_max (entries 0 and 1 unused), complex64 like the noise they mix
    (so that no frame converts them again)."""
    return tuple(
        (gaussian_roots(beta, n) if n >= 2 else np.ones((beta.size, 1, 1), np.float32)).astype(np.complex64)
        for n in range(n_max + 1)
    )


def _grid_offsets(sines: np.ndarray, spacings: list[float]) -> list[np.ndarray]:
    """Each transmit's integer offset on the output grid per lateral axis; ValueError when one is off the grid."""
    si = np.asarray(sines, dtype=np.float64)
    out = []
    for d, ds in enumerate(spacings):
        m = np.rint(si[:, d] / ds).astype(np.int64)
        if not np.allclose(m * ds, si[:, d], atol=1e-7, rtol=0.0):
            raise ValueError("sines: expected every transmit on the output grid (memory effect: cbs=True aligns it)")
        out.append(m)
    return out


def lattice_steps(sines: np.ndarray, spacings: list[float]) -> list[int]:
    """The transmits' lattice step L per lateral axis, in output-grid steps (the gcd of their offsets; 1 for a
    single transmit along an axis). Raises ValueError when a transmit is off the output grid."""
    steps = []
    for m in _grid_offsets(sines, spacings):
        off = m - m.min()
        steps.append(int(np.gcd.reduce(off)) if np.any(off) else 1)
    return steps


def grid_kernel(
    axes: list[np.ndarray],
    keep: np.ndarray,
    spacings: list[float],
    sines: np.ndarray,
    steps: list[int],
    beta_per_step2: Callable[[float], np.ndarray],
) -> MemoryKernel:
    """The kernel of the background's main grid (outputs `axes`/`keep` × transmits `sines`), correlated along
    (o + L δ_o, θ + 1) per lateral axis, L = `steps` the transmits' lattice step in output-grid steps
    (`lattice_steps`); `beta_per_step2(δ)` gives β(t) = k² δ² D_eff(τ(t)) for a tilt δ."""
    n_ax = len(axes)
    shape_o = tuple(a.size for a in axes)
    flat = np.flatnonzero(keep)
    o_idx = np.unravel_index(flat, shape_o)  # each kept output's grid index per axis
    t_idx, n_t, lines = [], [], []
    for d, m in enumerate(_grid_offsets(sines, spacings)):
        step = steps[d]
        j = (m - m.min()) // step  # the transmit's lattice index
        t_idx.append(j)
        n_t.append(int(j.max()) + 1)
        lines.append((d, n_ax + d, step, 1, _roots_up_to(beta_per_step2(step * spacings[d]), n_t[-1])))
    index = tuple(o[:, None] for o in o_idx) + tuple(j[None, :] for j in t_idx)
    return MemoryKernel(shape_o + tuple(n_t), tuple(lines), index)


def block_kernel(
    m_inputs: np.ndarray, spacings: list[float], steps: list[int], beta_per_step2: Callable[[float], np.ndarray]
) -> MemoryKernel:
    """The kernel of the reciprocal block (`reciprocity.ReciprocalBlock`): rows o_i = −a_i and inputs a_j given
    by their integer grid offsets `m_inputs` (P, 2); a common tilt (o_i + δ, a_j + δ) is (m_i − 1, m_j + 1) per
    axis, so the lines are m_i + m_j = const. Only tilts by whole steps L of the transmits' lattice (`steps`)
    are correlated (stride L), as on the main grid, where the transmits are the only inputs; what remains of
    the correlation within a transmit's beam (L = 1 under a small array) is divided out of the energy by
    `block_energy_gain`. `index` reads the full (P, P) table X_ij."""
    m = np.asarray(m_inputs, dtype=np.int64)
    n_ax = len(spacings)
    lo = m[:, :n_ax].min(axis=0)
    b = m[:, :n_ax] - lo[None, :]
    size = tuple(int(x) for x in b.max(axis=0) + 1)
    lines = []
    for d, step in enumerate(steps):
        n_max = -(-size[d] // step)
        lines.append((d, n_ax + d, -1, step, _roots_up_to(beta_per_step2(step * spacings[d]), n_max)))
    index = tuple(b[:, d][:, None] for d in range(n_ax)) + tuple(b[:, d][None, :] for d in range(n_ax))
    return MemoryKernel(size + size, tuple(lines), index)


def block_energy_gain(
    elements: np.ndarray,
    spacings: list[float],
    m_inputs: np.ndarray,
    steps: list[int],
    beta_per_step2: Callable[[float], np.ndarray],
    k: float,
) -> np.ndarray:
    """G(t): the factor by which the block's correlation raises the energy the elements receive (n_t,).

    A transmit mixes its lobe's inputs, A(o_i, θ) = Σ_j W_θj T_ij (`reciprocity`), so with (M1) two outputs n
    grid steps apart, fed by (i, j) and (i + n, j − n) on one line, are correlated by C(n) ρ_B(n), ρ_B the
    transmit beam's autocorrelation on the grid; the elements then receive Σ_n B(n Δs) ρ_B(n) C(n) times the
    independent outputs' energy (B the array factor at wavenumber k, `reciprocity.array_factor`, per axis, the
    product over axes; C of (M1) at whole lattice steps L = `steps` only, as in `block_kernel`). The
    envelope already sets the energy the array receives from the halo (transport theory), so the block's
    envelopes are divided by √G: the correlation redistributes the energy and does not add to it."""
    m = np.asarray(m_inputs, dtype=np.int64)
    gain = None
    for d, ds in enumerate(spacings):
        half = int(np.ptp(m[:, d]))
        n = np.arange(-half, half + 1)
        offs = np.zeros((n.size, 2))
        offs[:, d] = n * ds
        b = array_factor(elements, offs, np.array([k]))[:, 0]  # the receive side's B(nΔs), the transmit beam alike
        full = np.correlate(b, b, mode="full")  # Σ_m B(m + n) B*(m), lags −2·half … 2·half
        rho = full[half : 3 * half + 1] / np.sum(np.abs(b) ** 2)  # lags −half … half
        step = steps[d]
        beta = beta_per_step2(step * ds)
        c = np.where((n % step == 0)[None, :], np.exp(-beta[:, None] * (n[None, :] / step) ** 2), 0.0)
        g = c @ np.real(np.conj(b) * rho)  # outputs n steps apart are weighted by B(−nΔs) = B*(nΔs) (e^{−ik s_o·u})
        gain = g if gain is None else gain * g
    assert gain is not None
    return np.maximum(gain, 1e-3)
