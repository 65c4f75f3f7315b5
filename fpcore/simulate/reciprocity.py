"""Reciprocity of the multiple-scattering background between finite transmit beams (docs/design.md §6.3).

Physics. The medium's plane-wave matrix T(o, a) (upgoing output o, downgoing input a) is reciprocal:
T(o, a) = T(−a, −o). A transmit synthesised by an array of elements u is not one plane wave but the
array's angular spectrum about its sine s_θ, B_f(a − s_θ) = (1/N_u) Σ_u e^{ik(a − s_θ)·u} (the same
function as the array's receive beam), so the data hold A(o, θ) = Σ_a B_f(a − s_θ) T(o, a). A receive
beam b through the same elements, R̃(b, θ) = N_u Σ_o w_o B_f(b − s_o) A(o, θ), then pairs every path
(o, a) with its reversed path (−a, −o) under the same weight when b = −s_θ', so that

    R̃(−s_θ', θ)/c_θ = R̃(−s_θ, θ')/c_θ'                      (element-basis symmetry, R_uu' = R_u'u)

and ⟨|R̃(−s_θ, θ)|²⟩ is twice the ladder: coherent backscattering of height 2 at exact retro-reflection,
over a cone exp(−k²q² a_g²/4) as wide as the beams (Gaussian algebra with B ∝ e^{−k²δ² a_g²/4}), whatever the
age of the paths. A model whose A(o, θ) are independent per output cannot do this: a receive beam mixes
the neighbouring outputs of −s_θ, whose noise is independent, and dilutes both the cone and the
symmetry (measured on the 3-D Foldy–Lax geometry: cone 1.4, symmetry 0.15, against 2.1 and 0.997).

Construction. On the aligned output grid (its spacing divides the transmits' lattice) each transmit's
main lobe is the set of grid inputs a within ±M steps of s_θ per axis (M: the last step before the
array factor's first null at the band's lowest frequency). Their union A (P inputs) and its mirror
O = −A (P outputs, all on the output grid) carry one noise T(o_i, a_j, t) with T_ij = T_ji (the reversed
path's very amplitude), whose envelope is that of the pair (o_i, a_j) in the background's geometry
(symmetric under the swap; computed once per pair i ≤ j, so exactly symmetric). Transmit θ's outputs in O are then

    A(o_i, θ, f) = Σ_j W_θj(f) T_ij(f),  W_θj(f) = c_θ w(o_j) B_f(a_j − s_θ)/β_f,

w the outputs' grid weights (taper × 1/c_o), j over the whole block (the main lobe and the sidelobes that fall
inside it: the receive beam's very weights there, so the symmetry is exact for the part of a receive
beam inside O; beyond, its sidelobes see independent outputs) and β_f² = Σ_j |B_f(a_j − s_c)|² for the
transmit nearest the axis (one constant, as the symmetry requires). ⟨|A|²⟩ = Σ_j |W_θj|² env²_ij is the
ladder of (o_i, s_θ) (c_θ/c_j ≈ 1 across a lobe). The diagonal T_ii, the exactly retro-reflected plane
wave (−a_i, a_i), is its own reversed path: ⟨|T_ii|²⟩ = 2 × ladder (in the element basis, the confocal
diagonal's enhancement of 2). With it, a receive beam's retro intensity is 2 − ΣW⁴/(ΣW²)² + ΣW⁴/(ΣW²)²
= 2 × ladder exactly; without it, ~1.6 for a beam of a few grid steps (measured). The outputs outside O
keep their independent noise.

The cone's width is the beams' (exp(−k²q²a_g²/4)) at every age: while the halo is still narrower than the
aperture (the first few µs under the surface) the physical cone is wider; plane-wave elements with the
same momentum transfer would then be correlated, which this model does not represent.

The measured reciprocity (`ElementReciprocity`). What the array measures of R_uu' = R_u'u through its transmits
(plane-wave phases φ_θ(u) = e^{−ik s_θ·u}, the transmits' obliquity c_θ) is that the N_θ × N_θ matrix

    S(θ', θ) = Σ_u φ_θ'(u) M(u, θ)/c_θ  is symmetric                                                    (R1)

(the receive beam at −s_θ' of transmit θ: the bench's symmetry figure). A field drawn per output with independent
noise outside the block breaks (R1) through the beams' sidelobes, and a projection that takes a symmetric part
out of the field (the confocal notch, `confocal_notch`) raises the antisymmetric remainder's share. The orthogonal
projection of W = M/c_θ onto the fields that satisfy (R1) removes W's component along Φ̄ Y, Y antisymmetric (the
span orthogonal to them), with

    G Y + Y Gᵀ = −(S − Sᵀ),   G = Φᵀ Φ̄ (N_θ × N_θ, Hermitian, positive),                                    (R2)

solved in G's eigenbasis (G = U Λ U^H, Gᵀ = Ū Λ Uᵀ; Y = U Z Uᵀ gives Λ Z + Z Λ = U^H C Ū, so Z_ij = (U^H C Ū)_ij /
(λ_i + λ_j)). S loses its antisymmetric part; its symmetric part moves too, by that of G Y, unless G is a multiple of
the identity (transmits the array resolves exactly): the projection is the smallest change of W, not of S, and the
part of W orthogonal to every Φ̄ Y is left as it was.
"""

