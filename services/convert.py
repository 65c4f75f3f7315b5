"""fpcore results → wire messages (``services.messages``): what the processor publishes for one frame.

Every message carries the input frame's index and acquisition timestamp. Values are made JSON- and
model-safe here: C_γ is infinite on a map that is zero outside the peak (capped), probabilities are
clipped to [0, 1], a track's covariance is symmetrised, non-finite or non-numeric fingerprint state is
left out.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fpcore import Fingerprint
from fpcore.metrics import Detection as CoreDetection
from fpcore.tracking import TrackState
from fpcore.velocity import VelocityEstimate
from services.messages import (
    UINT16_MAX,
    ConfocalImage,
    Detection,
    Detections,
    GammaMap,
    Normalisation,
    RFFrame,
    Track,
    Tracks,
)
from services.messages import Grid as WireGrid
from services.pipeline import FrameResult

__all__ = [
    "CONFOCAL_DB_STEP",
    "MAP_ENCODINGS",
    "QuantisedSource",
    "confocal_db_codes",
    "detection",
    "finite",
    "frame_messages",
    "motion_of",
    "gamma_step",
    "numeric_state",
    "quantise_rf",
    "track",
]


def finite(v: float, cap: float = 1e300) -> float:
    """A JSON-safe non-negative number (C_γ is infinite on a map that is zero outside the peak)."""
    return 0.0 if math.isnan(v) else float(min(max(v, 0.0), cap))


def numeric_state(fp: Fingerprint) -> dict[str, float]:
    """The finite numeric entries of a fingerprint's state q (booleans and strings left out)."""
    return {
        k: float(v)
        for k, v in fp.state.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
    }


def _vec3(v: Any) -> tuple[float, float, float]:
    a = np.asarray(v, float).reshape(3)
    return float(a[0]), float(a[1]), float(a[2])


def detection(
    d: CoreDetection,
    state: dict[str, float],
    truth_error_m: float | None,
    velocity: VelocityEstimate | None = None,
    statistic: str | None = None,
) -> Detection:
    """The wire Detection of a core detection (with its velocity estimate, when there is one, and the union's
    map it was found on, `statistic`)."""
    extra: dict[str, Any] = {} if statistic is None else {"statistic": statistic}
    if velocity is not None:
        extra |= {
            "velocity_m_s": _vec3(velocity.velocity_m_s),
            "velocity_sigma_m_s": _vec3(velocity.sigma_m_s),
            "velocity_position_m": _vec3(velocity.position_m),
            "velocity_gamma": max(float(velocity.gamma), 0.0),
            "velocity_states": max(int(velocity.n_states), 1),
        }
    return Detection(
        fingerprint=d.fingerprint,
        state=state,
        position_m=tuple(np.asarray(d.position_m, float).tolist()),
        gamma_max=max(float(d.gamma_max), 0.0),
        contrast_c_gamma=finite(d.c_gamma),
        contrast_c=finite(d.c_pfa),
        contrast_local=finite(d.c_local),
        pfa=float(np.clip(d.pfa, 0.0, 1.0)),
        precision_m=(float(d.precision_m[0]), float(d.precision_m[1])),
        truth_error_m=truth_error_m,
        **extra,
    )


def motion_of(dets: Detections) -> dict[str, list[VelocityEstimate]]:
    """The velocity estimates a Detections message carries (Detections 1.2), per fingerprint: the tracker's
    velocity measurements (``fpcore.tracking.Tracker.update(motion=…)``) where only the messages travel (a
    sharded merger)."""
    out: dict[str, list[VelocityEstimate]] = {}
    for d in dets.detections:
        if d.velocity_m_s is None or d.velocity_position_m is None:
            continue
        est = VelocityEstimate(
            d.fingerprint,
            np.asarray(d.position_m, float),
            np.asarray(d.velocity_position_m, float),
            np.asarray(d.velocity_m_s, float),
            np.asarray(d.velocity_sigma_m_s or (0.0, 0.0, 0.0), float),
            float(d.velocity_gamma or 0.0),
            int(d.velocity_states or 1),
            0.0,
        )
        out.setdefault(d.fingerprint, []).append(est)
    return out


def track(tr: TrackState) -> Track:
    c = np.asarray(tr.covariance_m2, float)
    c = 0.5 * (c + c.T)
    return Track(
        id=tr.track_id,
        fingerprint=tr.fingerprint,
        position_m=tuple(tr.position_m),
        velocity_m_s=tuple(tr.velocity_m_s),
        covariance=tuple(tuple(row) for row in c.tolist()),
        confidence=float(np.clip(tr.confidence, 0.0, 1.0)),
        age=tr.age,
        status=tr.status,
        pfa=float(np.clip(tr.pfa, 0.0, 1.0)),
    )


#: how the maps (γ, confocal image) travel: ``uint16`` (GammaMap / ConfocalImage 1.1 codes; the processor's
#: default) or ``float32``.
MAP_ENCODINGS = ("uint16", "float32")
#: dB step of a uint16 confocal image: level error ≤ 0.005 dB (intensity within 0.12 %).
CONFOCAL_DB_STEP = 0.01


def gamma_step(gamma: np.ndarray) -> float:
    """Step of a uint16 γ-map: γ_max / 65535 (1/65535 for an all-zero map), so that the error is at most
    γ_max / 131070 ≤ 7.7e-6 of γ ≤ 1."""
    top = float(np.max(gamma)) if gamma.size else 0.0
    return (top if top > 0 else 1.0) / UINT16_MAX


