"""The null level of γ² under single scattering: the confocal image blurred by the fingerprint's point
response (docs/design.md §4.9, eq. B2), and its mixture with the diffuse level of eq. (B1).

Why a second level. Eq. (B1) (`fpcore.background`) treats the plane-wave coefficients as independent.
Single scattering by a random continuum of scatterers is not: with the Born echo R_j = Σ_s a_s e^{−iK_j·r_s}
of scatterers of density ρ (delta-correlated reflectivity), ⟨R_j R*_j'⟩ = ∫ ρ(r') e^{−i(K_j − K_j')·r'} dr',
so the numerator of γ (paper eq. P), N(r) = Σ_j R_j T_j e^{iK_j·r} with T_j = conj(F_j) e^{−iK_j·r0}, has

    ⟨|N(r)|²⟩ = ∫ ρ(r') |h(r − r')|² dr',    h(Δ) = Σ_j T_j e^{iK_j·Δ},                          (B2)

h the fingerprint's response to one point scatterer: the shot-noise (Campbell) level of a speckle made of
point echoes. Samples that share a wavevector add coherently in it, which eq. (B1) misses; and it follows
the scatterers' density at the resolution of the point response, where eq. (B1) smears it over the
fingerprint's whole time support. Under the suspension's surface, where single scattering dominates,
(B1) under-predicts γ² by up to 5× over a millimetre and the maximum of the map sits there.

ρ is estimated from the frame's own confocal image, I = |Σ_j R_j e^{iK_j·r}|², whose mean is ρ blurred
by the compact confocal point spread |p|²: Q = I ⋆ |h|² (`SpeckleLevel.level`), up to a constant. A
bright grain of the speckle raises γ² around it, and Q with it: the map is then tested against the
hypothesis "single scatterers, as bright as the image shows", not "independent coefficients".

The background is a mixture — single scattering under the surface, diffuse multiple scattering and noise
deeper — so the null level of a map is max(a P A, b Q), a, b fitted on the map's own per-depth means of
γ² (`mix`); the CFAR (fpcore.cfar) then corrects what the mixture leaves, as before.

The price: a target bright enough to stand out of the confocal image raises its own Q, and is tested
against a point scatterer of its own brightness. Measured (docs/design.md §4.9): on the focused
single-scattering speckle the mixture brings target-free maps from 35 % (2-D) and 55 % (3-D) reporting
PFA < 0.01 to 0.7 % and 5 %; on the legacy rig, where the targets stand 2–4× above the fog in the
confocal image, their detections fall from 82 % to 49 %. So it is an option (`NullLevel(single_scattering=
True)`), for backgrounds dominated by single scattering.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
from scipy.signal import fftconvolve

from .acquisition import PlaneWaveData
from .fingerprint import Fingerprint
from .geometry import from_xyz
from .kernel import wavevectors
from .likelihood import Imager

__all__ = ["SpeckleLevel", "compact", "conv_centred", "mix"]

KEEP_ENERGY = 0.999  # share of |h|²'s energy kept in its compact box (the convolution's support)


def compact(
    kernel: np.ndarray, centre: tuple[int, ...], keep: float = KEEP_ENERGY
) -> tuple[np.ndarray, tuple[int, ...]]:
    """The smallest box around `centre` (per axis, from the marginal energy) holding `keep` of the energy
    of a non-negative kernel, and the centre's index inside the box."""
    total = float(kernel.sum())
    if total <= 0:
        return kernel[tuple(slice(c, c + 1) for c in centre)], (0,) * kernel.ndim
    lo: list[int] = []
    hi: list[int] = []
    tail = (1.0 - keep) / (2 * kernel.ndim)
    for ax in range(kernel.ndim):
        m = kernel.sum(axis=tuple(a for a in range(kernel.ndim) if a != ax)) / total
        c = np.cumsum(m)
        a = min(int(np.searchsorted(c, tail)), centre[ax])
        b = max(int(np.searchsorted(c, 1.0 - tail)) + 1, centre[ax] + 1)
        lo.append(a)
        hi.append(min(b, kernel.shape[ax]))
    box = kernel[tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))]
    return np.ascontiguousarray(box), tuple(c - a for c, a in zip(centre, lo, strict=True))


def conv_centred(image: np.ndarray, kernel: np.ndarray, centre: tuple[int, ...]) -> np.ndarray:
    """Q(n) = Σ_m image(m) kernel(n − m + centre): the kernel's node `centre` is its zero lag; zero outside
    the grid (FFT convolution), clipped at 0."""
    full = fftconvolve(image, kernel, mode="full")
    out = full[tuple(slice(c, c + n) for c, n in zip(centre, image.shape, strict=True))]
    return np.maximum(out, 0.0)