from __future__ import annotations

import numpy as np

from ..acquisition import element_grid_axes
from ..geometry import cosines

__all__ = ["ElementReciprocity", "ReciprocalBlock", "array_factor", "main_lobe_steps"]

#: At most this many grid steps per axis in a transmit's main lobe (cost: P² noise series).
MAX_LOBE_STEPS = 4


def array_factor(elements: np.ndarray, offsets: np.ndarray, k: np.ndarray) -> np.ndarray:
    """B_f(δ) = (1/N_u) Σ_u e^{ik δ·u} for sine offsets δ (n, 2) at wavenumbers k (N_f,): (n, N_f) complex."""
    el = np.asarray(elements, dtype=np.float64)[:, :2]
    phase = np.asarray(offsets, dtype=np.float64) @ el.T  # (n, N_u)
    return np.mean(np.exp(1j * k[None, :, None] * phase[:, None, :]), axis=2)


def main_lobe_steps(elements: np.ndarray, spacing: float, axis: int, k_min: float) -> int:
    """The last grid step m (≥ 1) before the first minimum of |B(m Δs e_axis)| at the lowest wavenumber."""
    m = np.arange(0, 4 * MAX_LOBE_STEPS + 2)
    offs = np.zeros((m.size, 2))
    offs[:, axis] = m * spacing
    mag = np.abs(array_factor(elements, offs, np.array([k_min]))[:, 0])
    drop = np.flatnonzero(np.diff(mag) >= 0)  # first m whose successor is not smaller: a minimum
    first_min = int(drop[0]) if drop.size else m[-1]
    return int(np.clip(first_min - 1, 1, MAX_LOBE_STEPS))


