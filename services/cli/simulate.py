"""`fp simulate SCENARIO --out DIR`: write a simulated scenario as UFF files (issues 3 and 7).

DIR/frames.uff (every frame, truth in each frame's metadata), DIR/calibration_<target>.uff for every
target (the target alone in water at its r0, named after it: calibration_sphere1.uff, …), DIR/truth.json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from services.cli.output import make_console, progress
from services.cli.scenario_args import add_scenario_arguments, depth_note, scenario_kwargs

__all__ = ["add_simulate_parser", "run_simulate"]


def add_simulate_parser(sub: argparse._SubParsersAction) -> None:
    from fpcore.simulate import SCENARIOS

    p = sub.add_parser(
        "simulate",
        help="write a simulated scenario (frames, calibrations, truth) as UFF",
        description="Simulated plane-wave acquisitions with ground truth, as USTB UFF files.",
    )
    p.add_argument("scenario", choices=sorted(SCENARIOS), help="scenario name")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--quick", action="store_true", help="the small variant that runs in seconds")
    p.add_argument("--frames", type=int, help="number of frames (default: the scenario's)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    add_scenario_arguments(p)
    p.set_defaults(func=run_simulate)


def run_simulate(args: argparse.Namespace) -> int:
    from fpcore.io import write_uff
    from fpcore.simulate import scenario

    console = make_console()
    sc = scenario(args.scenario, quick=args.quick, seed=args.seed, **scenario_kwargs(args, args.scenario))
    n = sc.n_frames if args.frames is None else args.frames
    if not 1 <= n <= sc.n_frames:
        raise ValueError(f"--frames: expected 1 … {sc.n_frames} for {args.scenario}, got {n}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    console.print(
        f"{args.scenario}{' (quick)' if args.quick else ''}: {sc.probe.n_elements} elements, "
        f"{sc.sequence.n_waves} plane waves, {n} frames of {sc.frame_nbytes / 1e6:.1f} MB"
    )
    note = depth_note(sc)
    if note:
        console.print(note)
    t = time.perf_counter()
    frames = []
    with progress(console) as bar:
        task = bar.add_task("frames", total=n)
        for k, acq in enumerate(sc.frames()):
            if k >= n:
                break
            frames.append(acq)
            bar.advance(task)
    write_uff(out / "frames.uff", frames)
    for name in sc.target_names:
        write_uff(out / f"calibration_{name}.uff", sc.calibration(name))
    truth = {
        "scenario": args.scenario,
        "quick": args.quick,
        "seed": args.seed,
        "band_hz": list(sc.band),
        "frames": [f.truth for f in frames],
        "calibrations": {name: sc.calibration(name).truth for name in sc.target_names},
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=2))
    console.print(
        f"wrote {n} frames, {len(sc.target_names)} calibration(s) and truth.json to {out} "
        f"({time.perf_counter() - t:.1f} s)"
    )
    return 0