def frame_messages(
    res: FrameResult, frame_index: int, timestamp: float, map_encoding: str = "float32"
) -> dict[str, Any]:
    """``{"image": ConfocalImage | None, "gamma": [GammaMap, …], "tracks": Tracks, "detections":
    Detections}`` of one frame's result. Detections (γ_max, C_γ, PFA, precision) and tracks come from
    ``res``, computed on float γ; ``map_encoding="uint16"`` only changes how the maps travel: γ as codes of
    :func:`gamma_step`, the confocal image in dB (``scale="db"``) as codes of :data:`CONFOCAL_DB_STEP`."""
    if map_encoding not in MAP_ENCODINGS:
        raise ValueError(f"map_encoding: expected one of {', '.join(MAP_ENCODINGS)}, got {map_encoding!r}")
    quantise = map_encoding == "uint16"
    fi, ts = frame_index, timestamp
    states = {name: numeric_state(fp) for name, fp in res.fingerprints.items()}
    vels = res.velocities or [None] * len(res.detections)
    dets = [
        detection(d, states[d.fingerprint], err, v, res.statistic.get(d.fingerprint))
        for (d, err), v in zip(res.detections, vels, strict=True)
    ]
    tracks = [track(tr) for tr in res.tracks]
    wgrid = WireGrid.from_grid(res.grid)
    r_energy = float(np.vdot(res.pw.data, res.pw.data).real)
    w_energy = float(np.vdot(res.weighted_pw.data, res.weighted_pw.data).real) if res.weighted_pw is not None else None
    gammas = []
    for name, g in res.gammas.items():
        fp = res.fingerprints[name]
        g_m = float(np.sqrt(np.mean(np.square(g, dtype=np.float64))))
        statistic = res.statistic.get(name)
        energy = w_energy if statistic == "weighted" else r_energy  # the frame this map was made from
        norm = Normalisation(band_hz=res.band, r_energy=energy, f_energy=fp.norm2, gamma_m=g_m)
        gammas.append(
            GammaMap(
                frame_index=fi,
                timestamp=ts,
                fingerprint=name,
                state=states[name],
                grid=wgrid,
                gamma=g,
                normalisation=norm,
                gamma_step=gamma_step(g) if quantise else None,
                statistic=statistic,
            )
        )
    image = None
    if res.image is not None:
        image = ConfocalImage(frame_index=fi, timestamp=ts, grid=wgrid, image=res.image)
        if quantise:
            image = confocal_db_codes(image)
    return {
        "image": image,
        "gamma": gammas,
        "tracks": Tracks(frame_index=fi, timestamp=ts, tracks=tracks),
        "detections": Detections(frame_index=fi, timestamp=ts, detections=dets),
    }


def confocal_db_codes(image: ConfocalImage, step: float = CONFOCAL_DB_STEP) -> ConfocalImage:
    """The image in dB (``scale="db"``), to travel as uint16 codes of ``step`` dB (ConfocalImage 1.1): the
    levels span the image's maximum − 65535 × step (655 dB at 0.01 dB) up to its maximum; zeros and
    anything lower read as that floor. Decoding it costs a multiply-add, not a power per voxel."""
    if image.db_step is not None:
        return image
    img = np.asarray(image.image, np.float64)
    if image.scale == "linear":
        if img.size and float(np.min(img)) < 0:
            raise ValueError(f"image: expected a linear image ≥ 0 to travel in dB, got {float(np.min(img)):.3g}")
        with np.errstate(divide="ignore"):
            img = 10.0 * np.log10(img)
    top = float(np.max(img[np.isfinite(img)])) if np.isfinite(img).any() else 0.0
    floor = top - UINT16_MAX * step
    level = np.maximum(np.nan_to_num(img, neginf=floor), floor).astype(np.float32)
    return ConfocalImage(
        frame_index=image.frame_index,
        timestamp=image.timestamp,
        grid=image.grid,
        image=level,
        scale="db",
        db_step=step,
        db_floor=floor,
    )


def quantise_rf(frame: RFFrame, bits: int = 16) -> RFFrame:
    """A ``bits``-bit ADC (≤ 16): int16 RF scaled so that the largest |sample| uses the full range, with its
    ``rf_scale`` (RFFrame 1.2). The rounding error is at most rf_scale/2 per sample (−6 dB per bit below the
    peak: 16 bits, ≈ 96 dB)."""
    if not 2 <= bits <= 16:
        raise ValueError(f"bits: expected 2…16, got {bits}")
    if frame.rf.dtype == np.int16:
        return frame
    rf = frame.rf.astype(np.float64)
    peak = float(np.max(np.abs(rf))) if rf.size else 0.0
    full = float(2 ** (bits - 1) - 1)
    scale = peak / full if peak > 0 else 1.0
    q = np.clip(np.rint(rf / scale), -full, full).astype(np.int16)
    return frame.model_copy(update={"rf": q, "rf_scale": scale})


class QuantisedSource:
    """A publisher source (``services.sources``) whose float RF goes through a ``bits``-bit ADC first
    (:func:`quantise_rf`): int16 RF with its scale, as a scanner delivers it. Other attributes (``n_frames``,
    ``fingerprint_specs``, …) are the wrapped source's."""

    def __init__(self, source: Any, bits: int = 16) -> None:
        self.source, self.bits = source, bits

    def __getattr__(self, name: str) -> Any:
        return getattr(self.source, name)

    def __iter__(self) -> Any:
        from services.sources import Item
        from services.wire import decode, encode_with_header

        for item in self.source:
            msg = decode(item.payload, expect=RFFrame)
            assert isinstance(msg, RFFrame)
            payload, header = encode_with_header(quantise_rf(msg, self.bits))
            yield Item(payload, header, item.frame_index, item.t_s, item.trusted)