class ReciprocalBlock:
    """The reciprocal main-lobe block of the background (module doc): index sets, beam weights, mixing.

    s_out (N_o, 2) and its grid `spacings` (per lateral axis), the transmits' `sines` (N_θ, 2) on that grid,
    `grid_weights` (N_o,) the outputs' weights (taper × 1/c_o, any normalisation), the array's `elements`
    and the band's frequencies `freqs` (Hz). `rows` are the outputs O in s_out, `inputs` the sines of A
    (O = −A elementwise). Raises ValueError when a transmit is not on the grid.
    """

    def __init__(
        self,
        s_out: np.ndarray,
        spacings: list[float],
        sines: np.ndarray,
        grid_weights: np.ndarray,
        elements: np.ndarray,
        freqs: np.ndarray,
        c0: float,
    ) -> None:
        so, si = np.asarray(s_out, dtype=np.float64), np.asarray(sines, dtype=np.float64)
        n_ax = len(spacings)
        ds = np.array(spacings + [1.0] * (2 - n_ax))
        m_t = np.rint(si / ds).astype(int)
        if n_ax == 1:
            m_t[:, 1] = 0
        if not np.allclose(m_t[:, :n_ax] * ds[:n_ax], si[:, :n_ax], atol=1e-7, rtol=0.0):
            raise ValueError("sines: expected every transmit on the output grid (aligned spacing)")
        k = 2 * np.pi * np.asarray(freqs, dtype=np.float64) / c0
        steps = [main_lobe_steps(elements, spacings[d], d, float(k.min())) for d in range(n_ax)] + [0] * (2 - n_ax)
        self.steps = tuple(steps[:n_ax])
        mx, my = np.meshgrid(np.arange(-steps[0], steps[0] + 1), np.arange(-steps[1], steps[1] + 1), indexing="ij")
        lobe = np.stack([mx.ravel(), my.ravel()], axis=1)  # (n_off, 2) integer offsets
        m_o = np.rint(so / ds).astype(int)
        if n_ax == 1:
            m_o[:, 1] = 0
        index = {tuple(m): i for i, m in enumerate(m_o)}
        cand = np.unique((m_t[:, None, :] + lobe[None, :, :]).reshape(-1, 2), axis=0)
        # An input a belongs to the block when its mirror −a is an output (then its partner is in the data).
        keep = [tuple(-c) in index for c in cand]
        m_a = cand[np.array(keep, dtype=bool)]
        self.rows = np.array([index[tuple(-c)] for c in m_a], dtype=np.int64)  # o_i = −a_i in s_out
        self.m_inputs = m_a  # a_j's integer grid offsets (`memory.block_kernel`)
        self.inputs = m_a * ds[None, :]
        if n_ax == 1:
            self.inputs[:, 1] = 0.0
        self.n_block = m_a.shape[0]
        # Transmit θ's weight on every input of the block, W_θj(f) = c_θ w(o_j) B_f(a_j − s_θ)/β_f: its main lobe
        # and the sidelobes that fall inside the block, the very weights of the receive beam at −s_θ over the
        # block's outputs (so the symmetry is exact there). β_f² = Σ_j |B_f(a_j − s_c)|² for the transmit
        # nearest the axis, a constant over θ as the symmetry requires (edge transmits keep a little less).
        rel = m_a[None, :, :] - m_t[:, None, :]  # (N_θ, P, 2) integer offsets
        uniq, inv = np.unique(rel.reshape(-1, 2), axis=0, return_inverse=True)
        b = _array_factor_on_grid(elements, uniq, ds, k)[inv.ravel()].reshape(rel.shape[0], rel.shape[1], k.size)
        centre = int(np.argmin(np.linalg.norm(si, axis=1)))
        beta = np.sqrt(np.sum(np.abs(b[centre]) ** 2, axis=0))  # (N_f,)
        w_rows = np.asarray(grid_weights, dtype=np.float64)[self.rows]  # w(o_j)
        c_t = cosines(si)
        beam = c_t[:, None, None] * w_rows[None, :, None] * b / beta[None, None, :]  # (N_θ, P, N_f)
        self.beam = np.ascontiguousarray(np.transpose(beam, (2, 1, 0)), dtype=np.complex64)  # (N_f, P, N_θ)
        # The block's pairs i ≤ j (T_ij = T_ji: only these carry noise), and the packed index of every (i, j).
        self.pairs = np.triu_indices(self.n_block)
        self.packed_index = np.empty((self.n_block, self.n_block), dtype=np.int64)
        self.packed_index[self.pairs] = np.arange(self.pairs[0].size)
        self.packed_index[self.pairs[1], self.pairs[0]] = np.arange(self.pairs[0].size)
        self.n_pairs = int(self.pairs[0].size)
        self.diagonal = self.pairs[0] == self.pairs[1]  # (o_i, a_i) = (−a_i, a_i): exact retro-reflection

    def envelopes(self, ladder: list[np.ndarray]) -> list[np.ndarray]:
        """The block's packed envelopes (module doc) from the ladder envelope of each pair i ≤ j (n_pairs, 1, …):
        √2 on the diagonal, where the exactly retro-reflected plane wave (−a_i, a_i) is its own reversed path
        (⟨|T_ii|²⟩ = 2 × ladder). One envelope per packed pair serves T_ij and T_ji alike."""
        out = []
        for env in ladder:
            e = env.copy()
            e[self.diagonal] *= np.float32(np.sqrt(2.0))
            out.append(e)
        return out

    def mix(self, packed_spec: np.ndarray) -> np.ndarray:
        """A(o_i, θ, f) = Σ_j W_θj(f) T_ij(f) from the block's packed spectrum (n_pairs, 1, N_f):
        (P, N_θ, N_f) complex64."""
        full = np.transpose(packed_spec[:, 0, :][self.packed_index], (2, 0, 1))  # (N_f, P, P)
        return np.ascontiguousarray(np.transpose(np.matmul(full, self.beam), (1, 2, 0)))


def _array_factor_on_grid(elements: np.ndarray, m: np.ndarray, ds: np.ndarray, k: np.ndarray) -> np.ndarray:
    """B_f(m Δs) for integer grid offsets m (n, 2): separable over a full regular matrix array (the product
    of the axes' factors), direct otherwise. (n, N_f) complex."""
    el = np.asarray(elements, dtype=np.float64)
    axes = element_grid_axes(el)
    if axes is None:
        return array_factor(el, m * ds[None, :], k)
    out = np.ones((m.shape[0], k.size), dtype=np.complex128)
    for d, u in enumerate(axes):
        vals, inv = np.unique(m[:, d], return_inverse=True)
        f_d = np.mean(np.exp(1j * k[None, :, None] * (vals[:, None, None] * ds[d]) * u[None, None, :]), axis=2)
        out *= f_d[inv.ravel()]
    return out


