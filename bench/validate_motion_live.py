"""Live velocity dictionaries through the bus on `fast-cylinder` (issue 15 item 3; docs/design.md §4.13).

Publisher → processor (→ tracks) over zenoh on loopback (``services.nodes.local.run_pipeline``), twice on
the same frames: the calibration fingerprint alone, then with a velocity dictionary (``--velocity-grid``,
symmetric about 0: no knowledge of the target's velocity). The scenario is water only, so the fingerprint
keeps the whole record (``gate=False``, `fp track --gate none`): gated after the front face, the 10 mm
cylinder's internal reverberation (period 2d/c_p ≈ 7.4 µs) puts an alias of γ 5.5 mm above the target
that is stronger than the target's own peak.

Per frame: the truth, the detection's error (and, with the dictionary, its velocity estimate, the error of
the motion-aware peak and of the velocity), the track's position and velocity errors. Then the means over
the frames after the first (a track's velocity needs two frames without a velocity measurement), the
per-frame time of the 'detection' stage (which holds the velocity dictionaries) and the dictionary size.

    python bench/validate_motion_live.py [--frames N] [--velocity-grid 0.5,0.2:0.1] [--full]
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from typing import Any

import numpy as np

from fpcore.simulate import scenario
from fpcore.truth import Truth
from services.cli.fingerprint_args import parse_velocity_grid
from services.nodes.local import run_pipeline
from services.nodes.processor import ProcessorConfig
from services.sources import SimulatorSource

__all__ = ["run"]


def _truth(doc: Any) -> tuple[np.ndarray, np.ndarray]:
    tg = Truth.from_dict(doc).target("cylinder")
    return tg.position, tg.velocity


def run(frames: int = 6, velocity_grid: str | None = "0.5,0.2:0.1", roi: str = "3mm", quick: bool = True) -> dict:
    """One bus run: per frame, the errors of the detection, of its velocity estimate and of the track (m, m/s)."""
    src = SimulatorSource(scenario("fast-cylinder", quick=quick, n_frames=frames), n_frames=frames)
    vg = parse_velocity_grid(velocity_grid, roi) if velocity_grid else None
    specs = [dataclasses.replace(s, gate=False, velocity_grid=vg) for s in src.fingerprint_specs()]
    rows: list[dict[str, Any]] = []

    def on_result(res: dict[str, Any]) -> None:
        r, v = _truth(res["truth"])
        row: dict[str, Any] = {"frame": res["frame_index"], "truth": r, "v_truth": v}
        if res["detections"]:
            d = res["detections"][0]
            row["det_err"] = float(np.linalg.norm(np.asarray(d["position_m"]) - r))
            if d.get("velocity_m_s") is not None:
                row["v_det"] = np.asarray(d["velocity_m_s"])
                row["v_det_err"] = float(np.linalg.norm(row["v_det"] - v))
                row["vpos_err"] = float(np.linalg.norm(np.asarray(d["velocity_position_m"]) - r))
        live = [t for t in res["tracks"] if t["status"] != "lost"]
        if live:
            t = min(live, key=lambda t: np.linalg.norm(np.asarray(t["position_m"]) - r))
            row["track_err"] = float(np.linalg.norm(np.asarray(t["position_m"]) - r))
            row["v_track"] = np.asarray(t["velocity_m_s"])
            row["v_track_err"] = float(np.linalg.norm(row["v_track"] - v))
            row["status"] = t["status"]
        rows.append(row)

    with tempfile.TemporaryDirectory() as out:
        cfg = ProcessorConfig(rig="motion", queue="fifo", publish_image=False)
        summary = run_pipeline(
            src, "motion", out, frames, on_result, fingerprints=specs, processor=cfg, record=False, warmup=1
        )
    rows.sort(key=lambda r: r["frame"])
    return {
        "rows": rows,
        "detection_stage_s": summary["stage_mean_s"]["detection"],
        "n_states": 0 if vg is None else vg.size(2),
        "grid": None if vg is None else vg.describe(),
        "processed": summary["frames_processed"],
    }


def search_cost(velocity_grid: str, roi: str = "3mm", quick: bool = True, repeat: int = 3) -> dict[str, Any]:
    """Seconds of one region's velocity search (median of ``repeat``, after one warm call) on frame 0, with
    and without thinning the samples (fpcore.velocity.VelocitySearch.strides), in this process."""
    from fpcore.velocity import VelocitySearch
    from services.pipeline import Pipeline, PipelineConfig

    src = SimulatorSource(scenario("fast-cylinder", quick=quick, n_frames=1), n_frames=1)
    specs = [dataclasses.replace(s, gate=False) for s in src.fingerprint_specs()]
    pipe = Pipeline(PipelineConfig(publish_image=False), specs)
    acq = src.scenario.frame(0)
    res = pipe.process(acq)
    vg = parse_velocity_grid(velocity_grid, roi)
    out: dict[str, Any] = {"samples": int(res.pw.data.size)}
    for thin in (True, False):
        search = VelocitySearch(res.fingerprints["cylinder"], vg, acq.sequence.transmit_times(), thin=thin)
        origin = acq.ground_truth.target("cylinder").position
        search.estimate(res.pw, origin, res.grid.spacing)
        secs = [search.estimate(res.pw, origin, res.grid.spacing).seconds for _ in range(repeat)]
        out["thinned" if thin else "all"] = float(np.median(secs))
        if thin:
            out["strides"] = search.strides(res.pw, res.grid.ndim)
    return out


def _mm(v: float | None) -> str:
    return "—" if v is None else f"{v * 1e3:6.2f}"


def _ms(v: float | None) -> str:
    return "—" if v is None else f"{v:6.3f}"


def _mean(rows: list[dict], key: str) -> float | None:
    vals = [r[key] for r in rows[1:] if key in r]
    return float(np.mean(vals)) if vals else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--velocity-grid", default="0.5,0.2:0.1", help="VMAX[:STEP] (fp process --velocity-grid)")
    ap.add_argument("--velocity-roi", default="3mm")
    ap.add_argument("--full", action="store_true", help="128 elements instead of 64")
    args = ap.parse_args()
    results = {}
    for label, grid in (("static fingerprint", None), ("velocity dictionary", args.velocity_grid)):
        res = results[label] = run(args.frames, grid, args.velocity_roi, quick=not args.full)
        print(f"\n{label}" + (f": {res['n_states']} velocities, {res['grid']}" if grid else ""))
        print(
            " frame | truth x, z (mm) | det err (mm) | v est (m/s)   | v err | v-peak err (mm) | track err (mm) "
            "| v track (m/s)  | v err"
        )
        for r in res["rows"]:
            vd = r.get("v_det")
            vt = r.get("v_track")
            print(
                f" {r['frame']:5d} | {r['truth'][0] * 1e3:6.2f}, {r['truth'][2] * 1e3:6.2f} | "
                f"{_mm(r.get('det_err')):>12} | "
                f"{'—' if vd is None else f'{vd[0]:5.2f}, {vd[2]:5.2f}':>13} | {_ms(r.get('v_det_err'))} | "
                f"{_mm(r.get('vpos_err')):>15} | {_mm(r.get('track_err')):>14} | "
                f"{'—' if vt is None else f'{vt[0]:6.3f}, {vt[2]:6.3f}':>14} | {_ms(r.get('v_track_err'))}"
            )
    print("\nmeans over frames 1.. (the first frame has no track velocity without the dictionary):")
    for label, res in results.items():
        rows = res["rows"]
        print(
            f"  {label:>19}: detection error {_mm(_mean(rows, 'det_err'))} mm, track error "
            f"{_mm(_mean(rows, 'track_err'))} mm, track velocity error {_ms(_mean(rows, 'v_track_err'))} m/s, "
            f"detection-stage time {res['detection_stage_s']:.2f} s/frame ({res['processed']} frames)"
        )
        if res["n_states"]:
            print(
                f"  {'':>19}  velocity estimate at the detection: error {_ms(_mean(rows, 'v_det_err'))} m/s, "
                f"motion-aware peak {_mm(_mean(rows, 'vpos_err'))} mm"
            )
    cost = search_cost(args.velocity_grid, args.velocity_roi, quick=not args.full)
    print(
        f"\none region's search ({results['velocity dictionary']['n_states']} velocities, {cost['samples']} samples): "
        f"{cost['thinned']:.2f} s thinned (strides {cost['strides']} in frequency, output direction), "
        f"{cost['all']:.2f} s with every sample"
    )


if __name__ == "__main__":
    main()
