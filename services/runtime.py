"""Process-wide run-time tuning of the numerical libraries (stack notes, bench/bench_streaming.py).

:func:`limit_blas_threads` caps OpenBLAS's worker threads at run time through its C API (ctypes), for
numpy's bundled scipy-openblas or a system OpenBLAS: the processor's output projection is a batch of
small GEMMs whose OpenBLAS threads spin against the zenoh, recorder and publisher threads — on 2 cores
the spectrum+projection stage ran 6× slower with 2 BLAS threads than with 1. Environment variables
(OPENBLAS_NUM_THREADS) only act before numpy is imported; this acts any time.
"""

from __future__ import annotations

import ctypes

__all__ = ["limit_blas_threads"]

_SETTERS = (
    "scipy_openblas_set_num_threads64_",
    "scipy_openblas_set_num_threads",
    "openblas_set_num_threads64_",
    "openblas_set_num_threads",
)


def limit_blas_threads(n: int) -> bool:
    """Set OpenBLAS's thread count at run time (numpy's bundled scipy-openblas or a system OpenBLAS);
    False if no OpenBLAS is loaded. OSError where there is no /proc (not Linux)."""
    done = False
    with open("/proc/self/maps") as maps:
        libs = sorted({line.split()[-1] for line in maps if "openblas" in line.lower() and "/" in line})
    for path in libs:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for sym in _SETTERS:
            fn = getattr(lib, sym, None)
            if fn is not None:
                fn(ctypes.c_int(n))
                done = True
                break
    return done
