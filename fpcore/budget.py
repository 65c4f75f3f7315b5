"""Sizes checked before allocating: a memory budget and estimates of what imaging and reading will take.

Every large allocation of a run is sized by its inputs — the imaging grid, the band's frequencies, the
output directions, the dictionary's fingerprints, a file's declared data shape — and a bad input (a
spacing of 1 µm, a frame whose probe positions were multiplied by 200, a sparse HDF5 file declaring
2³¹ samples) can ask for terabytes. The readers, the command line and the processing pipeline estimate
the bytes first (:func:`imaging_bytes`, :func:`array_bytes`) and :func:`check` refuses an estimate above
the budget with a :class:`BudgetError` that says what was asked for, how much, and the limit.

The budget (:func:`memory_budget`) defaults to half of the machine's physical memory
(:data:`DEFAULT_FRACTION`); ``FP_MEMORY_BUDGET`` (``8GiB``, ``512MB``, plain bytes, or ``25%`` of the
RAM) or :func:`set_memory_budget` (the ``fp --memory-budget`` option) change it.

The imaging estimate counts the arrays of one frame (docs/design.md §4.1–4.3, §5): the zero-padded
spectrum (N_u N_θ N_FFT complex64), the plane-wave matrix and its projection (N_f N_o N_θ and
N_f N_o N_u complex64), the NUFFT's points and one template per fingerprint (N_f N_o N_θ), and the maps
on the grid (the NUFFT's oversampled fine grid, the complex field, the image, one γ-map, null level and CFAR
per fingerprint) and the structured kernel's lateral tables (quadratic in the lateral node count), with
per-element constants measured on `fp locate` runs. It is an estimate — within a
factor 2 of the measured peak (tests/test_budget.py checks that on a grid and an output-direction sweep) —
meant to refuse requests that are orders of magnitude too large before they start, not to count every byte.

RF amplitudes are bounded too (:data:`MAX_RF_ABS`): spectra and energies are float32 (max 3.4e38), and
|x|² summed over a record overflows long before |x| reaches float32's limit.
"""

from __future__ import annotations

import math
import os
import re

import numpy as np

__all__ = [
    "DEFAULT_FRACTION",
    "ENV_VAR",
    "MAX_RF_ABS",
    "BudgetError",
    "array_bytes",
    "check",
    "check_rf_amplitude",
    "format_bytes",
    "imaging_bytes",
    "memory_budget",
    "output_directions",
    "parse_bytes",
    "physical_memory",
    "set_memory_budget",
    "spectrum_bins",
]

#: Default budget: this fraction of the machine's physical memory.
DEFAULT_FRACTION = 0.5
#: Environment variable that sets the budget (``8GiB``, ``512MB``, bytes, or ``25%`` of the RAM).
ENV_VAR = "FP_MEMORY_BUDGET"
#: Largest RF amplitude accepted: float32 energies (Σ|x|² over ≤ 1e8 coefficients, each |X(f)| ≤ N_t |x|)
#: stay below float32's 3.4e38 with four decades to spare.
MAX_RF_ABS = 1e12

