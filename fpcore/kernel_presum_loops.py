"""The compiled per-frame loops of the lattice pre-sum kernel (`fpcore.kernel_presum.PresumTransform`,
docs/design.md §5) and the thread pool that runs them; the plan they execute (lattice, fixed-point
positions, tables) is built in `fpcore.kernel_presum`.

numba kernels — the whole per-frame path. Single precision; flat float32 buffers in which a row holds L
real parts then L imaginary parts. They run on plain Python threads (`pool`; the kernels release the
GIL) as small tasks handed out one at a time, each thread with its own accumulators: no BLAS and no
numba/OpenMP pool, whose spinning workers fight each other on a 2-core machine (~8 ms per hand-over
measured here). Indices are uint64 (no negative-index wraparound code) and inner loops have run-time
lengths, so LLVM's loop vectorizer emits AVX code (numba leaves the SLP vectorizer off). Without numba
(`nb` None) only `pool`, `split` and the constants exist.

Compiled once per machine (issue 15, item 4): the kernels are cached on disk (`cache=True`), so a fresh
process loads them (a first frame costs what the next ones do) instead of compiling them (seconds).
numba keeps the cache next to this file (`__pycache__`, a clean clone), or in the user's cache
folder when the package is read-only, or in NUMBA_CACHE_DIR when set; when none of these can be
written (read-only install and home) `_jit` points NUMBA_CACHE_DIR's setting at a per-user folder of
the temporary directory (created 0700; not used unless it is this user's own with no group/other
bits), and compiles without a cache when that fails too — importing never fails.
"""

from __future__ import annotations

import importlib
import os
import stat
import tempfile
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from types import ModuleType

import numpy as np

nb: ModuleType | None
try:  # numba compiles the spreading loops; without it PresumTransform is unavailable
    nb = importlib.import_module("numba")
except ImportError:  # pragma: no cover - depends on the environment
    nb = None

# fixed-point depth positions and the kernel table, as the plan (fpcore.kernel_presum) builds them
TAB_BITS = 11
N_TABLE = 1 << TAB_BITS  # kernel table resolution per cell (linear interpolation error ≈ 1e-6)
FRAC = 40  # fractional bits of the fixed-point depth positions
u64 = np.uint64  # every index of the kernels (no negative-index wraparound code)


def _fallback_cache_dir() -> str | None:
    """A per-user numba cache folder in the temporary directory (used when numba finds no writable one), or
    None when it is not safe: numba's cache index is a pickle, so on a shared temporary directory the folder
    must be a real directory (no link) of this user that nobody else can write or read (mode 0700)."""
    if not hasattr(os, "getuid"):  # Windows: the temporary directory is the user's own
        return os.path.join(tempfile.gettempdir(), f"fpcore-numba-cache-{os.environ.get('USERNAME', 'user')}")
    path = os.path.join(tempfile.gettempdir(), f"fpcore-numba-cache-{os.getuid()}")
    try:
        os.mkdir(path, 0o700)
    except FileExistsError:
        pass
    except OSError:
        return None
    try:
        st = os.lstat(path)
    except OSError:
        return None
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
        return None  # planted by someone else, a link, or open to others: compile without a cache
    return path


def _jit(fn: Callable[..., None]) -> Callable[..., None]:
    """numba.njit(fastmath, nogil, cached on disk; see the module doc for where)."""
    assert nb is not None
    try:
        return nb.njit(fastmath=True, cache=True, nogil=True)(fn)
    except RuntimeError:  # "cannot cache function …: no locator available": nothing numba tried is writable
        fallback = None if nb.config.CACHE_DIR else _fallback_cache_dir()
        if fallback is not None:
            nb.config.CACHE_DIR = fallback
            try:
                return nb.njit(fastmath=True, cache=True, nogil=True)(fn)
            except RuntimeError:
                pass
        return nb.njit(fastmath=True, nogil=True)(fn)  # compiled at its first call, every process


