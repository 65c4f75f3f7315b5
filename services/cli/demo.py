"""`fp demo`: the main job on the built-in simulated scenario.

Two metal spheres in a granular suspension (one sinking), seen by a matrix array, streamed publisher →
processor → recorder over zenoh on loopback (``services.nodes.local.run_pipeline``); the processor holds
each sphere's calibration fingerprint and publishes γ-maps, detections (C_γ, PFA, Cramér–Rao precision)
and tracks; a live table, an MCAP recording, a JSON summary and PNGs of γ and of the tracks over the
confocal image come out.
"""

from __future__ import annotations

import argparse
import contextlib
from dataclasses import replace
from pathlib import Path

import numpy as np

from fpcore.cfar import DEFAULT_CFAR
from services.bus import DEFAULT_HUB
from services.cli.fingerprint_args import add_null_arguments, add_whitening_argument
from services.cli.output import make_console
from services.cli.scenario_args import add_scenario_arguments, depth_note, scenario_kwargs

__all__ = ["add_demo_parser", "cmd_demo", "DEMO_DEPTH_LS"]

#: The demo's depth (ℓ_s below the surface) for the sinking scenarios: shallower than the paper's regime,
#: where the method does not find the spheres in this simulator (README, "The paper's regime").
DEMO_DEPTH_LS = 2.0

COLUMNS = ("frame", "target", "position (mm)", "truth (mm)", "error (mm)", "C_γ", "PFA", "track")


