"""Confocal images and γ-maps of acquisitions (docs/design.md §4.3, §4.7; paper eq. P and S7).

γ(r) = |Σ_f Tr{R(f) F(r, f)^†}| / √(Σ_f ‖R(f)‖²_F · Σ_f ‖F(r, f)‖²_F)

is computed in the plane-wave basis, where Tr{R F^†} = Σ_{o,i} R_θθ F*_θθ and the virtual shift is a
phase ramp, so the numerator over positions is the beamforming kernel applied to R ∘ F*(r0)
(paper S7, eq. gamma_BF). By Cauchy–Schwarz 0 ≤ γ ≤ 1.

Normalisation choice (docs/design.md §4.7): the paper prints the denominator with unsquared Frobenius norms
(eq. P); we use squared norms so that γ is a true normalised correlation bounded by 1. With a
unitary shift ‖F(r)‖ is independent of r, so the two differ by a constant factor per frame and
maps, peak positions and contrasts agree.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from .acquisition import Acquisition, PlaneWaveData, Probe, output_sines, to_plane_waves
from .fingerprint import Fingerprint, angular_mask, check_geometry
from .grid import Grid
from .kernel import GridTransform, Kernel, KernelType, wavevectors
from .kernel_gpu import GpuTransform
from .kernel_presum import PresumTransform
from .support import SupportProduct, angular_support
from .time_weighting import inverse_variance_weighted

__all__ = ["Imager", "ImagingConfig", "KERNELS", "make_kernel"]

#: The kernel classes by name (docs/design.md §5); kernel="auto" takes the first, in this order, that
#: supports the geometry: cufinufft on a CUDA device when one is usable and FP_DEVICE is not 'cpu'
#: (fpcore.kernel_gpu), the lattice pre-sum kernel, else the general finufft type-1.
KERNELS: dict[str, KernelType] = {"gpu": GpuTransform, "presum": PresumTransform, "nufft": GridTransform}

_REQUIRES = {
    "presum": "transmit and output sines on one lattice (and numba)",
    "gpu": "a usable CUDA device with CuPy and cufinufft (the 'gpu' extra) and FP_DEVICE not 'cpu'",
}


def make_kernel(kind: str, pw: PlaneWaveData, grid: Grid, eps: float) -> Kernel:
    """The kernel of `pw`'s geometry on `grid`: kind 'auto' (the first of `KERNELS` that supports it) or
    a name of `KERNELS` (ValueError if that class does not support the geometry)."""
    if kind == "auto":
        kinds = [k for k in KERNELS.values() if k.supports(pw.out_sines, pw.in_sines, grid.ndim)]
        if not kinds:
            raise ValueError(f"kernel: none of {sorted(KERNELS)} supports this geometry")
        kt = kinds[0]
    elif kind in KERNELS:
        kt = KERNELS[kind]
        if not kt.supports(pw.out_sines, pw.in_sines, grid.ndim):
            raise ValueError(f"kernel: {kind!r} needs {_REQUIRES.get(kind, 'another geometry')}")
    else:
        raise ValueError(f"kernel: expected 'auto' or one of {sorted(KERNELS)}, got {kind!r}")
    return kt.for_geometry(pw.freqs, pw.out_sines, pw.in_sines, pw.c0, grid, eps)


_K = TypeVar("_K")
_V = TypeVar("_V")


class _LRU(Generic[_K, _V]):
    """A mapping bounded to `maxsize` entries, dropping the least recently used."""

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValueError(f"cache size: expected at least 1, got {maxsize}")
        self.maxsize = maxsize
        self._data: OrderedDict[_K, _V] = OrderedDict()

    def __len__(self) -> int:
        return len(self._data)

    def get(self, key: _K) -> _V | None:
        value = self._data.get(key)
        if value is not None:
            self._data.move_to_end(key)
        return value

    def put(self, key: _K, value: _V) -> None:
        self._data[key] = value
        self._data.move_to_end(key)
        while len(self._data) > self.maxsize:
            self._data.popitem(last=False)

    def drop(self, which: Callable[[_K], bool]) -> None:
        for key in [k for k in self._data if which(k)]:
            del self._data[key]


@dataclass(frozen=True)
class ImagingConfig:
    """What the processor does to every frame: band [f_min, f_max] (Hz), number of frequencies kept,
    output directions (None: sampled from the probe, `output_sines`), grid, NUFFT accuracy.

    kernel: 'auto' (cufinufft on a usable CUDA device, fpcore.kernel_gpu; else the structured pre-sum
    kernel when the sines allow it, else finufft) or a name of
    `KERNELS`: 'gpu', 'nufft' or 'presum' (`make_kernel`).
    apodization_tiles: split the grid into this many tiles per axis and apply the shift apodization
    A(θ_out, r) A(θ_in, r) of paper eq. BF at each tile's centre (docs/design.md §5); None: no shift apodization
    (the angular filter acts at r0 only and ‖F(r)‖ is constant).
    time_weighting: weigh every frame by its own inverse variance 1/v(t) before the band selection (eq. W1,
    fpcore.time_weighting): γ's numerator becomes the matched filter in a fog that decays in time.
    """

    grid: Grid
    band: tuple[float, float]
    n_freq: int | None = None
    out_sines: np.ndarray | None = None
    eps: float = 1e-5
    apodization_tiles: tuple[int, ...] | None = None
    kernel: str = "auto"
    time_weighting: bool = False

    def __post_init__(self) -> None:
        if self.kernel != "auto" and self.kernel not in KERNELS:
            raise ValueError(f"kernel: expected 'auto' or one of {sorted(KERNELS)}, got {self.kernel!r}")


class Imager:
    """Holds one imaging configuration and the kernels of the geometries it has seen.

    Kernels (finufft plans with their points) are cached per geometry — the content of (frequencies,
    sines, c0) — so that every frame of the same acquisition geometry reuses them; γ templates per
    (fingerprint token, geometry) (`Fingerprint.token`: never reused, unlike ``id``). Both caches keep
    the `max_kernels` / `max_templates` most recently used entries.
    """

    def __init__(self, config: ImagingConfig, max_kernels: int = 4, max_templates: int = 32) -> None:
        self.config = config
        self._kernels: _LRU[tuple, Kernel] = _LRU(max_kernels)
        self._templates: _LRU[tuple, np.ndarray] = _LRU(max_templates)
        self._tiled: _LRU[tuple, list[tuple[tuple[slice, ...], GridTransform, np.ndarray]]] = _LRU(max_kernels)
        # a template on its angular support: (output directions where it is not zero, its values there)
        self._supported: _LRU[tuple, tuple[np.ndarray, np.ndarray]] = _LRU(max_templates)
        self._weights = SupportProduct()  # γ's numerator weights, zero off the fingerprint's support

    @property
    def grid(self) -> Grid:
        return self.config.grid

    def out_sines_for(self, acq: Acquisition) -> np.ndarray:
        if self.config.out_sines is not None:
            return np.asarray(self.config.out_sines, dtype=float)
        g = self.grid
        width = (float(np.ptp(g.x)), float(np.ptp(g.y)) if g.y is not None else 0.0)
        return output_sines(
            acq.probe, acq.c0, self.config.band[1], field_width=width, transmit_sines=acq.sequence.sines
        )

    def weighted(self, acq: Acquisition) -> Acquisition:
        """The frame as this imager maps it: weighted by 1/v(t) with `time_weighting` (eq. W1), else itself."""
        return inverse_variance_weighted(acq) if self.config.time_weighting else acq

    def plane_waves(self, acq: Acquisition) -> PlaneWaveData:
        """Band selection and output projection: R_θθ(f, θ_out, θ_in) (docs/design.md §4.1–4.2), of the frame
        weighted by 1/v(t) when the configuration says so (`weighted`)."""
        acq = self.weighted(acq)
        spec = acq.spectrum(self.config.band[0], self.config.band[1], self.config.n_freq)
        return to_plane_waves(spec, self.out_sines_for(acq))

    @staticmethod
    def _key(pw: PlaneWaveData) -> tuple:
        return (pw.data.shape, pw.freqs.tobytes(), pw.out_sines.tobytes(), pw.in_sines.tobytes(), float(pw.c0))

    def cache_key(self, pw: PlaneWaveData) -> tuple:
        """The content a kernel of this imager for `pw` depends on: grid axes, accuracy and geometry."""
        return (tuple(a.tobytes() for a in self.grid.axes), self.config.eps, self._key(pw))

    def kernel(self, pw: PlaneWaveData) -> Kernel:
        """The kernel for this geometry (`make_kernel` with `ImagingConfig.kernel`): by default the
        structured pre-sum kernel when transmit and output sines lie on one lattice (docs/design.md §5,
        fpcore.kernel_presum), else the general finufft type-1."""
        key = self._key(pw)
        kern = self._kernels.get(key)
        if kern is None:
            kern = make_kernel(self.config.kernel, pw, self.grid, self.config.eps)
            self._kernels.put(key, kern)
        return kern

    def _run(self, pw: PlaneWaveData, weights: np.ndarray) -> np.ndarray:
        """Σ w e^{iK·r} (paper S7) for weights already multiplied by the kernel's ramp (`Kernel.ramp`)."""
        return self.kernel(pw).execute_ramped(weights)

    def template(self, pw: PlaneWaveData, fp: Fingerprint) -> np.ndarray:
        """conj(F(r0)) e^{-iK·r0} / ‖F‖ times the kernel's grid ramp (paper S7), cached per fingerprint
        (its token) and geometry."""
        key = (fp.token, self._key(pw))
        t = self._templates.get(key)
        if t is None:
            check_geometry(fp, pw)
            norm = np.sqrt(fp.norm2)
            if norm == 0:
                raise ValueError(f"fingerprint '{fp.name}': is identically zero (gate or filter removed all)")
            t = fp.centred_conj(self.grid.ndim) * (self.kernel(pw).ramp / np.float32(norm))
            self._templates.put(key, t)
        return t

    def forget(self, fp: Fingerprint) -> None:
        """Drop cached templates of a fingerprint (after it is removed from a dictionary)."""
        self._templates.drop(lambda k: k[0] == fp.token)
        self._supported.drop(lambda k: k[0] == fp.token)
        self._tiled.drop(lambda k: k[0] == fp.token)

    def _weights_of(self, pw: PlaneWaveData, fp: Fingerprint) -> np.ndarray:
        """R ∘ template (γ's numerator weights, flat), made on the template's angular support only
        (fpcore.support): not a full-size product on every map."""
        key = (fp.token, self._key(pw))
        hit = self._supported.get(key)
        if hit is None:
            t = self.template(pw, fp).reshape(pw.data.shape)
            support = angular_support(t)
            hit = (support, np.ascontiguousarray(t[:, support]))
            self._supported.put(key, hit)
        support, t_sup = hit
        return self._weights(pw.data, support, t_sup).ravel()

    def field(self, pw: PlaneWaveData) -> np.ndarray:
        """Complex confocal field B(r) = Σ R_θθ e^{iK·r} (paper S7 eq. I_BF; F ≡ 1)."""
        return self.kernel(pw)(pw.data.ravel())

    def confocal(self, pw: PlaneWaveData) -> np.ndarray:
        """Confocal image I(r) = |B(r)|² (docs/design.md §4.3), float32 on the grid."""
        return (np.abs(self.field(pw)) ** 2).astype(np.float32)

    def gamma(self, pw: PlaneWaveData, fp: Fingerprint, probe: Probe | None = None) -> np.ndarray:
        """γ-map of one fingerprint on the grid, 0 ≤ γ ≤ 1 (paper eq. P, S7; docs/design.md §4.7).

        With `apodization_tiles` set, `probe` gives the aperture of A(θ, r) (paper S2, Fig. S9).
        """
        r = pw.data.ravel()
        r_norm = np.sqrt(float(np.vdot(r, r).real))
        if r_norm == 0:
            return np.zeros(self.grid.shape, dtype=np.float32)
        if self.config.apodization_tiles is not None:
            if probe is None:
                raise ValueError("probe: needed for the shift apodization A(θ, r) (apodization_tiles is set)")
            return self._gamma_tiled(pw, fp, probe, r, r_norm)
        num = self._run(pw, self._weights_of(pw, fp))
        return (np.abs(num) / r_norm).astype(np.float32)

    def _tiles(self) -> list[tuple[tuple[slice, ...], Grid]]:
        tiles = self.config.apodization_tiles or ()
        if len(tiles) != self.grid.ndim:
            raise ValueError(f"apodization_tiles: expected {self.grid.ndim} counts (one per axis), got {tiles}")
        edges = [np.linspace(0, a.size, n + 1).astype(int) for a, n in zip(self.grid.axes, tiles, strict=True)]
        out = []
        for idx in np.ndindex(*tiles):
            sl = tuple(slice(e[i], e[i + 1]) for e, i in zip(edges, idx, strict=True))
            axes = [a[s] for a, s in zip(self.grid.axes, sl, strict=True)]
            sub = Grid.from_axes(axes)
            out.append((sl, sub))
        return out

    def _gamma_tiled(
        self, pw: PlaneWaveData, fp: Fingerprint, probe: Probe, r: np.ndarray, r_norm: float
    ) -> np.ndarray:
        """γ with S = A(θ, r_t) P(θ, Δr) per tile t (paper eq. BF), normalised by ‖F ∘ A‖ per tile."""
        key = (fp.token, self._key(pw), probe.positions.tobytes(), probe.pitch)  # A(θ, r) depends on the probe
        cached = self._tiled.get(key)
        if cached is None:
            check_geometry(fp, pw)
            K = wavevectors(pw.freqs, pw.out_sines, pw.in_sines, pw.c0, self.grid.ndim)
            base = fp.centred_conj(self.grid.ndim).reshape(fp.data.shape)
            cached = []
            for sl, sub in self._tiles():
                centre = sub.centre_index_point()
                a = (
                    angular_mask(pw.out_sines, centre, probe)[:, None]
                    & angular_mask(pw.in_sines, centre, probe)[None, :]
                ).astype(np.float32)
                t = (base * a[None]).ravel()
                norm = float(np.sqrt(np.vdot(t, t).real))
                kern = GridTransform(K, sub, eps=self.config.eps)
                cached.append((sl, kern, t * kern.ramp / np.float32(max(norm, 1e-300))))
            self._tiled.put(key, cached)
        out = np.zeros(self.grid.shape, dtype=np.float32)
        for sl, kern, t in cached:
            out[sl] = np.abs(kern.execute_ramped(r * t)) / r_norm
        return out
