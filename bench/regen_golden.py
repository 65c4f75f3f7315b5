"""Regenerate the golden-master reference of tests/test_golden.py: tests/golden/golden_maps.npz.

    python bench/regen_golden.py            # recompute the case and overwrite the reference
    python bench/regen_golden.py --check    # recompute and print the differences, write nothing

The case itself (scenario, seed, target, grid) is defined once, in tests/test_golden.py
(`compute_maps`), so the script and the test cannot drift apart. The file holds each map in dB re its
maximum (float16: 0.03 dB steps at worst, clipped at −40 dB), the node of its peak, the peak's level
and the grid axes; it stays well under 300 kB. Regenerate only after a change that is meant to move
the maps, and say in the commit what changed and by how much (the script prints it).
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
TEST = ROOT / "tests" / "test_golden.py"


def _golden_module():
    spec = importlib.util.spec_from_file_location("test_golden", TEST)
    if spec is None or spec.loader is None:
        raise SystemExit(f"cannot load {TEST}")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def reference_arrays(mod, maps: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """What goes into the npz: per map its dB (float16), peak node and peak level; axes and band."""
    out: dict[str, np.ndarray] = {"x": maps["x"], "z": maps["z"], "band_hz": maps["band_hz"]}
    for name, power in (("gamma", False), ("confocal", True)):
        m = maps[name]
        out[f"{name}_db"] = mod.to_db(m, power).astype(np.float16)
        out[f"{name}_peak"] = np.array(np.unravel_index(int(np.argmax(m)), m.shape), dtype=np.int32)
        out[f"{name}_max"] = np.array(float(m.max()))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="print the differences to the stored reference only")
    args = p.parse_args(argv)
    mod = _golden_module()
    t = time.perf_counter()
    maps = mod.compute_maps()
    elapsed = time.perf_counter() - t
    new = reference_arrays(mod, maps)
    print(
        f"golden case computed in {elapsed:.1f} s: grid {maps['gamma'].shape} (x, z), "
        f"band {new['band_hz'][0] / 1e6:.2f}–{new['band_hz'][1] / 1e6:.2f} MHz"
    )
    old = None
    if mod.GOLDEN.exists():
        with np.load(mod.GOLDEN) as f:
            old = {k: f[k] for k in f.files}
    for name in ("gamma", "confocal"):
        peak = tuple(int(i) for i in new[f"{name}_peak"])
        pos = (maps["x"][peak[0]] * 1e3, maps["z"][peak[1]] * 1e3)
        level = float(new[f"{name}_max"])
        line = f"  {name:8s} peak at node {peak} = ({pos[0]:.2f}, {pos[1]:.2f}) mm, level {level:.4g}"
        if old is not None and old[f"{name}_db"].shape == new[f"{name}_db"].shape:
            diff = np.abs(new[f"{name}_db"].astype(np.float32) - old[f"{name}_db"].astype(np.float32))
            moved = tuple(int(i) for i in old[f"{name}_peak"]) != peak
            line += f"; vs stored: max |Δ| {diff.max():.3f} dB, peak {'MOVED' if moved else 'same node'}"
        print(line)
    if args.check:
        return 0
    mod.GOLDEN.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(mod.GOLDEN, **new)
    print(f"wrote {mod.GOLDEN.relative_to(ROOT)} ({mod.GOLDEN.stat().st_size / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
