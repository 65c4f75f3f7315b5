"""The compiled per-frame loops of the lattice pre-sum kernel (`fpcore.kernel_presum.PresumTransform`,
docs/design.md §5) and the thread pool that runs them; the plan they execute (lattice, fixed-point
positions, tables) is built in `fpcore.kernel_presum`. Also the separable projection P_θu of
`fpcore.acquisition.to_plane_waves` (`project_freq`), on the same threads.

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
from typing import Any

import numpy as np

nb: ModuleType | None
try:  # numba compiles the spreading loops; without it PresumTransform is unavailable
    nb = importlib.import_module("numba")
except ImportError:  # pragma: no cover - depends on the environment
    nb = None

# fixed-point depth positions and the kernel table, as the plan (fpcore.kernel_presum) builds them
TAB_BITS = 11
N_TABLE = 1 << TAB_BITS  # kernel table resolution per cell (linear interpolation error ≈ 1e-6)
TAPS = 8  # kernel taps stored per sample: `taps8` adds them as one 8-float vector, so the tables have 8 columns
FRAC = 40  # fractional bits of the fixed-point depth positions
u64 = np.uint64  # every index of the kernels (no negative-index wraparound code)
SLAB_Q = 4  # y outputs q per slab of `lateral_sym` (≤ 2·SLAB_Q rows y; a multiple of 4, `accumulate_tile`'s)


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


def _jit(fn: Callable[..., Any], fastmath: bool = True) -> Callable[..., Any]:
    """numba.njit(fastmath, nogil, cached on disk; see the module doc for where). ``fastmath=False`` keeps
    IEEE order and no fused multiply-adds: a lane of a vectorized loop then rounds as the scalar tail does."""
    assert nb is not None
    try:
        return nb.njit(fastmath=fastmath, cache=True, nogil=True)(fn)
    except RuntimeError:  # "cannot cache function …: no locator available": nothing numba tried is writable
        fallback = None if nb.config.CACHE_DIR else _fallback_cache_dir()
        if fallback is not None:
            nb.config.CACHE_DIR = fallback
            try:
                return nb.njit(fastmath=fastmath, cache=True, nogil=True)(fn)
            except RuntimeError:
                pass
        return nb.njit(fastmath=fastmath, nogil=True)(fn)  # compiled at its first call, every process


def _inline(fn: Callable[..., Any]) -> Callable[..., Any]:
    """numba.njit(fastmath, nogil, inline='always'): a helper compiled inside each kernel that calls it (cached
    with it), never on its own."""
    assert nb is not None
    return nb.njit(fastmath=True, nogil=True, inline="always")(fn)


if nb is not None:
    _ir = importlib.import_module("llvmlite.ir")
    _types = importlib.import_module("numba.core.types")

    @importlib.import_module("numba.extending").intrinsic
    def taps8(typingctx, G, dst, dim, tab, dtab, k0, r, cr, ci):  # pragma: no cover
        """G[dst : dst + 8] += cr·v and G[dim : dim + 8] += ci·v, v = tab[k0 : k0 + 8] + r·dtab[k0 : k0 + 8]: one
        sample's 8 kernel taps (re and im) as three 8-float vector FMAs, fused as the scalar loop's. LLVM leaves
        that loop scalar (8 runtime iterations, two stores into one array): ~70 instructions a sample. G, tab,
        dtab: float32 arrays; the pieces must not overlap (|dim − dst| ≥ 8)."""
        f32 = _types.float32
        if not all(isinstance(a, _types.Array) and a.dtype == f32 for a in (G, tab, dtab)):
            return None
        sig = _types.void(G, dst, dim, tab, dtab, k0, f32, f32, f32)

        def codegen(context, builder, signature, args):
            g, d_re, d_im, t, dt, k, rv, crv, civ = args
            v8 = _ir.VectorType(_ir.FloatType(), 8)
            fma = builder.module.declare_intrinsic("llvm.fma.v8f32", (), _ir.FunctionType(v8, [v8, v8, v8]))

            def at(arr, ty, idx):  # a vector pointer to arr[idx]
                data = context.make_array(ty)(context, builder, arr).data
                return builder.bitcast(builder.gep(data, [idx]), v8.as_pointer())

            def splat(x):  # x in all 8 lanes
                one = builder.insert_element(_ir.Constant(v8, None), x, _ir.IntType(32)(0))
                return builder.shuffle_vector(
                    one, _ir.Constant(v8, None), _ir.Constant(_ir.VectorType(_ir.IntType(32), 8), [0] * 8)
                )

            gty, tty, dty = signature.args[0], signature.args[3], signature.args[4]
            v = builder.call(
                fma, [splat(rv), builder.load(at(dt, dty, k), align=4), builder.load(at(t, tty, k), align=4)]
            )
            for d, c in ((d_re, crv), (d_im, civ)):
                p = at(g, gty, d)
                builder.store(builder.call(fma, [splat(c), v, builder.load(p, align=4)]), p, align=4)
            return context.get_dummy_value()

        return sig, codegen

    @_inline
    def spread_freq(w, P, Q, ua, ub, go, gi, L, tab, dtab, G, b0, bstride, f, occ):  # pragma: no cover
        """Depth spreading of frequency f's samples j = (f, o, i) for each weight vector b:
        G[b0 + b·bstride + g(o, i)·2L + (re/im)·L + l] += w_bj P_fo Q_fi φ(u_j − l).

        w (Nb, Nf, No, Ni, 2), P (Nf, No, 2), Q (Nf, Ni, 2): re/im pairs; g = go[o] + gi[i], the lattice
        group (m_y·M_x + m_x). u = ua[f, o] + ub[f, i] ≥ 0, fixed point with FRAC fractional bits: position
        from the band's first bin, ⌊u⌋ the first of the 8 taps. Per (f, o), vectorizable passes over i make
        the ramp, the positions (shared by the Nb weight vectors) and the strengths; each sample adds 8 taps
        (`taps8`: tab and dtab have 8 columns).
        Zero weights (outside a fingerprint's angular support) are skipped; occ[b, g] = 1 marks the groups
        that received a non-zero one (occ: (Nb, M_x·M_y) uint8, not cleared here)."""
        nb, _, no, ni, _ = w.shape
        ntap = tab.shape[1]
        tabf = tab.ravel()
        dtabf = dtab.ravel()
        shift = FRAC - TAB_BITS
        fmask = (1 << shift) - 1
        fscale = np.float32(1.0 / (1 << shift))
        er = np.empty(ni, np.float32)
        ei = np.empty(ni, np.float32)
        cre = np.empty(ni, np.float32)
        cim = np.empty(ni, np.float32)
        rr = np.empty(ni, np.float32)
        kb = np.empty(ni, np.int64)
        off = np.empty(ni, np.int64)
        qr = np.empty(ni, np.float32)
        qi = np.empty(ni, np.float32)
        qr[:] = Q[f, :, 0]
        qi[:] = Q[f, :, 1]
        uL = u64(L)
        for o in range(no):
            pr = P[f, o, 0]
            pi = P[f, o, 1]
            a = ua[f, o]
            for i in range(ni):
                er[i] = pr * qr[i] - pi * qi[i]
                ei[i] = pr * qi[i] + pi * qr[i]
            for i in range(ni):
                u = a + ub[f, i]
                kb[i] = ((u >> shift) & (N_TABLE - 1)) * ntap
                rr[i] = np.float32(np.int32(u & fmask)) * fscale
                off[i] = (go[o] + gi[i]) * (L + L) + (u >> FRAC)
            for b in range(nb):
                wo = w[b, f, o]
                for i in range(ni):
                    xr = np.float32(wo[i, 0])
                    xi = np.float32(wo[i, 1])
                    cre[i] = xr * er[i] - xi * ei[i]
                    cim[i] = xr * ei[i] + xi * er[i]
                bb = u64(b0) + u64(b) * u64(bstride)
                for i in range(ni):
                    if wo[i, 0] == 0 and wo[i, 1] == 0:
                        continue
                    occ[b, go[o] + gi[i]] = 1
                    cr = cre[i]
                    ci = cim[i]
                    r = rr[i]
                    k0 = u64(kb[i])
                    dst = bb + u64(off[i])
                    dim = dst + uL
                    taps8(G, dst, dim, tabf, dtabf, k0, r, cr, ci)

    @_jit
    def spread_depth(w, P, Q, ua, ub, go, gi, gbase, glen, tab, dtab, G, f0, fstep):  # pragma: no cover
        """`spread_freq` of one weight vector w (1, Nf, No, Ni, 2) for f = f0, f0 + fstep, … into the
        frequency blocks G[gbase[f]:gbase[f + 1]] (zeroed first)."""
        occ = np.zeros((1, (go.max() + gi.max() + 1)), np.uint8)
        for f in range(f0, w.shape[1], fstep):
            G[u64(gbase[f]) : u64(gbase[f + 1])] = 0
            spread_freq(w, P, Q, ua, ub, go, gi, glen[f], tab, dtab, G, gbase[f], 0, f, occ)

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

    @_inline
    def butterfly(G, M, n, j0, j1):  # pragma: no cover
        """Rows j ∈ [j0, min(j1, M//2)) of G (M rows of n) become G_j + G_{M−1−j}, rows M−1−j become
        G_j − G_{M−1−j}."""
        for j in range(j0, min(j1, M // 2)):
            a = u64(j) * u64(n)
            b = u64(M - 1 - j) * u64(n)
            for t in range(u64(n)):
                x = G[a + t]
                y = G[b + t]
                G[a + t] = x + y
                G[b + t] = x - y

    @_inline
    def pair_span(occ, mx, M, axis, a0, a1):  # pragma: no cover
        """[lo, hi): the pairs (j, M−1−j) of lattice rows holding data. axis 0: rows m_y, any group of the
        columns m_x ∈ [a0, a1); axis 1: rows m_x, any group. occ (M_y·M_x) marks the occupied groups."""
        lo, hi = M, 0
        my = occ.size // mx
        for j in range(M):
            jp = min(j, M - 1 - j)
            if lo <= jp < hi:
                continue
            for a in range(a0, a1) if axis == 0 else range(my):
                if occ[j * mx + a if axis == 0 else a * mx + j]:
                    lo = min(lo, jp)
                    hi = max(hi, jp + 1)
                    break
        return lo, max(lo, hi)

    @_inline
    def accumulate_tile(G, c0, width, n, r_first, r_step, m0, nrows, coef, q0, acc):  # pragma: no cover
        """acc[k, :width] = Σ_{m0≤m<nrows} coef[q0 + k, m] G[row_m·n + c0 : … + width] for k < 4 (rows of coef past
        its end give 0), row_m = r_first + r_step·m: four outputs from each row loaded, eight rows at a time, then
        four (32 FMAs per 8 loads and 4 accumulator updates; the accumulators of a column block stay in L1). Alone,
        17 → 31 GFMA/s a core against four rows at a time; inside `lateral_sym`, 5–10 % of a full-size call."""
        nq = coef.shape[0]
        uw = u64(width)
        a0, a1, a2, a3 = acc[0], acc[1], acc[2], acc[3]
        a0[:width] = 0
        a1[:width] = 0
        a2[:width] = 0
        a3[:width] = 0
        m = m0
        while m < nrows:
            ns = 8 if nrows - m >= 8 else 4  # rows this step (past nrows: clamped rows, zero coefficients)
            cf = np.zeros((4, 8), np.float32)
            r = [u64(0)] * 8
            for s in range(ns):
                r[s] = u64(r_first + r_step * min(m + s, nrows - 1)) * u64(n) + u64(c0)
                if m + s < nrows:
                    for k in range(4):
                        if q0 + k < nq:
                            cf[k, s] = coef[q0 + k, m + s]
            r0, r1, r2, r3, r4, r5, r6, r7 = r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7]
            c00, c01, c02, c03 = cf[0, 0], cf[0, 1], cf[0, 2], cf[0, 3]
            c04, c05, c06, c07 = cf[0, 4], cf[0, 5], cf[0, 6], cf[0, 7]
            c10, c11, c12, c13 = cf[1, 0], cf[1, 1], cf[1, 2], cf[1, 3]
            c14, c15, c16, c17 = cf[1, 4], cf[1, 5], cf[1, 6], cf[1, 7]
            c20, c21, c22, c23 = cf[2, 0], cf[2, 1], cf[2, 2], cf[2, 3]
            c24, c25, c26, c27 = cf[2, 4], cf[2, 5], cf[2, 6], cf[2, 7]
            c30, c31, c32, c33 = cf[3, 0], cf[3, 1], cf[3, 2], cf[3, 3]
            c34, c35, c36, c37 = cf[3, 4], cf[3, 5], cf[3, 6], cf[3, 7]
            if ns == 8:
                for t in range(uw):
                    g0, g1, g2, g3 = G[r0 + t], G[r1 + t], G[r2 + t], G[r3 + t]
                    g4, g5, g6, g7 = G[r4 + t], G[r5 + t], G[r6 + t], G[r7 + t]
                    a0[t] += (c00 * g0 + c01 * g1 + c02 * g2 + c03 * g3) + (c04 * g4 + c05 * g5 + c06 * g6 + c07 * g7)
                    a1[t] += (c10 * g0 + c11 * g1 + c12 * g2 + c13 * g3) + (c14 * g4 + c15 * g5 + c16 * g6 + c17 * g7)
                    a2[t] += (c20 * g0 + c21 * g1 + c22 * g2 + c23 * g3) + (c24 * g4 + c25 * g5 + c26 * g6 + c27 * g7)
                    a3[t] += (c30 * g0 + c31 * g1 + c32 * g2 + c33 * g3) + (c34 * g4 + c35 * g5 + c36 * g6 + c37 * g7)
            else:
                for t in range(uw):
                    g0, g1, g2, g3 = G[r0 + t], G[r1 + t], G[r2 + t], G[r3 + t]
                    a0[t] += c00 * g0 + c01 * g1 + c02 * g2 + c03 * g3
                    a1[t] += c10 * g0 + c11 * g1 + c12 * g2 + c13 * g3
                    a2[t] += c20 * g0 + c21 * g1 + c22 * g2 + c23 * g3
                    a3[t] += c30 * g0 + c31 * g1 + c32 * g2 + c33 * g3
            m += ns

    @_inline
    def emit(cr, ci, sr, si, Pr, Pi, Mr, Mi, ec, es, vp, vm, add):  # pragma: no cover
        """The outputs p = ±q of `lateral_sym` from the cosine sums U = cr + i·ci and sine sums V = sr + i·si:
        (U ± iV) e^{±iθ_c q} into P (p = +q, when vp) and M (p = −q, when vm), written or added (add); both
        from one pass over the sums when both exist. P may stand for M when only vm holds."""
        if vp and vm:
            for t in range(cr.size):
                r1, i1 = cr[t] - si[t], ci[t] + sr[t]
                r2, i2 = cr[t] + si[t], ci[t] - sr[t]
                a, b = r1 * ec - i1 * es, r1 * es + i1 * ec
                c, d = r2 * ec + i2 * es, i2 * ec - r2 * es
                if add:
                    Pr[t] += a
                    Pi[t] += b
                    Mr[t] += c
                    Mi[t] += d
                else:
                    Pr[t] = a
                    Pi[t] = b
                    Mr[t] = c
                    Mi[t] = d
        elif vp or vm:
            sv = np.float32(1.0 if vp else -1.0)
            for t in range(cr.size):
                rr, ii = cr[t] - sv * si[t], ci[t] + sv * sr[t]
                a, b = rr * ec - sv * ii * es, sv * rr * es + ii * ec
                if add:
                    Pr[t] += a
                    Pi[t] += b
                else:
                    Pr[t] = a
                    Pi[t] = b

    @_inline
    def lateral_sym(G, L, mx, my, nx, ny, Cy, Sy, Ey, Cx, Sx, Ex, T, accC, accS, H, ls, blk, occ):  # pragma: no cover
        """Exact lateral DFTs of one frequency's rows G[(m_y, m_x), re/im, l] accumulated into H[x, y, re/im,
        ls + l (mod nglob)]: Σ_m e^{iθ_m p} G_m = e^{iθ_c p} Σ_m e^{iθ'_m p} G_m with θ' = θ − θ_c symmetric
        about the lattice's centre θ_c, so the pairs m, M−1−m share cos(θ'q) and sin(θ'q) up to sign (a
        butterfly, then half the products); p = ±q even/odd as before. C (Q, (M+1)//2) = cos θ'q,
        S (Q, M//2) = sin θ'q, E (Q, 2) = (cos, sin) θ_c q. The y outputs go SLAB_Q q at a time (≤ 2·SLAB_Q rows
        y = N_y//2 ± q): the y sums of every column m_x into a slab T[m_x, y-slot, re/im, l] (L2-sized), then
        the x sums of that slab into H, so the y pass's output never leaves the core's cache (a whole T[m_x, y]
        per frequency did: 4.5 MB a thread on the full-size frame; a column block of G is re-read from L3 once
        per slab instead). Columns in blocks of ~blk floats, four q at a time (`accumulate_tile`; accC, accS
        (4, ≥ max(blk, 2L))). Only the pairs that hold data are summed: occ (M_y·M_x) marks the occupied groups
        (a fingerprint's angular support leaves most of them empty).
        G and T (≥ M_x·min(2·SLAB_Q, N_y)·2L) are overwritten."""
        L2 = L + L
        uL = u64(L)
        nglob = u64(H.shape[3])
        Hf = H.ravel()
        wrap = ls + uL > nglob
        xlo, xhi = pair_span(occ, mx, mx, 1, 0, 0)
        if xlo >= xhi:
            return  # no data at this frequency
        ylo, yhi = pair_span(occ, mx, my, 0, 0, mx)
        butterfly(G, my, mx * L2, ylo, yhi)
        ub = max(1, blk // L2)  # units of 2L columns per block
        u1 = mx - xlo  # the columns m_x that the x pass reads
        nblk = (u1 - xlo + ub - 1) // ub
        span = np.empty((nblk, 2), np.int64)  # occupied pairs of rows m_y per column block
        for bi in range(nblk):
            a0 = xlo + bi * ub
            span[bi, 0], span[bi, 1] = pair_span(occ, mx, my, 0, a0, min(u1, a0 + ub))
        ys = np.empty(2 * SLAB_Q, np.int64)
        cy, cx = ny // 2, nx // 2
        nG = mx * L2
        nq = Cy.shape[0]
        for q0 in range(0, nq, SLAB_Q):
            q1 = min(q0 + SLAB_Q, nq)
            ns = 0  # slots of the slab: y = cy ± q, q0 ≤ q < q1, in `emit`'s order (+q, then −q)
            for q in range(q0, q1):
                if cy + q < ny:
                    ys[ns] = cy + q
                    ns += 1
                if q > 0 and cy - q >= 0:
                    ys[ns] = cy - q
                    ns += 1
            if ns == 0:
                continue
            nT = ns * L2
            # y: rows m_y of G → slab T[m_x, slot, re/im, l]; a column block of G stays in L2 for all its q
            for bi in range(nblk):
                a0 = xlo + bi * ub
                a1 = min(u1, a0 + ub)
                width = (a1 - a0) * L2
                jlo, jhi = span[bi, 0], span[bi, 1]
                s = 0
                for q in range(q0, q1):
                    k = (q - q0) % 4
                    if k == 0:
                        accumulate_tile(G, a0 * L2, width, nG, 0, 1, jlo, min(jhi, (my + 1) // 2), Cy, q, accC)
                        accumulate_tile(G, a0 * L2, width, nG, my - 1, -1, jlo, min(jhi, my // 2), Sy, q, accS)
                    vp, vm = cy + q < ny, q > 0 and cy - q >= 0
                    if not (vp or vm):
                        continue
                    aC = accC[k]
                    aS = accS[k]
                    ec = Ey[q, 0]
                    es = Ey[q, 1]
                    sm = s + 1 if vp and vm else s
                    for a in range(a0, a1):
                        u = u64(a - a0) * u64(L2)
                        cr, ci, sr, si = aC[u : u + uL], aC[u + uL : u + L2], aS[u : u + uL], aS[u + uL : u + L2]
                        dp = u64(a * ns + s) * u64(L2)
                        dm = u64(a * ns + sm) * u64(L2)
                        Tp, Tm = T[dp : dp + L2], T[dm : dm + L2]
                        emit(cr, ci, sr, si, Tp[:uL], Tp[uL:], Tm[:uL], Tm[uL:], ec, es, vp, vm, False)
                    s = sm + 1
            # x: rows m_x of the slab (n = slots·2L) → H[x, y, re/im, ls + l]
            butterfly(T, mx, nT, xlo, xhi)
            for b0 in range(0, ns, ub):
                b1 = min(ns, b0 + ub)
                width = (b1 - b0) * L2
                for q in range(Cx.shape[0]):
                    k = q % 4
                    if k == 0:  # cosine rows j < (M+1)//2, sine rows M−1−j, j < M//2 (`butterfly`)
                        accumulate_tile(T, b0 * L2, width, nT, 0, 1, xlo, min(xhi, (mx + 1) // 2), Cx, q, accC)
                        accumulate_tile(T, b0 * L2, width, nT, mx - 1, -1, xlo, min(xhi, mx // 2), Sx, q, accS)
                    aC = accC[k]
                    aS = accS[k]
                    ec = Ex[q, 0]
                    es = Ex[q, 1]
                    pp, pm = cx + q, cx - q  # outputs p = ±q about the centre
                    vp, vm = pp < nx, q > 0 and pm >= 0
                    for b in range(b0, b1):
                        u = u64(b - b0) * u64(L2)
                        y = ys[b]
                        cr, ci, sr, si = aC[u : u + uL], aC[u + uL : u + L2], aS[u : u + uL], aS[u + uL : u + L2]
                        if not wrap:
                            dp = u64((pp if vp else pm) * ny + y) * (nglob + nglob) + ls
                            dm = u64(pm * ny + y) * (nglob + nglob) + ls
                            Hp, Hm = Hf[dp : dp + nglob + uL], Hf[dm : dm + nglob + uL]
                            emit(cr, ci, sr, si, Hp[:uL], Hp[nglob:], Hm[:uL], Hm[nglob:], ec, es, vp, vm, True)
                        else:  # the band wraps modulo nglob
                            for sgn in range(2):
                                if not (vp if sgn == 0 else vm):
                                    continue
                                sv = np.float32(1 - 2 * sgn)
                                dst = u64((pp if sgn == 0 else pm) * ny + y) * (nglob + nglob)
                                for t in range(uL):
                                    rr = aC[u + t] - sv * aS[u + uL + t]
                                    ii = aC[u + uL + t] + sv * aS[u + t]
                                    lg = (ls + t) % nglob
                                    Hf[dst + lg] += rr * ec - sv * ii * es
                                    Hf[dst + nglob + lg] += sv * rr * es + ii * ec

    @_jit
    def exact_fused(
        w, P, Q, ua, ub, go, gi, glen, lstart, tab, dtab, lat, G, T, accC, accS, H, blk, f0, fstep
    ):  # pragma: no cover
        """The exact-lateral path per frequency f = f0, f0 + fstep, …: `spread_freq` of the Nb weight vectors
        into G (Nb, ≥ M_x·M_y·2L_f; this thread's, zeroed first), then `lateral_sym` of each into H[b]
        (Nb, N_x, N_y, 2, nglob; this thread's partial sums). One frequency's block stays in cache from
        spreading to synthesis. lat = (Cy, Sy, Ey, Cx, Sx, Ex) per frequency."""
        Cy, Sy, Ey, Cx, Sx, Ex = lat
        nb = w.shape[0]
        nx, ny = H.shape[1], H.shape[2]
        mx = Cx.shape[2] + Sx.shape[2]
        my = Cy.shape[2] + Sy.shape[2]
        gs = G.shape[1]
        Gf = G.ravel()
        occ = np.zeros((nb, mx * my), np.uint8)
        for f in range(f0, w.shape[1], fstep):
            L = glen[f]
            n1 = mx * my * 2 * L
            for b in range(nb):
                G[b, :n1] = 0
            occ[:] = 0
            spread_freq(w, P, Q, ua, ub, go, gi, L, tab, dtab, Gf, 0, gs, f, occ)
            for b in range(nb):
                lateral_sym(
                    G[b],
                    L,
                    mx,
                    my,
                    nx,
                    ny,
                    Cy[f],
                    Sy[f],
                    Ey[f],
                    Cx[f],
                    Sx[f],
                    Ex[f],
                    T,
                    accC,
                    accS,
                    H[b],
                    u64(lstart[f]),
                    blk,
                    occ[b],
                )

    @_inline
    def caccumulate(Xr, Xi, n, m0, m1, c0, width, Cr, Ci, q0, Ar, Ai):  # pragma: no cover
        """A[k, :width] = Σ_{m0≤m<m1} (Cr + iCi)[q0 + k, m] (Xr + iXi)[m·n + c0 : … + width] for k < 4 (rows
        of C past its end give 0): complex rows on split re/im planes, four outputs per row loaded."""
        nq = Cr.shape[0]
        uw = u64(width)
        for k in range(4):
            Ar[k, :width] = 0
            Ai[k, :width] = 0
        for m in range(m0, m1):
            r = u64(m) * u64(n) + u64(c0)
            for k in range(min(4, nq - q0)):
                cr = Cr[q0 + k, m]
                ci = Ci[q0 + k, m]
                ar = Ar[k]
                ai = Ai[k]
                for t in range(uw):
                    xr = Xr[r + t]
                    xi = Xi[r + t]
                    ar[t] += cr * xr - ci * xi
                    ai[t] += cr * xi + ci * xr

    @_jit
    def project_freq(R, pyr, pyi, pxr, pxi, oidx, out, Xr, Xi, Yr, Yi, Ar, Ai, blk, f0, fstep):  # pragma: no cover
        """R_θθ(f) = P_θu(f) R_uθ(f) on a regular matrix array and a tensor grid of output sines, separable
        (docs/design.md §4.2): per frequency f = f0, f0 + fstep, …, Y[s_y, (u_x, i)] = Σ_{u_y} P^y[s_y, u_y]
        R[(u_y, u_x), i], then Z[s_x, (s_y, i)] = Σ_{u_x} P^x[s_x, u_x] Y[u_x, (s_y, i)], out[f, oidx[s_y, s_x],
        i] = Z (oidx < 0: a sine not kept). R (Nf, N_uy, N_ux, N_i, 2) and out (Nf, N_o, N_i, 2): re/im
        pairs; P^y = pyr + i pyi (Nf, N_sy, N_uy), P^x likewise; Xr … Ai: this thread's work planes."""
        nf, nuy, nux, ni, _ = R.shape
        nsy, nsx = oidx.shape
        for f in range(f0, nf, fstep):
            # split planes X[u_y, (u_x, i)]
            for uy in range(nuy):
                for ux in range(nux):
                    for i in range(ni):
                        j = (uy * nux + ux) * ni + i
                        Xr[j] = R[f, uy, ux, i, 0]
                        Xi[j] = R[f, uy, ux, i, 1]
            # y: Y[s_y, (u_x, i)], stored transposed as Yt[u_x, (s_y, i)]
            n = nux * ni
            for c0 in range(0, n, blk):
                w = min(blk, n - c0)
                for q in range(0, nsy, 4):
                    caccumulate(Xr, Xi, n, 0, nuy, c0, w, pyr[f], pyi[f], q, Ar, Ai)
                    for k in range(min(4, nsy - q)):
                        for t in range(w):
                            ux, i = divmod(c0 + t, ni)
                            j = (ux * nsy + q + k) * ni + i
                            Yr[j] = Ar[k, t]
                            Yi[j] = Ai[k, t]
            # x: Z[s_x, (s_y, i)] → out
            n = nsy * ni
            for c0 in range(0, n, blk):
                w = min(blk, n - c0)
                for q in range(0, nsx, 4):
                    caccumulate(Yr, Yi, n, 0, nux, c0, w, pxr[f], pxi[f], q, Ar, Ai)
                    for k in range(min(4, nsx - q)):
                        for t in range(w):
                            sy, i = divmod(c0 + t, ni)
                            o = oidx[sy, q + k]
                            if o >= 0:
                                out[f, o, i, 0] = Ar[k, t]
                                out[f, o, i, 1] = Ai[k, t]

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