def add_demo_parser(sub: argparse._SubParsersAction) -> None:
    demo = sub.add_parser(
        "demo",
        help="run the main job on the built-in simulated scenario",
        description="Publisher, processor and recorder on loopback zenoh with the simulated "
        "sinking-sphere scenario: live table, MCAP recording, summary, PNG.",
    )
    demo.add_argument("--scenario", default="sinking-sphere", help="simulator scenario (default sinking-sphere)")
    demo.add_argument("--frames", type=int, default=None, help="number of frames (default: the scenario's)")
    demo.add_argument("--full", action="store_true", help="full-size scenario (default: quick)")
    demo.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    add_scenario_arguments(demo, default_depth_ls=DEMO_DEPTH_LS)
    add_whitening_argument(demo)
    add_null_arguments(demo)
    demo.add_argument("--rig", default="demo", help="rig name in the key expressions (default demo)")
    demo.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    demo.add_argument(
        "--adc-bits",
        type=int,
        default=16,
        help="digitise the simulated RF as a scanner does: int16 samples of this many bits with their scale "
        "(default 16, ≈ 96 dB; 0 keeps float32). Halves the RF in the recording.",
    )
    demo.add_argument(
        "--listen",
        default=None,
        help=f"endpoint of the demo's hub (default {DEFAULT_HUB}, where `fp view --live` looks; a free "
        "loopback port if that one is taken)",
    )
    demo.set_defaults(func=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    """Publisher → processor → recorder on loopback with the simulated sinking-sphere scenario."""
    from rich.console import Group
    from rich.live import Live
    from rich.table import Table

    from fpcore.truth import TargetTruth, Truth
    from services.convert import QuantisedSource
    from services.nodes.local import run_pipeline
    from services.nodes.processor import ProcessorConfig
    from services.pipeline import truth_positions
    from services.sources import SimulatorSource
    from services.viewing.figures import gamma_over_confocal

    if args.frames is not None and args.frames < 1:
        raise ValueError(f"--frames: expected at least 1, got {args.frames}")
    if args.adc_bits != 0 and not 2 <= args.adc_bits <= 16:
        raise ValueError(f"--adc-bits: expected 0 (float32 RF) or 2…16, got {args.adc_bits}")
    hub = demo_hub(args.listen)
    console = make_console()  # not a terminal: plain lines, one per detection, instead of the live table
    kwargs = scenario_kwargs(args, args.scenario, DEMO_DEPTH_LS)
    sim = SimulatorSource(args.scenario, n_frames=args.frames, quick=not args.full, seed=args.seed, **kwargs)
    source = QuantisedSource(sim, args.adc_bits) if args.adc_bits else sim
    # The default grid: the record's whole time window, the suspension's surface included — no depth
    # window chosen from the truth; detections are judged on their local significance (docs/design.md §4.9).
    cfg = ProcessorConfig(
        rig=args.rig,
        queue="fifo",
        single_scattering_null=args.null_single_scattering,
        cfar=args.cfar,
        time_weighting=args.time_weighting,
        union=args.union,
    )
    specs = [replace(spec, whiten_modes=not args.no_whitening) for spec in sim.fingerprint_specs()]
    rows: list[tuple] = []
    last: dict = {}
    n_total = args.frames or source.n_frames

    def table() -> Table:
        t = Table(
            title=f"fp demo — {args.scenario} ({'full' if args.full else 'quick'}): "
            f"{len({r[0] for r in rows})}/{n_total} frames"
        )
        for col in COLUMNS:
            t.add_column(col, justify="right")
        for r in rows[-12:]:
            t.add_row(*r)
        return t

    history: list[dict] = []

    def on_frame(res: dict) -> None:
        n_rows = len(rows)
        truths = dict(truth_positions(res["truth"]))  # the frame's truth, as the RF message carries it
        tracks = {tr["fingerprint"]: f"{tr['id']} {tr.get('status') or ''}".strip() for tr in res["tracks"]}
        if not res["detections"]:
            rows.append((str(res["frame_index"]), "no detection", "", "", "", "", "", ""))
        for d in res["detections"]:
            pos = np.array(d["position_m"])
            tr = truths.get(d["fingerprint"])
            err = f"{np.linalg.norm(pos - tr) * 1e3:.2f}" if tr is not None else ""
            rows.append(
                (
                    str(res["frame_index"]),
                    d["fingerprint"],
                    _mm(pos),
                    _mm(tr) if tr is not None else "",
                    err,
                    f"{d['contrast_c_gamma']:.1f}",
                    f"{d['pfa']:.1e}",
                    str(tracks.get(d["fingerprint"], "")),
                )
            )
        if not console.is_terminal:
            for r in rows[n_rows:]:
                console.print("  ".join(f"{c}={v}" for c, v in zip(COLUMNS, r, strict=True) if v))
        last.update(res)
        history.append(
            {"frame_index": res["frame_index"], "tracks": res["tracks"], "truth": res["truth"].get("targets", [])}
        )

    console.print(
        f"[bold]fingerprint demo[/]: {args.scenario} on loopback zenoh — publisher → processor → "
        f"recorder; default grid (the record's whole time window); detections at calibrated PFA < "
        f"{cfg.max_pfa:g}; writing to {args.out}"
    )
    options = ["F = R0′"] if args.no_whitening else []
    options += ["null level with eq. (B2)"] if args.null_single_scattering else []
    options += ["frames weighted by 1/v(t) (eq. W1)"] if args.time_weighting else []
    options += ["the union of the frames as recorded and weighted by 1/v(t) (eq. W2: PFA × 2)"] if args.union else []
    options += [f"CFAR {args.cfar!r}"] if args.cfar != DEFAULT_CFAR else []
    if options:
        console.print(f"options: {', '.join(options)}")
    note = depth_note(sim.scenario)
    if note:
        console.print(
            f"{note}. The demo runs shallower than the paper because this implementation does not detect the "
            "spheres at the paper's depths (README, \"The paper's regime\"); --depth-ls sets the depth."
            if "depth_ls" in kwargs
            else note
        )
    follow = "fp view --live" + ("" if hub == DEFAULT_HUB else f" --connect {hub}")
    console.print(f"bus: {hub} (follow it with `{follow} --rig {args.rig}`)")
    live = (
        Live(Group(table()), console=console, refresh_per_second=4, get_renderable=lambda: Group(table()))
        if console.is_terminal
        else contextlib.nullcontext()
    )
    with live:
        summary = run_pipeline(
            source,
            rig=args.rig,
            out_dir=args.out,
            n_frames=args.frames,
            progress_callback=on_frame,
            fingerprints=specs,
            processor=cfg,
            hub=hub,
        )
    errors = [float(r[4]) for r in rows if r[4]]
    rec = summary.get("recording") or {}
    console.print(
        f"{summary['frames_processed']} frames processed at {summary['frame_rate_hz']:.1f} frames/s, "
        f"latency median {summary['latency_ms']['median']:.0f} ms; detection error RMS "
        f"{np.sqrt(np.mean(np.square(errors))) if errors else float('nan'):.2f} mm, "
        f"max {max(errors) if errors else float('nan'):.2f} mm"
    )
    console.print(
        f"recording: {', '.join(map(str, rec.get('files', []))) or 'none'}; summary: "
        f"{Path(args.out) / 'pipeline_summary.json'}"
    )
    det = next((d for d in last.get("detections", []) if d["fingerprint"] in last.get("gamma", {})), None)
    if det is not None:
        name = det["fingerprint"]
        gamma = last["gamma"][name]
        targets = Truth.from_dict(last["truth"] or {}).targets or []
        target = next((t for t in targets if t.name == name), TargetTruth())
        truth = target.position if target.position_m is not None else None
        png = Path(args.out) / "demo_gamma_over_confocal.png"
        gamma_over_confocal(
            png,
            last["grid"],
            last["image"],
            gamma,
            np.array(det["position_m"]),
            truth=truth,
            title=f"frame {last['frame_index']}, {name}: C_γ = {det['contrast_c_gamma']:.1f}, PFA = {det['pfa']:.1e}",
            name=name,
            diameter=target.diameter_m,
            c_gamma=det["contrast_c_gamma"],
        )
        console.print(f"figure: {png}")
    if history and last.get("image") is not None:
        from services.viewing.figures import tracks_over_confocal

        png = Path(args.out) / "demo_tracks.png"
        tracks_over_confocal(png, last["grid"], last["image"], history)
        console.print(f"tracks figure: {png}")
    return 0


def _mm(p: np.ndarray) -> str:
    return ", ".join(f"{v * 1e3:.2f}" for v in p)


def demo_hub(listen: str | None) -> str:
    """The endpoint the demo's processor listens on: ``listen`` if given (checked to be loopback TCP), else the
    well-known hub ``tcp/127.0.0.1:7447`` (what `fp view --live` and the other nodes connect to by default), or
    a free loopback port when another node already holds it."""
    import socket

    from services.bus import free_port

    if listen is not None:
        host, _, port = listen.removeprefix("tcp/").rpartition(":")
        if not listen.startswith("tcp/") or host not in ("127.0.0.1", "localhost") or not port.isdigit():
            raise ValueError(f"--listen: expected a loopback endpoint such as {DEFAULT_HUB}, got {listen!r}")
        return listen
    port = int(DEFAULT_HUB.rsplit(":", 1)[1])
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return f"tcp/127.0.0.1:{free_port()}"
    return DEFAULT_HUB