#: Pairs of G's eigen-directions whose λ_i + λ_j fall below this fraction of the largest are left unprojected (R2).
RANK_TOLERANCE = 1e-10


class ElementReciprocity:
    """The orthogonal projection of element-basis spectra M (N_f, N_u, N_θ) onto those whose measured matrix
    S(θ', θ) = Σ_u e^{−ik s_θ'·u} M(u, θ)/c_θ is symmetric at every frequency (module doc, R1–R2), for the
    array's `elements`, the transmits' `sines` (N_θ, 2) and the frequencies `freqs` (Hz)."""

    def __init__(self, elements: np.ndarray, sines: np.ndarray, freqs: np.ndarray, c0: float) -> None:
        el = np.asarray(elements, dtype=np.float64)[:, :2]
        si = np.asarray(sines, dtype=np.float64)
        k = 2 * np.pi * np.asarray(freqs, dtype=np.float64) / c0
        phi = np.exp(-1j * k[:, None, None] * (el @ si[:, :2].T)[None, :, :])  # (N_f, N_u, N_θ)
        gram = np.einsum("fua,fub->fab", phi, np.conj(phi))  # G = Φᵀ Φ̄
        lam, u = np.linalg.eigh(gram)
        lam = np.maximum(lam, 0.0)
        pair = lam[:, :, None] + lam[:, None, :]
        # Transmits closer than the array resolves make G nearly singular: the pairs of directions it does not
        # resolve (λ_i + λ_j below RANK_TOLERANCE of the largest) carry no measured asymmetry and are left alone.
        resolved = pair > RANK_TOLERANCE * pair.max(axis=(1, 2), keepdims=True)
        self.shape = (k.size, el.shape[0], si.shape[0])
        self._phi = phi
        self._u = u
        self._inv_sum = np.where(resolved, 1.0 / np.where(resolved, pair, 1.0), 0.0)  # 1/(λ_i + λ_j)
        self._c = cosines(si)

    def _weighted(self, m: np.ndarray) -> np.ndarray:
        """W = M/c_θ (complex128), the field the projection is orthogonal in."""
        return m.astype(np.complex128) / self._c[None, None, :]

    def _measured(self, w: np.ndarray) -> np.ndarray:
        return np.matmul(np.swapaxes(self._phi, 1, 2), w)

    def measured(self, m: np.ndarray) -> np.ndarray:
        """S(θ', θ) of (R1) per frequency: (N_f, N_θ, N_θ)."""
        return self._measured(self._weighted(m))

    def symmetry(self, m: np.ndarray) -> float:
        """|Σ S Sᵀ*| / Σ |S|² over the off-diagonal pairs and the frequencies (1: reciprocal as measured; ≈ 0:
        independent), the bench's figure (`background_metrics.cbs_enhancement`) on the transmits' own mirrors."""
        s = self.measured(m)
        off = ~np.eye(s.shape[1], dtype=bool)
        return float(abs(np.sum((s * np.conj(np.swapaxes(s, 1, 2)))[:, off])) / np.sum(np.abs(s[:, off]) ** 2))

    def __call__(self, m: np.ndarray) -> np.ndarray:
        """M projected onto the fields satisfying (R1) (module doc, R2), complex64 of M's shape."""
        if m.shape != self.shape:
            raise ValueError(f"m: expected shape {self.shape} (N_f, N_u, N_θ), got {m.shape}")
        w = self._weighted(m)
        s = self._measured(w)
        rhs = -(s - np.swapaxes(s, 1, 2))  # G Y + Y Gᵀ = −(S − Sᵀ)
        uh = np.conj(np.swapaxes(self._u, 1, 2))
        z = np.matmul(np.matmul(uh, rhs), np.conj(self._u)) * self._inv_sum  # Z = U^H C Ū / (λ_i + λ_j)
        y = np.matmul(np.matmul(self._u, z), np.swapaxes(self._u, 1, 2))  # Y = U Z Uᵀ
        w += np.matmul(np.conj(self._phi), y)  # W − its component along Φ̄ Y
        return np.ascontiguousarray(w * self._c[None, None, :], dtype=np.complex64)