def mix(
    gamma2: np.ndarray, diffuse: np.ndarray, speckle: np.ndarray, visible: np.ndarray, censor: float = 8.0
) -> tuple[np.ndarray, tuple[float, float]]:
    """The mixture level max(a·diffuse, b·speckle) (module doc), a, b > 0 (b may be 0) fitted to the
    per-depth means of γ² over the visible nodes by least squares on their logarithms (nodes above
    `censor` × their depth's mean, targets, left out of the means). A maximum rather than a sum: the
    diffuse level P A of eq. (B1) is made from all of the data's energy, single scattering included, so a
    sum would count that energy twice. Returns the level and the shares of depth rows where each
    component sets it (diffuse, single scattering)."""
    nz = gamma2.shape[-1]
    g2 = gamma2.reshape(-1, nz)
    vis = np.broadcast_to(visible, gamma2.shape).reshape(-1, nz)
    mean = np.nanmedian(np.where(vis, g2, np.nan), axis=0) / np.log(2)
    w = (vis & (g2 <= censor * np.nan_to_num(mean, nan=np.inf)[None, :])).astype(np.float64)
    cnt = w.sum(axis=0)
    rows = cnt >= 8

    def row_mean(m: np.ndarray) -> np.ndarray:
        return (m.reshape(-1, nz) * w).sum(axis=0)[rows] / cnt[rows]

    gz, dz, sz = row_mean(gamma2), row_mean(diffuse), row_mean(speckle)
    ok = (gz > 0) & (dz > 0)
    if ok.sum() < 2:
        return diffuse, (1.0, 0.0)
    lg, ld, ls = np.log(gz[ok]), np.log(dz[ok]), np.log(np.maximum(sz[ok], 1e-300))
    # A grid search (two parameters, a few hundred rows). Where a component sets the level, γ² follows
    # it; elsewhere it lies above it: so a lies around the rows' median ratio to the diffuse level, and b
    # between the smallest ratio to the single-scattering level and its median.
    a0 = float(np.median(lg - ld))
    rb = (lg - ls)[sz[ok] > 0]
    b_lo, b_hi = (float(rb.min()) - 1.0, float(np.median(rb)) + 1.0) if rb.size else (0.0, 0.0)
    best = (np.inf, a0, -np.inf)
    for la in a0 + np.linspace(-2.0, 2.0, 41):
        for lb in [-np.inf, *np.linspace(b_lo, b_hi, 81)]:
            pred = np.maximum(la + ld, lb + ls)
            err = float(np.sum((lg - pred) ** 2))
            if err < best[0]:
                best = (err, la, lb)
    _, la, lb = best
    a, b = float(np.exp(la)), float(np.exp(lb))
    level = np.maximum(a * diffuse, b * speckle)
    share = float(np.mean(b * sz > a * dz))
    return level, (1.0 - share, share)


class SpeckleLevel:
    """Q(r) of eq. (B2) on an imager's grid: the frame's confocal image convolved with the fingerprint's
    point response |h|² (cached per fingerprint and geometry, small LRU)."""

    def __init__(self, imager: Imager, cache: int = 8) -> None:
        self.imager = imager
        self._responses: OrderedDict[tuple, tuple[np.ndarray, tuple[int, ...]]] = OrderedDict()
        self._cache = cache

    def point_response(self, pw: PlaneWaveData, fp: Fingerprint) -> tuple[np.ndarray, tuple[int, ...]]:
        """|h(Δ)|² of eq. (B2) in its compact box, and the index of Δ = 0 in it.

        h is the fingerprint's γ numerator for the echo of one point at the grid's centre node r_c,
        R_j = s(f) e^{−iK_j·r_c}, with the fingerprint's own amplitude spectrum s(f) = ‖F(f)‖ standing for
        the transducer's (the same probe made both)."""
        key = (getattr(fp, "token", id(fp)), pw.freqs.tobytes(), pw.out_sines.tobytes(), pw.in_sines.tobytes())
        hit = self._responses.get(key)
        if hit is not None:
            self._responses.move_to_end(key)
            return hit
        grid = self.imager.grid
        K = wavevectors(pw.freqs, pw.out_sines, pw.in_sines, pw.c0, grid.ndim)
        rc = from_xyz(grid.centre_index_point(), grid.ndim)
        spectrum = np.sqrt(np.sum(np.abs(np.asarray(fp.data)) ** 2, axis=(1, 2)))
        echo = np.exp(-1j * (K @ rc)).reshape(pw.data.shape) * spectrum[:, None, None]
        point = PlaneWaveData(echo.astype(np.complex64), pw.freqs, pw.out_sines, pw.in_sines, pw.c0)
        h2 = self.imager.gamma(point, fp).astype(np.float64) ** 2  # |h|² up to a constant (γ's norms)
        hit = compact(h2, tuple(n // 2 for n in grid.shape))
        self._responses[key] = hit
        while len(self._responses) > self._cache:
            self._responses.popitem(last=False)
        return hit

    def level(self, pw: PlaneWaveData, fp: Fingerprint, image: np.ndarray) -> np.ndarray:
        """Q = I ⋆ |h|² on the grid (eq. B2, up to a constant), float64. The image is not censored: a
        bright speckle grain is what raises γ² around it (censoring the grains brighter than 8× their
        depth's mean let 50 % of 3-D target-free maps report PFA < 0.01; docs/design.md §4.9)."""
        kernel, centre = self.point_response(pw, fp)
        return conv_centred(np.asarray(image, np.float64), kernel, centre)