if nb is not None:

    @_jit
    def spread_depth(w, P, Q, ua, ub, go, gi, gbase, glen, tab, dtab, G, f0, fstep):  # pragma: no cover
        """Depth spreading of the samples j = (f, o, i), f = f0, f0 + fstep, …:
        G[f, g(o, i), re/im, l] += w_j P_fo Q_fi φ(u_j − l).

        w (Nf, No, Ni, 2), P (Nf, No, 2), Q (Nf, Ni, 2): re/im pairs; g = go[o] + gi[i], the lattice group
        (m_y·M_x + m_x). u = ua[f, o] + ub[f, i] ≥ 0, fixed point with FRAC fractional bits: position from
        the band's first bin, ⌊u⌋ the first of the 8 taps. Per (f, o), a vectorizable pass over i makes
        the strengths and positions, then each sample adds its 8 taps."""
        nf, no, ni, _ = w.shape
        ntap = tab.shape[1]
        tabf = tab.ravel()
        dtabf = dtab.ravel()
        shift = FRAC - TAB_BITS
        fmask = (1 << shift) - 1
        fscale = np.float32(1.0 / (1 << shift))
        cre = np.empty(ni, np.float32)
        cim = np.empty(ni, np.float32)
        rr = np.empty(ni, np.float32)
        kb = np.empty(ni, np.int64)
        off = np.empty(ni, np.int64)
        qr = np.empty(ni, np.float32)
        qi = np.empty(ni, np.float32)
        for f in range(f0, nf, fstep):
            L = glen[f]
            b0 = u64(gbase[f])
            G[b0 : u64(gbase[f + 1])] = 0
            qr[:] = Q[f, :, 0]
            qi[:] = Q[f, :, 1]
            for o in range(no):
                pr = P[f, o, 0]
                pi = P[f, o, 1]
                a = ua[f, o]
                wo = w[f, o]
                for i in range(ni):
                    er = pr * qr[i] - pi * qi[i]
                    ei = pr * qi[i] + pi * qr[i]
                    xr = np.float32(wo[i, 0])
                    xi = np.float32(wo[i, 1])
                    cre[i] = xr * er - xi * ei
                    cim[i] = xr * ei + xi * er
                for i in range(ni):
                    u = a + ub[f, i]
                    kb[i] = ((u >> shift) & (N_TABLE - 1)) * ntap
                    rr[i] = np.float32(np.int32(u & fmask)) * fscale
                    off[i] = (go[o] + gi[i]) * (L + L) + (u >> FRAC)
                uL = u64(L)
                for i in range(ni):
                    cr = cre[i]
                    ci = cim[i]
                    r = rr[i]
                    k0 = u64(kb[i])
                    dst = b0 + u64(off[i])
                    dim = dst + uL
                    for t in range(u64(ntap)):
                        v = tabf[k0 + t] + r * dtabf[k0 + t]
                        G[dst + t] += cr * v
                        G[dim + t] += ci * v

    @_jit
    def spread_lateral(G, gbase, glen, lstart, ux, uy, tab, dtab, W, f0, fstep):  # pragma: no cover
        """Lateral spreading of the rows G[f, (m_y, m_x)] onto W[(k_y, k_x), re/im, l] (l on the global
        band), f = f0, f0 + fstep, …. ux (Nf, M_x), uy (Nf, M_y) ≥ 0: positions from the first tap; taps
        wrap modulo the fine grids (n_fy = 1, uy = 0 in 2D). W: (n_fy, n_fx, 2, nglob)."""
        nfy, nfx, _, nglob = W.shape
        nf, mx = ux.shape
        my = uy.shape[1]
        ntap = tab.shape[1]
        ntab = tab.shape[0] - 1
        nty = ntap if nfy > 1 else 1
        ung = u64(nglob)
        Wf = W.ravel()
        for f in range(f0, nf, fstep):
            L = u64(glen[f])
            ls = u64(lstart[f])
            wrap = ls + L > ung
            for g in range(mx * my):
                u = ux[f, g % mx]
                iu = int(u)
                x = (u - iu) * ntab
                kx = int(x)
                rx = np.float32(x - kx)
                v = uy[f, g // mx]
                iv = int(v)
                y = (v - iv) * ntab
                ky = int(y)
                ry = np.float32(y - ky)
                src = u64(gbase[f]) + u64(g) * (L + L)
                for ty in range(nty):
                    wy = tab[ky, ty] + ry * dtab[ky, ty] if nfy > 1 else np.float32(1)
                    rowy = ((iv + ty) % nfy) * nfx
                    for tx in range(ntap):
                        wgt = wy * (tab[kx, tx] + rx * dtab[kx, tx])
                        dre = u64(rowy + (iu + tx) % nfx) * (ung + ung)
                        if not wrap:
                            dre += ls
                            dim = dre + ung
                            for ll in range(L):
                                Wf[dre + ll] += wgt * G[src + ll]
                                Wf[dim + ll] += wgt * G[src + L + ll]
                        else:
                            for ll in range(L):
                                lg = (ls + ll) % ung
                                Wf[dre + lg] += wgt * G[src + ll]
                                Wf[dre + ung + lg] += wgt * G[src + L + ll]

    @_jit
    def accumulate(G, b0, n, c, s, acc):  # pragma: no cover
        """acc[:n] = Σ_m c_m G[b0 + m n : …], acc[n:2n] = Σ_m s_m G[…] (rows taken four at a time)."""
        nm = c.shape[0]
        acc[: n + n] = 0
        m = 0
        while m + 4 <= nm:
            c0, c1, c2, c3 = c[m], c[m + 1], c[m + 2], c[m + 3]
            s0, s1, s2, s3 = s[m], s[m + 1], s[m + 2], s[m + 3]
            r0 = b0 + u64(m) * n
            r1 = r0 + n
            r2 = r1 + n
            r3 = r2 + n
            for t in range(n):
                g0 = G[r0 + t]
                g1 = G[r1 + t]
                g2 = G[r2 + t]
                g3 = G[r3 + t]
                acc[t] += c0 * g0 + c1 * g1 + c2 * g2 + c3 * g3
                acc[n + t] += s0 * g0 + s1 * g1 + s2 * g2 + s3 * g3
            m += 4
        while m < nm:
            c0, s0 = c[m], s[m]
            r0 = b0 + u64(m) * n
            for t in range(n):
                g0 = G[r0 + t]
                acc[t] += c0 * g0
                acc[n + t] += s0 * g0
            m += 1

    @_jit
    def lat_y(G, b0, L, mx, Cy, Sy, ny, q0, q1, T, acc):  # pragma: no cover
        """T[m_x, y, re/im, l] = Σ_{m_y} e^{iθ_{m_y} p_y} G[b0 + (m_y, m_x, re/im, l)], y = N_y//2 ± q for
        q in [q0, q1): U = Σ C G, V = Σ S G (rows of M_x·2L), then U ± iV."""
        L2 = L + L
        n = u64(mx) * L2
        cy = ny // 2
        for q in range(q0, q1):
            accumulate(G, b0, n, Cy[q], Sy[q], acc)
            for sgn in range(2):
                y = cy + q if sgn == 0 else cy - q
                if y < 0 or y >= ny or (sgn == 1 and q == 0):
                    continue
                sv = np.float32(1 - 2 * sgn)
                for a in range(mx):  # U ± iV: re = Ur ∓ Vi, im = Ui ± Vr
                    u = u64(a) * L2
                    dst = u64(a * ny + y) * L2
                    for t in range(L):
                        T[dst + t] = acc[u + t] - sv * acc[n + u + L + t]
                        T[dst + L + t] = acc[u + L + t] + sv * acc[n + u + t]

    @_jit
    def lat_x(T, L, Cx, Sx, nx, ny, q0, q1, H, ls, acc):  # pragma: no cover
        """H[x, y, re/im, ls + l (mod nglob)] += Σ_{m_x} e^{iθ_{m_x} p_x} T[m_x, y, re/im, l], x = N_x//2 ± q
        for q in [q0, q1)."""
        nglob = u64(H.shape[3])
        Hf = H.ravel()
        L2 = L + L
        n = u64(ny) * L2
        cx = nx // 2
        wrap = ls + L > nglob
        for q in range(q0, q1):
            accumulate(T, u64(0), n, Cx[q], Sx[q], acc)
            for sgn in range(2):
                x = cx + q if sgn == 0 else cx - q
                if x < 0 or x >= nx or (sgn == 1 and q == 0):
                    continue
                sv = np.float32(1 - 2 * sgn)
                for y in range(ny):
                    u = u64(y) * L2
                    dst = u64(x * ny + y) * (nglob + nglob)
                    if not wrap:
                        dst += ls
                        for t in range(L):
                            Hf[dst + t] += acc[u + t] - sv * acc[n + u + L + t]
                            Hf[dst + nglob + t] += acc[u + L + t] + sv * acc[n + u + t]
                    else:
                        for t in range(L):
                            lg = (ls + t) % nglob
                            Hf[dst + lg] += acc[u + t] - sv * acc[n + u + L + t]
                            Hf[dst + nglob + lg] += acc[u + L + t] + sv * acc[n + u + t]

    @_jit
    def lateral_exact(G, gbase, glen, lstart, Cx, Sx, Cy, Sy, nx, ny, T, acc, H, f0, fstep):  # pragma: no cover
        """Exact lateral DFTs of the frequencies f0, f0 + fstep, … accumulated into H."""
        nf, qx, mx = Cx.shape
        qy, my = Cy.shape[1], Cy.shape[2]
        for f in range(f0, nf, fstep):
            L = u64(glen[f])
            b0 = u64(gbase[f])
            if ny == 1 and my == 1:  # 2D: the block is already (m_x, 1, re/im, l)
                lat_x(G[b0:], L, Cx[f], Sx[f], nx, ny, 0, qx, H, u64(lstart[f]), acc)
            else:
                lat_y(G, b0, L, mx, Cy[f], Sy[f], ny, 0, qy, T, acc)
                lat_x(T, L, Cx[f], Sx[f], nx, ny, 0, qx, H, u64(lstart[f]), acc)

    @_jit
    def depth_synthesis(H, A, B, out, r0, r1):  # pragma: no cover
        """out[r, (n, re/im)] = Σ_c Σ_l Hr[c, r, l] A[l] + Hi[c, r, l] B[l] (band → depth, partial sums c)."""
        nc = H.shape[0]
        nglob, n2 = A.shape
        for r in range(r0, r1):
            o = out[r]
            o[:] = 0
            for l in range(nglob):
                hr = H[0, r, 0, l]
                hi = H[0, r, 1, l]
                for c in range(1, nc):
                    hr += H[c, r, 0, l]
                    hi += H[c, r, 1, l]
                a = A[l]
                b = B[l]
                for k in range(n2):
                    o[k] += hr * a[k] + hi * b[k]


_POOLS: dict[int, ThreadPoolExecutor] = {}


def pool(n: int, ntasks: int, fn: Callable[..., None], args: Callable[[int, int], tuple]) -> None:
    """Run fn(*args(slot, t)) for the tasks t = 0…ntasks−1 on n threads (the calling one included),
    handed out one at a time, so a thread slowed by other jobs on the machine takes fewer. slot ∈ [0, n)
    names the running thread (its private buffers)."""
    n = max(1, min(n, ntasks))
    if n == 1:
        for t in range(ntasks):
            fn(*args(0, t))
        return
    tasks = iter(range(ntasks))
    lock = threading.Lock()

    def loop(slot: int) -> None:
        while True:
            with lock:
                t = next(tasks, None)
            if t is None:
                return
            fn(*args(slot, t))

    if n not in _POOLS:
        _POOLS[n] = ThreadPoolExecutor(max_workers=n - 1, thread_name_prefix="presum")
    futures = [_POOLS[n].submit(loop, slot) for slot in range(1, n)]
    loop(0)
    for fut in futures:
        fut.result()


def split(n: int, parts: int, c: int) -> tuple[int, int]:
    """c-th of `parts` contiguous shares of range(n)."""
    return n * c // parts, n * (c + 1) // parts
