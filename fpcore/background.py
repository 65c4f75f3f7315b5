"""The local null level of a γ-map from the data's own energy: the Cauchy–Schwarz bound made local
(docs/design.md §4.9).

γ (paper eq. P) divides |⟨R, F(r)⟩| by the energy of the *whole* record, so its background follows the
echo energy: high under a strong interface, low in deep, attenuated regions. Under the null hypothesis
of the paper's S6 — reflection-matrix coefficients that are independent random variables — but with a
variance v(θ_out, θ_in, t) that changes with time (the fog's echo decays with depth), the numerator
N(r) = Σ_f Σ_{o,i} R F*(r) is still a sum of many independent terms, circular complex Gaussian, with

    ⟨|N(r)|²⟩ ∝ P(r) = Σ_{o,i} Σ_t E_R(o, i, t) E_F(o, i, t − δτ_oi(r)),                      (B1)

E_R = |r(o, i, t)|² and E_F = |f(o, i, t)|² the energy envelopes of the data and of the fingerprint at
r0 (analytic signals in the plane-wave basis), δτ_oi(r) = [(s_o + s_i)·Δρ + (c_o + c_i)Δz]/c0 the
virtual shift's delay (paper eq. BF). P(r) is the energy of R *inside F(r)'s own time support*,
weighted by F's energy: Cauchy–Schwarz applied locally. In the frequency domain the cross-correlation
over t is a product of envelope spectra, so

    P(r) = Re Σ_ν Σ_{o,i} w_ν Ê_R(ν, o, i) Ê_F*(ν, o, i) e^{iK_ν·(r − r0)},  K_ν = 2πν/c0 (s_o + s_i, c_o + c_i),

ν ≥ 0 the envelope frequencies (w_0 = 1, w_ν>0 = 2): the same beamforming sum as γ's numerator
(docs/design.md §5) at baseband, one type-1 NUFFT per map. The null level of γ² is then
γ_M²(r) = κ P(r)/(‖R‖² ‖F‖²), with one constant κ per map (it absorbs the correlation of neighbouring
plane-wave and time samples) estimated robustly from the map itself, so that T = γ²/γ_M² is Exp(1) under
the null at every depth and lateral position — no depth window to choose.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
from scipy.ndimage import uniform_filter

from .acquisition import Acquisition, PlaneWaveData, Spectrum, to_plane_waves
from .cfar import DEFAULT_CFAR, check_cfar
from .envelope_loops import envelope_columns, envelope_spectrum
from .fingerprint import Fingerprint
from .geometry import from_xyz
from .grid import Grid
from .kernel import GridTransform, Kernel, wavevectors
from .kernel_presum import PresumTransform
from .likelihood import Imager
from .speckle_level import SpeckleLevel, mix
from .support import SupportProduct, angular_support

__all__ = ["envelope_spectrum", "NullPower", "NullLevel"]


class NullPower:
    """P(r) of eq. (B1) on a grid, with envelope kernels cached per geometry (small LRU)."""

    def __init__(self, grid: Grid, eps: float = 1e-4, cache: int = 4) -> None:
        self.grid = grid
        self.eps = eps
        self._kernels: OrderedDict[tuple, Kernel] = OrderedDict()
        # Ê_F e^{−iK·r0} per fingerprint, with its output directions
        self._fingerprints: OrderedDict[tuple, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._data: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # Ê_R of the last frame, directions made
        self._weights = SupportProduct()  # the kernel's weights, zero off the fingerprint's support
        self._cache = cache

    @staticmethod
    def uniform(freqs: np.ndarray) -> bool:
        """Eq. (B1) by envelope spectra needs (nearly) uniformly spaced frequencies: a periodic delay axis.
        A band decimated to n_freq bins (fpcore Spectrum: bins rounded from a linspace) qualifies; its mean
        step is used — the level is a smooth energy envelope, a fraction of a bin does not move it."""
        f = np.asarray(freqs, float)
        if f.size < 3:
            return True
        d = np.diff(f)
        return bool(d.min() > 0 and d.std() <= 0.25 * d.mean())

    def _kernel(self, pw: PlaneWaveData) -> tuple[Kernel, np.ndarray]:
        freqs = np.asarray(pw.freqs, float)
        if not self.uniform(freqs):
            raise ValueError("freqs: the null level needs uniformly spaced frequencies")
        df = float((freqs[-1] - freqs[0]) / (freqs.size - 1)) if freqs.size > 1 else 1.0
        nu = df * np.arange(freqs.size)
        key = (freqs.size, df, pw.out_sines.tobytes(), pw.in_sines.tobytes(), float(pw.c0))
        kern = self._kernels.get(key)
        if kern is None:
            # The same sum as γ's numerator at baseband (module doc): the lattice pre-sum kernel when the
            # sines lie on one lattice (docs/design.md §5; ≈ 7× faster than finufft on a 76×76×143 grid,
            # equal to it within the tolerance), else finufft's type 1.
            if PresumTransform.applicable(pw.out_sines, pw.in_sines, self.grid.ndim):
                kern = PresumTransform(nu, pw.out_sines, pw.in_sines, pw.c0, self.grid, eps=self.eps)
            else:
                K = wavevectors(nu, pw.out_sines, pw.in_sines, pw.c0, self.grid.ndim)
                kern = GridTransform(K, self.grid, eps=self.eps)
            self._kernels[key] = kern
            while len(self._kernels) > self._cache:
                self._kernels.popitem(last=False)
        else:
            self._kernels.move_to_end(key)
        return kern, nu

    def _fingerprint_side(self, pw: PlaneWaveData, fp: Fingerprint, nu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """conj(Ê_F) e^{−iK·r0} with the one-sided weights (w_0 = 1, w_ν>0 = 2) on the output directions where
        it is not zero (a fingerprint's angular support), (N_ν, N_support, N_i), and those directions; cached
        per fingerprint."""
        key = (getattr(fp, "token", id(fp)), nu.tobytes(), pw.out_sines.tobytes(), pw.in_sines.tobytes())
        hit = self._fingerprints.get(key)
        if hit is None:
            t = np.conj(envelope_spectrum(np.asarray(fp.data)))
            t[1:] *= 2.0
            support = angular_support(t)
            K = wavevectors(nu, pw.out_sines, pw.in_sines, pw.c0, self.grid.ndim)
            t = (t.ravel() * np.exp(-1j * (K @ from_xyz(fp.r0, self.grid.ndim)))).astype(np.complex64)
            t = np.ascontiguousarray(t.reshape(np.shape(fp.data))[:, support])
            hit = self._fingerprints[key] = (t, support)
            while len(self._fingerprints) > 8 * self._cache:
                self._fingerprints.popitem(last=False)
        return hit

    def _data_side(self, pw: PlaneWaveData, outputs: np.ndarray) -> np.ndarray:
        """Ê_R of this frame's data, (N_ν, N_o, N_i), made once per frame and output direction whatever the
        number of fingerprints, and only on the directions `outputs` asked for so far: the product with a
        fingerprint's side needs no more (≈ 20 % of the full-size frame's directions). The buffer is kept
        between frames of one shape; a direction not yet made for this frame holds an earlier frame's values
        and is never read (fpcore.envelope_loops, by frequency autocorrelation)."""
        data = np.ascontiguousarray(pw.data, dtype=np.complex64)
        if self._data is None or self._data[1].shape != data.shape:
            self._data = (pw.data, np.zeros(data.shape, np.complex64), np.zeros(data.shape[1], bool))
        elif self._data[0] is not pw.data:  # a new frame (its own array: its id is not reused while held)
            self._data = (pw.data, self._data[1], np.zeros(data.shape[1], bool))
        _, e, done = self._data
        need = outputs[~done[outputs]]
        envelope_columns(data, need, e)
        done[need] = True
        return e

    def power(self, pw: PlaneWaveData, fp: Fingerprint) -> np.ndarray:
        """P(r) ≥ 0 on the grid (eq. B1), float64."""
        kern, nu = self._kernel(pw)
        t, support = self._fingerprint_side(pw, fp, nu)
        w = self._weights(self._data_side(pw, support), support, t)
        p = kern(w.ravel()).real.astype(np.float64)
        return np.maximum(p, 0.0)

    def gamma_level(self, pw: PlaneWaveData, fp: Fingerprint) -> np.ndarray:
        """P(r)/(‖R‖² ‖F‖²): the null level of γ² up to the per-map constant κ (module doc)."""
        r2 = float(np.vdot(pw.data, pw.data).real)
        return self.power(pw, fp) / max(r2 * fp.norm2, 1e-300)


class NullLevel:
    """γ²'s null level up to a constant, from physics: the data's energy inside the fingerprint's own time
    support (eq. B1, per frame) times the fingerprint's aperture factor A(r) (per fingerprint and
    geometry, cached), and the region where the fingerprint can be tested at all.

    Why A(r). The output plane waves are sampled finer than the array's own Nyquist step so that the
    receive focus does not alias inside the field of view (docs/design.md §4.2); neighbouring output
    directions then carry correlated data, and the share of a shifted fingerprint's energy that the
    physical aperture can receive falls as the fingerprint is moved away from it. Eq. (B1) treats the
    plane-wave coefficients as independent and misses that lateral factor; A(r) = E|N(r)|² for
    independent, identically distributed element data (the paper's S6 null in the element basis) supplies
    it — estimated by passing `n_noise` white-noise frames through the same projection and kernel,
    smoothed over one resolution cell, normalised to a maximum of 1. Where A(r) < `min_aperture` the
    fingerprint, moved there, misses the array almost entirely: γ cannot test the hypothesis and the
    node is not searched (`visible`).

    Single scattering (`single_scattering`, off by default; fpcore.speckle_level, eq. B2). Given the map,
    the level is the mixture max(a P A, b Q) fitted to the map's per-depth means, Q the frame's confocal
    image blurred by the fingerprint's point response: where the beads' single scattering dominates, under
    the surface, P A is too smooth in depth and too low. It costs power on targets that stand out of the
    confocal image (module doc there). `last_shares` holds the last fit's shares of depth rows set by
    each component (diffuse, single scattering).

    `cfar`: the named CFAR setting that corrects this level (fpcore.cfar.CFAR_NAMES: "compact", the default —
    calibrated on the beads' focused single-scattering speckle —, "wide", the earlier default, or "both";
    docs/design.md §4.9).
    """

    def __init__(
        self,
        imager: Imager,
        n_noise: int = 24,
        min_aperture: float = 0.1,
        seed: int = 0,
        cache: int = 8,
        single_scattering: bool = False,
        cfar: str = DEFAULT_CFAR,
    ) -> None:
        check_cfar(cfar)  # a clear error for an unknown name, at construction
        self.imager = imager
        self.single_scattering = single_scattering
        self.cfar = cfar
        self.speckle = SpeckleLevel(imager)
        self.last_shares: tuple[float, float] = (1.0, 0.0)
        self._image: tuple[np.ndarray, np.ndarray] | None = None  # the last frame's confocal image (any fp)
        self.power = NullPower(imager.grid, eps=max(imager.config.eps, 1e-4))
        self.n_noise = n_noise
        self.min_aperture = min_aperture
        self.seed = seed
        self._apertures: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._cache = cache

    def aperture(
        self, acq: Acquisition, pw: PlaneWaveData, fp: Fingerprint, resolution: tuple[float, float]
    ) -> np.ndarray:
        """A(r) in [0, 1] (class doc) for the geometry of `acq` and `pw`, cached per fingerprint and geometry."""
        probe, seq = acq.probe, acq.sequence
        shape = (pw.freqs.size, probe.n_elements, seq.n_waves)
        key = (
            getattr(fp, "token", id(fp)),
            shape,
            pw.freqs.tobytes(),
            pw.out_sines.tobytes(),
            probe.positions.tobytes(),
            seq.sines.tobytes(),
            float(pw.c0),
        )
        a = self._apertures.get(key)
        if a is not None:
            self._apertures.move_to_end(key)
            return a
        rng = np.random.default_rng(self.seed)
        acc = np.zeros(self.imager.grid.shape)
        for _ in range(self.n_noise):
            noise = rng.standard_normal(shape, dtype=np.float32) + 1j * rng.standard_normal(shape, dtype=np.float32)
            pn = to_plane_waves(Spectrum(noise, pw.freqs, pw.c0, probe, seq), pw.out_sines)
            r2 = float(np.vdot(pn.data, pn.data).real)
            acc += self.imager.gamma(pn, fp).astype(np.float64) ** 2 * r2
        grid = self.imager.grid
        cells = [resolution[0]] * (grid.ndim - 1) + [resolution[1]]
        size = [max(1, int(round(c / s))) | 1 for c, s in zip(cells, grid.spacing, strict=True)]
        a = uniform_filter(acc, size, mode="nearest")
        a = (a / max(float(a.max()), 1e-300)).astype(np.float32)
        self._apertures[key] = a
        while len(self._apertures) > self._cache:
            self._apertures.popitem(last=False)
        return a

    def level(
        self,
        acq: Acquisition,
        pw: PlaneWaveData,
        fp: Fingerprint,
        resolution: tuple[float, float],
        gamma: np.ndarray | None = None,
        image: np.ndarray | None = None,
        aperture: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(level, visible): γ²'s null level up to a constant, and the nodes where the fingerprint can be
        tested (A ≥ `min_aperture`). With the map `gamma` (and `single_scattering`), the level is the
        fitted mixture with the single-scattering level (class doc); `image`: the frame's confocal image
        if the caller has it (else it is made here, once per frame); `aperture`: A(r) already made by
        `aperture` (a caller on another thread than the imager's must pass it: making it runs the imager's
        kernel, which is not re-entrant)."""
        a = self.aperture(acq, pw, fp, resolution) if aperture is None else aperture
        if self.power.uniform(pw.freqs):
            lev = self.power.gamma_level(pw, fp) * a
        else:  # decimated band (n_freq): no periodic envelope spectrum; the CFAR takes the depth trend alone
            lev = a.astype(np.float64)
        visible = a >= self.min_aperture
        if gamma is not None and self.single_scattering:
            q = self.speckle.level(pw, fp, self.confocal(pw) if image is None else image)
            lev, self.last_shares = mix(np.asarray(gamma, np.float64) ** 2, lev, q, visible)
        return lev, visible

    def confocal(self, pw: PlaneWaveData) -> np.ndarray:
        """The frame's confocal image (paper S7), made once per frame whatever the number of fingerprints."""
        if self._image is None or self._image[0] is not pw.data:  # keyed by the frame's array itself (as Ê_R)
            self._image = (pw.data, self.imager.confocal(pw))
        return self._image[1]
