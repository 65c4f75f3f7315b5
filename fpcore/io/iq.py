"""IQ (demodulated) channel data ↔ RF, in USTB's convention.

USTB and PICMUS store demodulated channel data with ``modulation_frequency`` f_m > 0: complex samples
IQ(t_k) at channel times t_k = initial_time + k/fs (``uff.channel_data.time``), made from the RF as

    IQ(t) = LPF[ A(t) e^{-i 2π f_m t} ]        (A: the analytic signal of the RF, or 2× the RF)

(USTB ``preprocess.fast_demodulation``: ``data .* exp(-j*2*pi*f_m*time)`` then a low-pass filter and
decimation; ``hilbert_transform_demodulation`` uses the analytic signal). The phase ramp runs on the
*absolute* channel time t, not on the sample index, so the inverse is

    RF(t) = Re[ IQ(t) e^{+i 2π f_m t} ]

**Choice: IQ is converted to RF on reading.** Every step of fpcore (the spectrum R(f) of
``Acquisition.spectrum``, docs/design.md §4.1, the calibration's time gate, the band estimate) works
on real RF samples; the IQ record's spectrum shifted by +f_m is exactly the positive-frequency band
of that RF, so the conversion loses nothing as long as the RF is sampled above 2 (f_m + fs_IQ/2):
:func:`iq_to_rf` interpolates the IQ band-limitedly (Fourier) by an integer factor M chosen so, then
applies the phase ramp. Handling IQ natively (complex ``Acquisition.rf``) would touch every kernel for
no gain in accuracy; the cost is memory (M× more samples than the IQ, as many as the scanner's RF).
The amplitude scale (a factor 2 between the two USTB demodulators) does not matter: γ is normalised.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.fft as sfft

__all__ = ["iq_to_rf", "rf_to_iq", "rf_upsampling"]

#: The largest RF upsampling factor M accepted: the RF record holds M times the IQ samples, and an IQ record whose
#: modulation frequency is hundreds of times its sampling rate is a misread header, not an acquisition.
MAX_RF_UPSAMPLING = 256


def rf_upsampling(fs: float, f_mod: float) -> int:
    """Smallest integer M with M·fs > 2 (f_m + fs/2) plus one sample of margin: the RF of an IQ record
    sampled at fs around f_m has content up to f_m + fs/2 (e.g. PICMUS: fs = f_m = 5.208 MHz → M = 4,
    20.8 MHz, the rate of its RF files)."""
    if not (fs > 0 and math.isfinite(fs)):
        raise ValueError(f"sampling_frequency: expected a positive frequency in Hz, got {fs}")
    if not (f_mod >= 0 and math.isfinite(f_mod)):
        raise ValueError(f"modulation_frequency: expected a frequency >= 0 Hz, got {f_mod}")
    if f_mod == 0:
        return 1
    ratio = f_mod / fs
    if not ratio < 0.5 * (MAX_RF_UPSAMPLING - 1):  # M = ⌊2 f_m/fs + 1⌋ + 1 ≤ MAX_RF_UPSAMPLING
        raise ValueError(
            f"modulation_frequency: expected below {0.5 * (MAX_RF_UPSAMPLING - 1):g} × the sampling frequency "
            f"({fs:g} Hz; an RF rate of at most {MAX_RF_UPSAMPLING} × it), got {f_mod:g} Hz"
        )
    return int(math.floor(2.0 * ratio + 1.0)) + 1


def _resample(x: np.ndarray, m: int) -> np.ndarray:
    """Band-limited (Fourier) interpolation of complex x (..., N) by the integer factor m: sample j of the
    output is at x's time j/m. The record is zero-padded first so that its end does not wrap onto its start."""
    n = x.shape[-1]
    n_pad = sfft.next_fast_len(n + max(16, n // 8))
    spec = sfft.fft(x, n=n_pad, axis=-1)
    out = np.zeros(x.shape[:-1] + (n_pad * m,), dtype=spec.dtype)
    h = n_pad // 2
    out[..., :h] = spec[..., :h]
    out[..., -(n_pad - h) :] = spec[..., h:]
    if n_pad % 2 == 0:  # split the Nyquist bin between ±fs/2
        out[..., h] = 0.5 * spec[..., h]
        out[..., -h] = 0.5 * spec[..., h]
    return sfft.ifft(out, axis=-1)[..., : n * m] * m


def iq_to_rf(
    iq: np.ndarray, fs: float, t0: float, f_mod: float, upsampling: int | None = None
) -> tuple[np.ndarray, float]:
    """(RF float32 (..., N·M), fs·M) of IQ samples (..., N) at t0 + k/fs: RF(t) = Re[IQ(t) e^{i2π f_m t}].

    M = :func:`rf_upsampling` unless given. With f_m = 0 the data are already at baseband = RF: the real
    part is returned (PICMUS RF files store a zero ``imag``)."""
    iq = np.asarray(iq)
    m = rf_upsampling(fs, f_mod) if upsampling is None else int(upsampling)
    if m < 1:
        raise ValueError(f"upsampling: expected an integer >= 1, got {upsampling}")
    if f_mod == 0 and m == 1:
        return np.ascontiguousarray(np.real(iq), dtype=np.float32), float(fs)
    fs_out = fs * m
    n_out = iq.shape[-1] * m
    ramp = np.exp(2j * np.pi * f_mod * (t0 + np.arange(n_out) / fs_out)).astype(np.complex64)
    lead = iq.reshape(-1, iq.shape[-1])
    out = np.empty((lead.shape[0], n_out), dtype=np.float32)
    step = max(1, (1 << 22) // max(n_out, 1))  # a few tens of MB of complex work at a time
    for i in range(0, lead.shape[0], step):
        up = _resample(lead[i : i + step].astype(np.complex64), m) if m > 1 else lead[i : i + step]
        out[i : i + step] = np.real(up * ramp)
    return out.reshape(iq.shape[:-1] + (n_out,)), float(fs_out)


def rf_to_iq(rf: np.ndarray, fs: float, t0: float, f_mod: float, decimation: int = 1) -> tuple[np.ndarray, float]:
    """(IQ complex64 (..., ⌈N/D⌉), fs/D) of RF samples (..., N) at t0 + k/fs, as USTB's Hilbert
    demodulation makes them: IQ(t) = A(t) e^{-i2π f_m t}, A the analytic signal, low-passed to ±fs/(2D)
    (ideal, in the Fourier domain) and decimated by D; IQ sample j is at t0 + jD/fs."""
    rf = np.asarray(rf, dtype=np.float64)
    d = int(decimation)
    if d < 1:
        raise ValueError(f"decimation: expected an integer >= 1, got {decimation}")
    n = rf.shape[-1]
    n_pad = sfft.next_fast_len(n + max(16, n // 8))
    n_pad += (-n_pad) % d
    spec = sfft.fft(rf, n=n_pad, axis=-1)
    f = sfft.fftfreq(n_pad, 1.0 / fs)
    spec[..., f < 0] = 0.0
    spec[..., f > 0] *= 2.0  # analytic signal A = RF + i H[RF]
    a = sfft.ifft(spec, axis=-1)[..., :n]
    bb = a * np.exp(-2j * np.pi * f_mod * (t0 + np.arange(n) / fs))
    if d == 1:
        return bb.astype(np.complex64), float(fs)
    # Ideal low-pass to |f| < fs/(2D), then keep every D-th sample.
    spec = sfft.fft(bb, n=n_pad, axis=-1)
    spec[..., np.abs(f) >= fs / (2 * d)] = 0.0
    low = sfft.ifft(spec, axis=-1)[..., :n:d]
    return low.astype(np.complex64), float(fs / d)
