"""Fingerprint construction for the dictionary entries (docs/design.md §4.4–4.5): calibrations, checked
against the data they will be matched with, and numerical models from a spec string.

Used by the processing pipeline (``services.pipeline``) and therefore by the processor node and
`fp locate`; no CLI or bus code here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from fpcore import Fingerprint, PlaneWaveData, from_calibration, mirror_fingerprint, point_fingerprint
from services.registry import FingerprintSpec
from services.units import parse_length

if TYPE_CHECKING:  # pragma: no cover
    from fpcore import Imager
    from fpcore.acquisition import Acquisition

__all__ = [
    "build_fingerprint",
    "build_model",
    "calibration_position",
    "check_calibration",
    "check_r0",
    "parse_model",
    "recorded_position",
]


def parse_model(spec: str) -> tuple[str, dict[str, float]]:
    """(kind, parameters in SI) of a model spec ``point`` or ``mirror:L=2mm,alpha=10`` (L > 0 a length,
    alpha a finite angle in degrees, returned in radians); ValueError naming the part at fault."""
    kind, _, rest = str(spec).strip().partition(":")
    if kind == "point":
        if rest.strip():
            raise ValueError(f"--model: 'point' takes no parameters, got {spec!r}")
        return kind, {}
    if kind != "mirror":
        raise ValueError(f"--model: unknown model {kind!r} (expected 'point' or 'mirror:L=…,alpha=…')")
    params: dict[str, str] = {}
    for kv in (p.strip() for p in rest.split(",") if p.strip()):
        key, eq, value = kv.partition("=")
        if not eq or key.strip() not in ("L", "alpha") or key.strip() in params:
            raise ValueError(f"--model: expected mirror:L=<length>[,alpha=<degrees>], got {kv!r} in {spec!r}")
        params[key.strip()] = value.strip()
    if "L" not in params:
        raise ValueError(f"--model: mirror needs L, e.g. mirror:L=2mm,alpha=10, got {spec!r}")
    length = parse_length(params["L"], "--model L")
    if not length > 0:
        raise ValueError(f"--model L: expected a length > 0, got {params['L']!r}")
    try:
        alpha = float(params.get("alpha", "0"))
    except ValueError:
        raise ValueError(f"--model alpha: expected an angle in degrees, got {params['alpha']!r}") from None
    if not np.isfinite(alpha):
        raise ValueError(f"--model alpha: expected a finite angle in degrees, got {params['alpha']!r}")
    return kind, {"L": length, "alpha": float(np.deg2rad(alpha))}


def build_model(spec: str, pw: PlaneWaveData, r0: np.ndarray = (0.0, 0.0, 0.0), name: str | None = None) -> Fingerprint:
    """Numerical fingerprint from a spec: ``point`` or ``mirror:L=2mm,alpha=10`` (alpha in degrees)."""
    kind, params = parse_model(spec)
    r0 = np.asarray(r0, dtype=float)
    if kind == "point":
        return point_fingerprint(pw.freqs, pw.out_sines, pw.in_sines, pw.c0, r0, name=name or "point")
    return mirror_fingerprint(
        pw.freqs, pw.out_sines, pw.in_sines, pw.c0, params["L"], params["alpha"], r0=r0, name=name or "mirror"
    )


def check_calibration(cal: Acquisition, data: Acquisition) -> None:
    """The calibration must come from the same probe, sequence, sampling and sound speed."""
    if cal.probe.n_elements != data.probe.n_elements or not np.allclose(
        cal.probe.positions, data.probe.positions, atol=1e-7
    ):
        raise ValueError("calibration probe: element positions differ from the data's (same probe expected)")
    if cal.sequence.n_waves != data.sequence.n_waves or not np.allclose(
        cal.sequence.sines, data.sequence.sines, atol=1e-9
    ):
        raise ValueError("calibration sequence: plane-wave angles differ from the data's (same sequence expected)")
    if abs(cal.fs - data.fs) > 1e-6 * data.fs:
        raise ValueError(f"calibration sampling_frequency: {cal.fs:g} Hz, data has {data.fs:g} Hz (same expected)")
    if abs(cal.c0 - data.c0) > 1e-6 * data.c0:
        raise ValueError(f"calibration sound_speed: {cal.c0:g} m/s, data has {data.c0:g} m/s (same expected)")


def recorded_position(cal: Acquisition) -> tuple[np.ndarray | None, float | None]:
    """(r0 (x, y, z), diameter), in metres, that a calibration file records (`Acquisition.ground_truth`):
    its ``r0_m``, else its first target's position; its ``diameter_m``, else its first target's. None
    where the file records nothing."""
    truth = cal.ground_truth
    target = truth.targets[0] if truth.targets else None
    r0 = truth.r0_m if truth.r0_m is not None else target.position_m if target is not None else None
    d = truth.diameter_m if truth.diameter_m is not None else target.diameter_m if target is not None else None
    return (None if r0 is None else np.asarray(r0, float)), (None if d is None else float(d))


def check_r0(r0: np.ndarray, cal: Acquisition, resolution: tuple[float, float], force: bool = False) -> str | None:
    """Compare a given r0 with the position the calibration file records (truth ``r0_m`` or its first
    target): farther than one resolution cell (lateral δρ_D, axial c0/(2Δf)) is refused — the fingerprint
    would be shifted from where it was measured and every detection displaced by the difference — unless
    ``force``, which turns the refusal into the returned warning. None when they agree or nothing is
    recorded."""
    rec, _ = recorded_position(cal)
    if rec is None:
        return None
    d = np.asarray(r0, float) - rec
    lateral, axial = float(np.hypot(d[0], d[1])), abs(float(d[2]))
    if lateral <= resolution[0] and axial <= resolution[1]:
        return None
    msg = (
        f"--r0: ({', '.join(f'{v * 1e3:.2f}' for v in r0)}) mm differs from the position the calibration "
        f"records, ({', '.join(f'{v * 1e3:.2f}' for v in rec)}) mm, by {lateral * 1e3:.2f} mm laterally and "
        f"{axial * 1e3:.2f} mm axially (resolution cell {resolution[0] * 1e3:.2f} × {resolution[1] * 1e3:.2f} mm)"
    )
    if not force:
        raise ValueError(msg + "; every detection would be displaced by the difference (use --force to proceed)")
    return msg


def calibration_position(spec: FingerprintSpec) -> tuple[np.ndarray, float | None]:
    """(r0 (x, y, z) in metres, target diameter in metres) of a calibration spec: the spec's own values,
    else the calibration's truth (``r0_m``, else its first target's position; ``diameter_m``); a diameter
    nobody knows is None (the gate is then placed at the echo's measured first arrival)."""
    cal = spec.calibration
    assert cal is not None
    rec_r0, rec_d = recorded_position(cal)
    if spec.r0 is not None:
        r0 = np.asarray(spec.r0, float)
    elif rec_r0 is not None:
        r0 = rec_r0
    else:
        raise ValueError(f"fingerprint {spec.name!r}: r0 unknown (give r0_m, or a calibration with truth)")
    if r0.shape != (3,):
        raise ValueError(f"fingerprint {spec.name!r}: r0 must be (x, y, z) in metres, got {r0.tolist()}")
    return r0, rec_d if spec.diameter is None else float(spec.diameter)


def build_fingerprint(
    spec: FingerprintSpec,
    acq: Acquisition,
    pw: PlaneWaveData | None,
    imager: Imager,
    band: tuple[float, float],
    n_freq: int | None,
    svd_threshold: float,
) -> Fingerprint:
    """The fingerprint of ``spec`` for data of the geometry of ``acq`` (plane waves ``pw`` from ``imager``,
    computed here for a model when None): a checked calibration (``from_calibration``) or a model centred
    at the spec's r0 (default: the grid's centre). ValueError when the calibration does not match the
    data or the spec is wrong."""
    if spec.calibration is not None:
        cal = spec.calibration
        check_calibration(cal, acq)
        r0, diameter = calibration_position(spec)
        return from_calibration(
            cal,
            r0,
            imager.out_sines_for(cal),
            band,
            n_freq,
            diameter=diameter,
            svd_threshold=svd_threshold,
            name=spec.name,
            gate=spec.gate,
            whiten_modes=spec.whiten_modes,
        )
    r0 = np.asarray(spec.r0, float) if spec.r0 is not None else imager.grid.centre_index_point()
    if r0.shape == (2,):
        r0 = np.array([r0[0], 0.0, r0[1]])
    return build_model(str(spec.model), imager.plane_waves(acq) if pw is None else pw, r0, spec.name)