_override: int | None = None
_UNITS = {"": 1, "b": 1, "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12}
_UNITS.update({"kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40})
_SIZE = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*([a-zA-Z%]*)\s*$")


class BudgetError(ValueError):
    """A request whose estimated size exceeds the memory budget; the message names it, its size and the limit."""


def physical_memory() -> int:
    """Bytes of physical memory (os.sysconf); 8 GiB where the system does not say."""
    try:
        n = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, ValueError, OSError):
        return 8 * 2**30
    return int(n) if n > 0 else 8 * 2**30


def parse_bytes(text: str, what: str = ENV_VAR) -> int:
    """'8GiB', '512MB', '1e9' (bytes) or '25%' (of the physical memory) → bytes (> 0)."""
    m = _SIZE.match(str(text))
    unit = m.group(2).lower() if m else ""
    if not m or (unit not in _UNITS and unit != "%"):
        raise ValueError(f"{what}: expected a size such as 8GiB, 512MB, 1e9 (bytes) or 25% of the RAM, got {text!r}")
    value = float(m.group(1))
    n = value / 100 * physical_memory() if unit == "%" else value * _UNITS[unit]
    if not (math.isfinite(n) and n >= 1):
        raise ValueError(f"{what}: expected a positive size, got {text!r}")
    return int(n)


def set_memory_budget(nbytes: int | None) -> None:
    """Set the process's budget in bytes (None: back to ``FP_MEMORY_BUDGET`` or the default fraction)."""
    global _override
    if nbytes is not None and nbytes < 1:
        raise ValueError(f"memory budget: expected a positive number of bytes, got {nbytes}")
    _override = nbytes


def memory_budget() -> int:
    """The budget in bytes: :func:`set_memory_budget`'s, else ``FP_MEMORY_BUDGET``, else half the RAM."""
    if _override is not None:
        return _override
    env = os.environ.get(ENV_VAR)
    if env:
        return parse_bytes(env, ENV_VAR)
    return int(DEFAULT_FRACTION * physical_memory())


def format_bytes(n: float) -> str:
    """1.5 GiB-style size."""
    if not math.isfinite(n):
        return "an unbounded size"
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if abs(n) >= size:
            return f"{n / size:.3g} {unit}"
    return f"{int(n)} B"


def check(what: str, nbytes: float, hint: str = "", budget: int | None = None) -> None:
    """Refuse (BudgetError) when ``nbytes`` exceeds the budget; ``what`` names the request, ``hint`` the cure."""
    limit = memory_budget() if budget is None else budget
    if not (nbytes <= limit):  # NaN too
        raise BudgetError(
            f"{what}: needs about {format_bytes(nbytes)}, over the memory budget of {format_bytes(limit)}"
            + (f"; {hint}" if hint else "")
            + f" (the budget is set by fp --memory-budget or {ENV_VAR})"
        )


def array_bytes(shape: tuple[int, ...] | list[int], itemsize: int) -> float:
    """Bytes of an array of this shape (float: no integer overflow for absurd declared shapes)."""
    return float(math.prod(float(n) for n in shape)) * itemsize


def spectrum_bins(
    n_samples: int, fs: float, band: tuple[float, float], n_freq: int | None = None, pad: int = 2
) -> tuple[int, int]:
    """(N_FFT, N_f) that ``Acquisition.spectrum`` will use, without computing it (docs/design.md §4.1)."""
    f_min, f_max = band
    if not (f_max > f_min and fs > 0):
        return n_samples, 1
    n_fft = pad * n_samples if n_freq is None else max(n_samples, math.ceil(n_freq * fs / (f_max - f_min)))
    n_band = math.floor(f_max * n_fft / fs) - math.ceil(f_min * n_fft / fs) + 1
    n_f = max(1, n_band if n_freq is None else min(n_band, n_freq))
    return n_fft, n_f


def output_directions(
    counts: tuple[int, ...], s_max: float, f_max: float, c0: float, widths: tuple[float, ...], n: int | None
) -> int:
    """Upper estimate of the number of output directions ``output_sines`` will make: per lateral axis ``n`` or
    max(elements, 2 s_max W/λ_min + 1) (Δs ≤ λ_min/W, docs/design.md §4.2); a matrix array keeps the disc."""
    per_axis = []
    for k, count in enumerate(counts):
        if n is not None:
            per_axis.append(float(n))
        else:
            w = widths[k] if k < len(widths) else 0.0
            per_axis.append(max(float(count), 2 * s_max * w * f_max / c0 + 1 if w > 0 else float(count)))
    total = math.prod(per_axis)
    return int(min(total * (math.pi / 4 if len(per_axis) == 2 else 1.0), 1e18)) or 1


def imaging_bytes(
    grid_shape: tuple[int, ...],
    n_freq: int,
    n_out: int,
    n_in: int,
    n_elements: int,
    n_fft: int,
    n_fingerprints: int = 1,
) -> float:
    """Estimated peak bytes of imaging one frame (module docstring): spectrum, plane waves, NUFFT points and
    templates, and the maps on the grid."""
    g = float(math.prod(float(n) for n in grid_shape))
    ndim = len(grid_shape)
    m = float(n_freq) * n_out * n_in  # plane-wave coefficients
    k = max(n_fingerprints, 1)
    spectrum = 8.0 * n_elements * n_in * (n_fft / 2 + 1) + 3 * 8.0 * n_freq * n_elements * n_in
    projection = 8.0 * n_freq * n_out * n_elements
    # Per coefficient: data, ramp, points, weights, the fingerprint and its template, the null level's
    # aperture factor; per grid node: finufft's fine grid (upsampfac ≤ 2 per axis, complex64), field, image,
    # and per fingerprint γ, its null level and the CFAR's windows. The constants are measured peaks of
    # `fp locate` (2-D, one fingerprint: ≈ 300 B per coefficient, ≈ 190 B per node; tests/test_budget.py).
    coefficients = m * (150 + 100 * k)
    maps = g * (8 * 2.0**ndim + 40 + 120 * k)
    # The structured kernel's per-lateral-axis synthesis tables: (n/2) × ≈3.2 n float64 cosines and sines
    # with their temporaries (fpcore/kernel_presum.py): quadratic in the lateral node count — the term that
    # made a frame with probe positions ×200 (22458 lateral nodes) ask for ~20 GiB.
    lateral = sum(40.0 * float(n) ** 2 for n in grid_shape[:-1])
    return spectrum + projection + coefficients + maps + lateral


def check_rf_amplitude(rf: np.ndarray, field: str) -> None:
    """ValueError when |rf| exceeds :data:`MAX_RF_ABS` (float32 spectra and energies would overflow)."""
    if rf.size == 0 or rf.dtype.kind not in "fc":
        return
    peak = float(max(abs(float(np.max(rf.real))), abs(float(np.min(rf.real)))))
    if rf.dtype.kind == "c":
        peak = max(peak, float(np.max(np.abs(rf.imag))))
    if not peak <= MAX_RF_ABS:
        raise ValueError(
            f"{field}: samples reach {peak:.3g}, above the {MAX_RF_ABS:.0e} that float32 spectra and energies "
            "can hold without overflow; expected values rescaled to a smaller unit"
        )
