"""A frame's imaging on a device: spectrum, projection, confocal image and γ (docs/design.md §5, "GPU backend").

`DeviceImager` is an `fpcore.likelihood.Imager` whose per-frame work runs on a `fpcore.kernel_gpu.Backend`:

1. the RF travels to the device once (in its own dtype), its band-limited spectrum is taken there
   (`Acquisition.spectrum(xp=...)`, docs/design.md §4.1) and projected to plane waves
   (`to_plane_waves(xp=...)`, §4.2): R_θθ stays on the device (`DevicePlaneWaveData`);
2. confocal: |Σ R_θθ e^{iK·r}|² on the device (`GpuTransform`), float32 copied back (§4.3);
3. γ: R_θθ ∘ template on the device (the template — conj(F(r0)) e^{−iK·r0}/‖F‖ times the ramp, paper S7 —
   is built on the host by `Imager.template` and copied to the device once per fingerprint and
   geometry), NUFFT, |·|/‖R‖, float32 copied back (§4.7).

Everything else (output sines, geometry checks, caches, null models) is the host Imager's. R_θθ is
copied to the host only when a caller reads `pw.data` (null models, fingerprint building).
With `emulated_backend()` the same code runs on numpy + finufft (tests without a device).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .acquisition import Acquisition, PlaneWaveData, Probe, to_plane_waves
from .fingerprint import Fingerprint
from .kernel import wavevectors
from .kernel_gpu import Backend, GpuTransform, cuda_backend
from .likelihood import _LRU, Imager, ImagingConfig

__all__ = ["DeviceImager", "DevicePlaneWaveData", "make_imager"]


def make_imager(config: ImagingConfig, max_kernels: int = 4, max_templates: int = 32) -> Imager:
    """A `DeviceImager` on the CUDA device when the GPU kernel would be chosen for `config` — kernel
    'auto' or 'gpu', a usable device, FP_DEVICE not 'cpu' (`GpuTransform.supports`) — and no shift
    apodization; else the host `Imager` (whose 'auto' kernel then picks presum or finufft)."""
    use = (
        config.kernel in ("auto", "gpu")
        and config.apodization_tiles is None
        and GpuTransform.supports(np.zeros((1, 2)), np.zeros((1, 2)), config.grid.ndim)
    )
    if use:
        return DeviceImager(config, max_kernels=max_kernels, max_templates=max_templates)
    return Imager(config, max_kernels, max_templates)


class DevicePlaneWaveData(PlaneWaveData):
    """`PlaneWaveData` whose R_θθ lives on a device (`device`); `data` copies it to the host on first
    read (and keeps the copy), so host code that needs it still works."""

    def __init__(
        self, device: Any, freqs: np.ndarray, out_sines: np.ndarray, in_sines: np.ndarray, c0: float, backend: Backend
    ) -> None:
        self.device = device
        self.backend = backend
        self._host: np.ndarray | None = None
        super().__init__(None, freqs, out_sines, in_sines, c0)  # type: ignore[arg-type]  # data: lazy

    @property
    def data(self) -> np.ndarray:
        if self._host is None:
            self._host = self.backend.to_host(self.device)
        return self._host

    @data.setter
    def data(self, value: np.ndarray | None) -> None:
        self._host = value

    @property
    def shape(self) -> tuple[int, ...]:
        """(N_f, N_o, N_i), without a copy to the host."""
        return tuple(self.device.shape)


class DeviceImager(Imager):
    """`Imager` with spectrum, projection, confocal and γ on `backend` (default: the CUDA device).

    Shift apodization (`apodization_tiles`) is not supported on the device (ValueError).
    """

    def __init__(
        self,
        config: ImagingConfig,
        backend: Backend | None = None,
        max_kernels: int = 4,
        max_templates: int = 32,
    ) -> None:
        if config.apodization_tiles is not None:
            raise ValueError("apodization_tiles: the shift apodization is not implemented on the device")
        super().__init__(config, max_kernels, max_templates)
        self.backend = backend or cuda_backend()
        self._device_templates: _LRU[tuple, Any] = _LRU(max_templates)

    @staticmethod
    def _key(pw: PlaneWaveData) -> tuple:
        shape = pw.shape if isinstance(pw, DevicePlaneWaveData) else pw.data.shape
        return (shape, pw.freqs.tobytes(), pw.out_sines.tobytes(), pw.in_sines.tobytes(), float(pw.c0))

    def kernel(self, pw: PlaneWaveData) -> GpuTransform:
        """The device kernel of this geometry (cached like `Imager.kernel`)."""
        key = self._key(pw)
        kern = self._kernels.get(key)
        if not isinstance(kern, GpuTransform):
            K = wavevectors(pw.freqs, pw.out_sines, pw.in_sines, pw.c0, self.grid.ndim)
            kern = GpuTransform(K, self.grid, eps=self.config.eps, backend=self.backend)
            self._kernels.put(key, kern)
        return kern

    def plane_waves(self, acq: Acquisition) -> DevicePlaneWaveData:
        """R_θθ(f, θ_out, θ_in) computed and kept on the device (docs/design.md §4.1–4.2), of the frame weighted
        by 1/v(t) when the configuration says so (`Imager.weighted`)."""
        xp = self.backend.xp
        acq = self.weighted(acq)
        spec = acq.spectrum(self.config.band[0], self.config.band[1], self.config.n_freq, xp=xp)
        pw = to_plane_waves(spec, self.out_sines_for(acq), xp=xp)
        return DevicePlaneWaveData(pw.data, pw.freqs, pw.out_sines, pw.in_sines, pw.c0, self.backend)

    def _device_data(self, pw: PlaneWaveData) -> Any:
        return pw.device if isinstance(pw, DevicePlaneWaveData) else self.backend.xp.asarray(pw.data)

    def field(self, pw: PlaneWaveData) -> np.ndarray:
        """Complex confocal field B(r) (paper S7 eq. I_BF), copied to the host."""
        return self.backend.to_host(self.kernel(pw).map(self._device_data(pw).ravel()))

    def confocal(self, pw: PlaneWaveData) -> np.ndarray:
        """Confocal image |B(r)|² (docs/design.md §4.3), float32, computed on the device."""
        xp = self.backend.xp
        b = self.kernel(pw).map(self._device_data(pw).ravel())
        return self.backend.to_host((xp.abs(b) ** 2).astype(xp.float32))

    def forget(self, fp: Fingerprint) -> None:
        super().forget(fp)
        self._device_templates.drop(lambda k: k[0] == fp.token)

    def gamma(self, pw: PlaneWaveData, fp: Fingerprint, probe: Probe | None = None) -> np.ndarray:
        """γ-map of one fingerprint (paper eq. P, S7; docs/design.md §4.7), computed on the device."""
        xp = self.backend.xp
        r = self._device_data(pw).ravel()
        r_norm = float(xp.sqrt(xp.vdot(r, r).real))
        if r_norm == 0:
            return np.zeros(self.grid.shape, dtype=np.float32)
        key = (fp.token, self._key(pw))
        t = self._device_templates.get(key)
        if t is None:
            t = xp.asarray(self.template(pw, fp))
            self._device_templates.put(key, t)
        num = self.kernel(pw).execute_device(r * t)
        return self.backend.to_host((xp.abs(num) / r_norm).astype(xp.float32))
