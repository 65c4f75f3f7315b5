"""The transport additions to the multiple-scattering background (fpcore.simulate.diffuse, single_scattering,
medium.ScatteringLayer): dispersion ℓ_s(f), the beads' single scattering, reciprocity and coherent
backscattering, and the ballistic echo filtered by ℓ_ext(f) (docs/design.md §6.3)."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore.acquisition import PlaneWaveSequence, Probe
from fpcore.geometry import cosines, secant_over_aperture
from fpcore.simulate import scenario
from fpcore.simulate.diffuse import DiffuseBackground, aligned_spacing, project_plane_waves, reciprocal_pairs
from fpcore.simulate.medium import ScatteringLayer
from fpcore.simulate.reciprocity import ElementReciprocity, array_factor, main_lobe_steps
from fpcore.simulate.scenarios import PAPER_POSITIONS
from fpcore.simulate.single_scattering import SingleScatteringField
from fpcore.simulate.waves import Band, TimeWindow, radiate_points

C0 = 1500.0


def _layer(**kw) -> ScatteringLayer:
    base = dict(z_surface=5e-3, ls=1.8e-3, la=8e-3, ls_exponent=4.0, f_ref=2.2e6, f_cross=1.54e6)
    base.update(kw)
    return ScatteringLayer(**base)


def test_dispersion_law_is_anchored_rayleigh_below_the_crossover_and_saturates_above() -> None:
    lay = _layer()
    assert float(lay.ls_at(2.2e6)) == pytest.approx(1.8e-3)
    lo = lay.ls_at(np.array([0.2e6, 0.4e6]))
    assert lo[0] / lo[1] == pytest.approx(2.0**4, rel=0.01)  # Rayleigh: ℓ_s ∝ f^−4 for f ≪ f_cross
    hi = lay.ls_at(np.array([20e6, 40e6]))
    assert hi[0] / hi[1] == pytest.approx(1.0, abs=0.01)  # geometric: independent of f
    pure = _layer(f_cross=0.0)
    assert float(pure.ls_at(1.1e6)) == pytest.approx(1.8e-3 * 2.0**4)
    assert float(lay.l_ext_at(2.2e6)) == pytest.approx(lay.l_ext)
    with pytest.raises(ValueError, match="f_ref"):
        ScatteringLayer(z_surface=5e-3, ls=1e-3, ls_exponent=4.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_diffusion_reflectance_conserves_flux_and_a_slab_lets_the_rest_through(dim: int) -> None:
    """Lossless diffusion (docs/design.md §6.3): a half-space returns all the flux (∫ρ ds = 1, the Lévy
    density); a slab whose extrapolated boundaries are L' = L + 2z_e apart returns 1 − z₁/L' (gambler's
    ruin of a walker started at z₁ = ℓ_s + z_e); a very thick slab is the half-space."""
    ls = 1.8e-3
    half = ScatteringLayer(z_surface=5e-3, ls=ls, envelope="diffusion")
    s = np.geomspace(1e-7, 400.0, 400_001)
    total = float(np.trapezoid(half.reflectance_density(s, dim=dim), s))
    assert total == pytest.approx(1.0, abs=0.01)
    dp, z_e = half.diffusion_constants(dim)
    assert dp == pytest.approx(ls / dim)
    assert z_e == pytest.approx(2 * ls / 3 if dim == 3 else np.pi * ls / 4)
    thick = 12e-3
    slab = ScatteringLayer(z_surface=5e-3, ls=ls, envelope="diffusion", thickness=thick)
    s_slab = np.geomspace(1e-7, 2.0, 200_001)  # the slab's slowest mode has decayed by e^{-16} at 0.4 m
    kept = float(np.trapezoid(slab.reflectance_density(s_slab, dim=dim), s_slab))
    assert kept == pytest.approx(1 - (ls + z_e) / (thick + 2 * z_e), abs=0.01)
    deep = ScatteringLayer(z_surface=5e-3, ls=ls, envelope="diffusion", thickness=10.0)
    early = np.linspace(1e-3, 0.2, 50)
    np.testing.assert_allclose(
        deep.reflectance_density(early, dim=dim), half.reflectance_density(early, dim=dim), rtol=1e-9
    )
    with pytest.raises(ValueError, match="thickness"):
        ScatteringLayer(z_surface=5e-3, ls=ls, thickness=0.0)


def test_ballistic_echo_is_filtered_by_l_ext_of_each_frequency() -> None:
    lay = _layer()
    probe = Probe.linear(16, 0.34e-3, 2.2e6, 0.8e6)
    sines = np.array([[0.0, 0.0], [0.1, 0.0]])
    f = np.linspace(1.6e6, 2.8e6, 5)
    r = np.array([1e-3, 0.0, 12e-3])
    h0 = radiate_points(r[None, :], np.array([1e-3]), probe.positions, sines, f, C0, 2)
    h = lay.attenuate(h0, r, 0.0, probe.positions, sines, freqs=f)
    depth = r[2] - lay.z_surface
    dist = np.linalg.norm(probe.positions - r[None, :], axis=1)
    legs = dist[None, :, None] * depth / r[2] + depth / cosines(sines)[None, None, :]
    expected = np.exp(-legs / (2 * lay.l_ext_at(f)[:, None, None])) * (1 - lay.reflection() ** 2)
    np.testing.assert_allclose(np.abs(h / h0), expected, rtol=2e-5)
    assert np.abs(h[-1] / h0[-1]).max() < np.abs(h[0] / h0[0]).min()  # high frequencies attenuated more


@pytest.mark.parametrize("dim", [2, 3])
def test_single_scattering_nufft_equals_the_direct_sum(dim: int) -> None:
    """A(o, θ, f) = W_b (1 − R²) Σ_j blend_j(f) Σ_m η_m w_θ(x_m) e^{−ik[(a − b)·x + (c_a + c_b) z]}
    × e^{−d (1/c_a + q(z))/(2ℓ_ext(f_j))} (single_scattering module doc): sub-bands blended, each transmit's beam
    steered, each transmit's leg extinguished along its own slant and the receive's over the aperture's fan."""
    lay = _layer(single_scattering="field")
    so = np.stack([np.linspace(-0.4, 0.4, 7), np.zeros(7) if dim == 2 else np.linspace(-0.3, 0.3, 7)], 1)
    si = np.array([[-0.2, 0.0], [0.0, 0.0], [0.1, 0.05 if dim == 3 else 0.0]])
    f = np.linspace(1.6e6, 2.8e6, 5)
    centres = np.array([1.9e6, 2.6e6])
    blend = np.stack([np.interp(f, centres, [1.0, 0.0]), np.interp(f, centres, [0.0, 1.0])])
    ap = (3e-3, 3e-3 if dim == 3 else 0.0)
    rng = np.random.default_rng(0)
    ss = SingleScatteringField(lay, si, f, blend, centres, C0, dim, ap, 3e-3, rng, s_out=so, ds=0.05)
    ss.advance()
    a = ss.spectrum()
    assert ss.state is not None
    xs = (np.arange(ss.nx) - ss.nx // 2) * ss.hx
    ys = (np.arange(ss.ny) - ss.ny // 2) * ss.hx
    x, y, d = np.meshgrid(xs, ys, ss.depths, indexing="ij")
    co, ci = cosines(so), cosines(si)
    ref = np.zeros_like(a)
    for wts, fc in zip(blend, centres, strict=True):
        ls, le, kc = float(lay.ls_at(fc)), float(lay.l_ext_at(fc)), 2 * np.pi * fc / C0
        strength = 4 * np.pi / ls if dim == 3 else 4 * kc / ls
        q = secant_over_aperture(ap[: dim - 1], lay.z_surface + d)
        eta = ss.state * np.exp(-d * q / (2 * le)) * np.sqrt(strength * ss._cell)
        for fi in np.flatnonzero(wts > 0):
            k = 2 * np.pi * f[fi] / C0
            for t in range(si.shape[0]):
                lit = eta * ss.beam(t) * np.exp(-d / (2 * le * ci[t]))
                for o in range(so.shape[0]):
                    w = -1j * k * 0.05**2 / (8 * np.pi**2 * co[o]) if dim == 3 else -1j * 0.05 / (4 * np.pi * co[o])
                    lateral = (si[t, 0] - so[o, 0]) * x + ((si[t, 1] - so[o, 1]) * y if dim == 3 else 0.0)
                    ph = np.exp(-1j * k * (lateral + (ci[t] + co[o]) * (lay.z_surface + d)))
                    ref[o, t, fi] += wts[fi] * w * ss._t_r * np.sum(lit * ph)
    assert np.linalg.norm(a - ref) / np.linalg.norm(ref) < 1e-3
    # The beam follows the transmit: centred on z tan θ, so the steered transmit lights x < 0 more than x > 0.
    b0 = ss.beam(0)
    assert b0[xs < -2.5e-3].sum() > 2 * b0[xs > 2.5e-3].sum()


@pytest.mark.parametrize("dim", [2, 3])
def test_single_scattering_grid_gives_a_scatterers_green_function_at_the_elements(dim: int) -> None:
    """On its own output grid (spatial period λ/Δs beyond twice the largest source–element offset), the
    projected single-scattering field of one reflectivity cell is the Born echo t e^{−ik(a·x + c_a z)} G(u, r)
    at every element — also for a cell at the beam's edge, which a grid sized by the aperture alone aliases
    (images of the cell λ/Δs away, dispersed in time: energy before the surface echo)."""
    from fpcore.simulate.diffuse import project_plane_waves

    lay = _layer(single_scattering="field")
    n = 8 if dim == 3 else 16
    probe = Probe.matrix(n, n, 0.34e-3, 2.2e6, 0.8e6) if dim == 3 else Probe.linear(n, 0.34e-3, 2.2e6, 0.8e6)
    si = np.array([[-0.2, 0.0], [0.0, 0.0], [0.15, 0.1 if dim == 3 else 0.0]])
    f = np.linspace(1.8e6, 2.6e6, 4)
    ap = (n * 0.34e-3, n * 0.34e-3 if dim == 3 else 0.0)
    ls, le = float(lay.ls_at(2.2e6)), float(lay.l_ext_at(2.2e6))
    strength = 4 * np.pi / ls if dim == 3 else 4 * (2 * np.pi * f / C0) / ls

    def echo_error(ss: SingleScatteringField, axes=None, keep=None) -> float:
        ix, iy, iz = int(np.argmin(np.abs(ss._xs - 0.8 * ss._half[0]))), ss.ny // 2, ss.nz // 2
        ss.state = np.zeros((ss.nx, ss.ny, ss.nz), dtype=np.complex64)
        ss.state[ix, iy, iz] = 1.0
        got = project_plane_waves(ss.spectrum(), f, C0, probe.positions, ss.s_out, axes, keep)
        r = np.array([[ss._xs[ix], ss._ys[iy] if dim == 3 else 0.0, lay.z_surface + ss.depths[iz]]])
        d = ss.depths[iz]
        q = secant_over_aperture(ap[: dim - 1], lay.z_surface + d)
        t = ss._t_r * np.exp(-d * q / (2 * le)) * np.sqrt(strength * ss._cell) * np.ones(f.size)
        ref = radiate_points(r, t[None, :].astype(np.complex64), probe.positions, si, f, C0, dim)
        lit = [ss.beam(i)[ix, iy, iz] * np.exp(-d / (2 * le * cosines(si)[i])) for i in range(si.shape[0])]
        ref = ref * np.array(lit)[None, None, :]
        return float(np.linalg.norm(got - ref) / np.linalg.norm(ref))

    own = SingleScatteringField(
        lay, si, f, np.ones((1, f.size)), np.array([2.2e6]), C0, dim, ap, 2e-3, np.random.default_rng(0)
    )
    assert own.axes is not None and own.keep is not None
    assert echo_error(own, own.axes, own.keep) < 0.12  # 2–10 %: the Weyl sum's sampling and taper
    # The grid the multiple scattering uses (spatial period 1.2 × the aperture) misses it entirely.
    ds = C0 / f.max() / (1.2 * ap[0])
    ax = np.arange(-int(0.9 / ds), int(0.9 / ds) + 1) * ds
    so = np.stack(np.meshgrid(ax, ax, indexing="ij"), -1).reshape(-1, 2) if dim == 3 else np.stack([ax, 0 * ax], 1)
    so = so[np.hypot(so[:, 0], so[:, 1]) < 0.9]
    coarse = SingleScatteringField(
        lay,
        si,
        f,
        np.ones((1, f.size)),
        np.array([2.2e6]),
        C0,
        dim,
        ap,
        2e-3,
        np.random.default_rng(0),
        s_out=so,
        ds=ds,
    )
    assert echo_error(coarse) > 0.3


def _small_2d(**kw) -> tuple[DiffuseBackground, Probe, PlaneWaveSequence, Band, TimeWindow]:
    probe = Probe.linear(48, C0 / 2.2e6 / 2, 2.2e6, 0.8e6)
    seq = PlaneWaveSequence.uniform_sines(9, 0.2)
    band = Band(1.8e6, 2.6e6)
    win = TimeWindow.covering(10.4e6, 16e-6, 40e-6, guard=20e-6)
    lay = ScatteringLayer(z_surface=10e-3, ls=1.8e-3, la=8e-3, cbs=True, **kw)
    bg = DiffuseBackground(
        lay, probe.positions, seq.sines, win, band, C0, 2, 0.5 * probe.aperture[0], np.random.default_rng(3)
    )
    return bg, probe, seq, band, win


def test_output_grid_is_aligned_with_the_transmits_and_pairs_are_involutions() -> None:
    assert aligned_spacing(0.012, np.array([-0.2, -0.05, 0.0, 0.05, 0.2])) == pytest.approx(0.05 / 5)
    assert aligned_spacing(0.012, np.array([0.0, 0.0123456, 0.031])) is None
    bg, _, seq, _, _ = _small_2d()
    po, pt = reciprocal_pairs(bg.s_out, seq.sines)
    has = po >= 0
    assert has.sum() == seq.n_waves**2  # every transmit pair (a, −b) lies on the output grid
    o, t = np.nonzero(has)
    assert np.array_equal(po[po[o, t], pt[o, t]], o) and np.array_equal(pt[po[o, t], pt[o, t]], t)
    np.testing.assert_allclose(bg.s_out[po[o, t]], -seq.sines[t], atol=1e-12)
    np.testing.assert_allclose(seq.sines[pt[o, t]], -bg.s_out[o], atol=1e-12)


def _receive_beams(bg: DiffuseBackground, a: np.ndarray, rows: np.ndarray, b: np.ndarray) -> np.ndarray:
    """R̃(b, θ, f) = Σ_u e^{+ik b·u} M(u, θ, f) of the outputs `rows` of A (weights applied), projected onto
    the elements: the array's receive beams b (N_b, 2) → (N_b, N_θ, N_f)."""
    m = project_plane_waves(a[rows], bg.freqs, bg.c0, bg.elements, bg.s_out[rows])  # (N_f, N_u, N_θ)
    k = 2 * np.pi * bg.freqs / bg.c0
    steer = np.exp(1j * k[:, None, None] * (b @ bg.elements[:, :2].T)[None])  # (N_f, N_b, N_u)
    return np.transpose(np.matmul(steer, m), (1, 2, 0))


@pytest.mark.parametrize("angular", ["uniform", "halo"])
@pytest.mark.parametrize("single", ["envelope", "field"])
def test_background_is_reciprocal(single: str, angular: str) -> None:
    """The element-basis matrix is symmetric (R_uu' = R_u'u, `reciprocity`): through the array's own receive
    beams at the transmits' mirrors, Q(θ', θ) = R̃(−s_θ', θ)/c_θ equals Q(θ, θ') exactly for the main lobes'
    block, whichever orders the multiple scattering carries and whichever angular geometry; with the
    independent outputs of the beams' sidelobes added, the symmetry measure |Σ Q Q^T*|/Σ|Q|² stays high (the
    single scattering, on its own grid, is a sum of point echoes: `test_single_scattering_grid_gives_...`)."""
    bg, _, seq, _, _ = _small_2d(single_scattering=single, angular=angular)
    assert bg.block is not None and bg.block.steps[0] >= 1
    bg._advance()  # the first frame's draws: the noise and the block's
    a = bg.multiple_spectrum() * bg.weights[:, None, None]
    mirror = -seq.sines
    c = cosines(seq.sines)
    q_block = _receive_beams(bg, a, bg.block.rows, mirror) / c[None, :, None]
    sym = np.linalg.norm(q_block - np.swapaxes(q_block, 0, 1)) / np.linalg.norm(q_block)
    assert sym < 1e-4
    q = _receive_beams(bg, a, np.arange(bg.n_o), mirror) / c[None, :, None]
    off = ~np.eye(seq.n_waves, dtype=bool)
    measure = abs(np.sum((q * np.conj(np.swapaxes(q, 0, 1)))[off])) / np.sum(np.abs(q[off]) ** 2)
    assert measure > 0.8
    # Not trivially so: a pair's spectrum is its partner's (|corr| ≈ 1), not any other pair's (|corr| at the
    # chance level of a few independent frequency samples, ≈ 0.35 on average).
    u = (q / np.linalg.norm(q, axis=2, keepdims=True)).reshape(-1, q.shape[2])
    corr = np.abs(u.conj() @ u.T).reshape(q.shape[:2] * 2)
    i, j = np.nonzero(off)
    partner = corr[i, j, j, i]
    unrelated = corr[i, j][:, i, j]
    unrelated = unrelated[(i[:, None] != i[None]) | (j[:, None] != j[None])]
    assert partner.mean() > 0.8 and np.mean(unrelated) < 0.5


def test_measured_reciprocity_makes_both_orders_symmetric_through_the_transmits_and_keeps_their_envelopes() -> None:
    """With measured_reciprocity (R1–R2, the default) the Gaussian field and the beads' speckle are each symmetric as
    the transmits measure them (without it the beams' independent sidelobes and the speckle's beam model leave a
    few % out), with their time envelopes kept in 2 µs gates from the surface echo on."""

    def gated(m: np.ndarray, bg: DiffuseBackground) -> np.ndarray:
        t = np.fft.ifft(m * np.hanning(m.shape[0] + 2)[1:-1, None, None], n=bg.n_bb, axis=0)
        gate = round(2e-6 / bg.dt)
        e = np.sum(np.abs(t) ** 2, axis=(1, 2))
        return e[: e.size // gate * gate].reshape(-1, gate).sum(axis=1)

    plain, *_ = _small_2d(single_scattering="field", angular="halo", measured_reciprocity=False)
    kept, _, seq, _, win = _small_2d(single_scattering="field", angular="halo")  # the default
    proj = ElementReciprocity(kept.elements, seq.sines, kept.freqs, C0)
    before, after = plain.next_orders(), kept.next_orders()
    for b, a in zip(before, after, strict=True):
        assert b is not None and a is not None
        assert proj.symmetry(b) < 0.99 and proj.symmetry(a) > 0.999
        e_b, e_a = gated(b, plain), gated(a, kept)
        starts = (np.arange(e_b.size) * round(2e-6 / plain.dt) * plain.dt + win.t0) % win.period
        lit = (starts >= 2 * 10e-3 / C0) & (e_b > 1e-2 * e_b.max())
        assert lit.sum() >= 5
        np.testing.assert_allclose(e_a[lit], e_b[lit], rtol=0.1)


@pytest.mark.parametrize("step", [0.06, 0.2])
def test_measured_reciprocity_is_an_orthogonal_projection_that_keeps_reciprocal_data(step: float) -> None:
    """`ElementReciprocity` (R1–R2): after it, S(θ', θ) = Σ_u e^{−ik s_θ'·u} M(u, θ)/c_θ is symmetric; applied twice
    it changes nothing; what it removes is orthogonal (in M/c_θ) to what it keeps; the data of any symmetric
    element-basis matrix K (M = K Φ c_θ) pass unchanged; and it holds for transmits closer than the array
    resolves (step 0.06 against λ/D ≈ 0.2: G nearly singular) as for resolved ones. On white noise it removes
    the antisymmetric share, N_θ(N_θ − 1)/2 of the N_u N_θ dimensions."""
    rng = np.random.default_rng(11)
    xs = (np.arange(12) - 5.5) * 0.3e-3
    el = np.stack(np.meshgrid(xs, xs, indexing="ij"), axis=-1).reshape(-1, 2)
    t = np.arange(-3, 4) * step
    sines = np.stack(np.meshgrid(t, t, indexing="ij"), axis=-1).reshape(-1, 2)
    freqs = np.linspace(1.5e6, 3.0e6, 7)
    proj = ElementReciprocity(el, sines, freqs, C0)
    n_f, n_u, n_t = proj.shape
    m = (rng.standard_normal(proj.shape) + 1j * rng.standard_normal(proj.shape)).astype(np.complex64)
    out = proj(m)
    s_before, s_after = proj.measured(m), proj.measured(out)
    assert np.linalg.norm(s_before - np.swapaxes(s_before, 1, 2)) > 1.3 * np.linalg.norm(s_before)
    assert np.linalg.norm(s_after - np.swapaxes(s_after, 1, 2)) < 1e-4 * np.linalg.norm(s_after)
    assert np.linalg.norm(proj(out) - out) < 1e-5 * np.linalg.norm(out)
    c = cosines(sines)[None, None, :]
    removed, kept = (m - out) / c, out / c
    assert abs(np.vdot(removed, kept)) < 1e-5 * np.linalg.norm(removed) * np.linalg.norm(kept)
    share = np.sum(np.abs(m - out) ** 2) / np.sum(np.abs(m) ** 2)
    assert share == pytest.approx(n_t * (n_t - 1) / 2 / (n_u * n_t), rel=0.1)
    k = 2 * np.pi * freqs / C0
    phi = np.exp(-1j * k[:, None, None] * (el @ sines.T)[None])
    kk = rng.standard_normal((n_f, n_u, n_u)) + 1j * rng.standard_normal((n_f, n_u, n_u))
    data = (np.matmul(kk + np.swapaxes(kk, 1, 2), phi) * c).astype(np.complex64)
    assert np.linalg.norm(proj(data) - data) < 1e-5 * np.linalg.norm(data)
    with pytest.raises(ValueError, match="m: expected shape"):
        proj(m[:, :, :-1])


def test_array_factor_is_the_dirichlet_kernel_and_the_lobe_stops_before_its_null() -> None:
    """B_f(δ) = (1/N) Σ_u e^{ikδu} of a regular line of N elements at pitch p is sin(Nkδp/2)/(N sin(kδp/2))
    (`reciprocity.array_factor`); the main lobe on a grid Δs ends at the last step before the first sampled
    minimum, i.e. below the null λ/(N p Δs) = 2.9 steps: 2 steps."""
    n, pitch, k = 16, 0.68e-3, 2 * np.pi * 1.4e6 / C0
    el = np.zeros((n, 3))
    el[:, 0] = (np.arange(n) - (n - 1) / 2) * pitch
    delta = np.linspace(1e-4, 0.2, 57)
    x = k * delta * pitch
    got = array_factor(el, np.stack([delta, np.zeros_like(delta)], axis=1), np.array([k]))[:, 0]
    np.testing.assert_allclose(got, np.sin(n * x / 2) / (n * np.sin(x / 2)), atol=1e-12)
    ds = 2 * np.pi / (k * n * pitch) / 2.9  # the null at 2.9 steps
    assert main_lobe_steps(el, ds, 0, k) == 2


def test_coherent_backscattering_doubles_the_retro_intensity() -> None:
    """Through the array's receive beams, ⟨|R̃(−a, a)|²⟩ / ⟨|R̃(b, a)|²⟩ ≈ 2 at exact retro-reflection and → 1
    far outside the cone (the reversed paths of the transmit's and the beam's main lobes, `reciprocity`)."""
    retro, far = [], []
    for seed in range(6):
        bg, _, seq, _, _ = _small_2d()
        bg.rng = np.random.default_rng(seed)
        bg._advance()  # the first frame's draws: the noise and the block's
        a = bg.multiple_spectrum() * bg.weights[:, None, None]
        b = np.stack([np.linspace(-0.3, 0.3, 25), np.zeros(25)], axis=1)
        p = np.mean(np.abs(_receive_beams(bg, a, np.arange(bg.n_o), np.concatenate([b, -seq.sines]))) ** 2, axis=2)
        sep = np.abs(b[:, None, 0] + seq.sines[None, :, 0])
        retro.append(np.mean(np.diag(p[b.shape[0] :])))
        far.append(p[: b.shape[0]][sep > 0.25].mean())
    ratio = np.mean(retro) / np.mean(far)
    assert 1.7 < ratio < 2.3


def test_default_sinking_sphere_is_in_the_papers_regime() -> None:
    """Paper conventions by default: centre depths where C_I is the paper's (5.2–5.6 ℓ_s), the focused
    single-scattering speckle, no gain, calibration at (0, 0, 25) mm in water; the paper's stated positions
    (9 and 7 mm) stay reachable."""
    sc = scenario("sinking-sphere", quick=True, n_frames=2)
    lay = sc.layer
    assert lay is not None and lay.gain == 1.0 and lay.attenuation_depth == "centre"
    assert lay.single_scattering == "field"
    depths = [(pl.positions[:, 2] - lay.z_surface) / lay.ls for pl in sc.placements.values()]
    assert min(d.min() for d in depths) >= 5.2 and max(d.max() for d in depths) <= 5.6
    stated = scenario(
        "sinking-sphere", quick=True, n_frames=2, sink=PAPER_POSITIONS[0], sphere2_depth=PAPER_POSITIONS[1]
    )
    assert stated.placements["sphere2"].positions[0, 2] == pytest.approx(lay.z_surface + 7e-3)
    for name in sc.target_names:
        np.testing.assert_allclose(sc.placements[name].calibration_position, [0.0, 0.0, 25e-3])
    legacy = scenario("sinking-sphere", quick=True, n_frames=2, conventions="legacy")
    assert legacy.layer is not None and legacy.layer.gain == 2.5 and legacy.layer.attenuation_depth == "front"


@pytest.mark.parametrize("dim", [2, 3])
def test_side_losses_match_the_walled_diffusions_eigenmodes(dim: int) -> None:
    """A medium of finite width keeps, per lateral axis, the share of a centred Gaussian halo (variance σ² =
    b²/2) that diffusion between absorbing walls at ±X (X = width/2 + z_e) leaves within |x| < a: the image
    series of `side_losses` equals the walls' eigenmode series, (1/X) Σ_{k odd} cos(kπx/2X) e^{−(kπ/2X)² σ²/2}
    integrated over |x| < a, over the free share erf(a/b); an unbounded medium loses nothing."""
    from scipy.special import erf

    ls, width, a = 1.8e-3, 12e-3, 2e-3
    lay = ScatteringLayer(z_surface=5e-3, ls=ls, envelope="diffusion", width=width)
    x_wall = 0.5 * width + lay.diffusion_constants(dim)[1]
    b2 = np.geomspace(1e-8, 4e-4, 40)
    k = np.arange(1, 4001, 2)[:, None]
    q = k * np.pi / (2 * x_wall)
    kept = np.sum((1 / x_wall) * (2 / q) * np.sin(q * a) * np.exp(-(q**2) * b2[None, :] / 4), axis=0)
    ratio = np.clip(kept / erf(a / np.sqrt(b2)), 0, 1) ** (dim - 1)
    got = lay.side_losses(b2, a, dim)
    np.testing.assert_allclose(got, ratio, atol=2e-4)
    assert got[0] == pytest.approx(1.0) and np.all(np.diff(got) <= 1e-12) and got[-1] < 0.5
    free = ScatteringLayer(z_surface=5e-3, ls=ls, envelope="diffusion")
    assert np.all(free.side_losses(b2, a, dim) == 1.0)
    with pytest.raises(ValueError, match="width"):
        ScatteringLayer(z_surface=5e-3, ls=ls, width=0.0)


def test_halo_geometry_times_each_direction_by_its_ray() -> None:
    """HaloGeometry (docs/design.md §6.3): τ solves t = t_spec + u(τ) t_rays + τ; at τ = 0 (u = ½) a direction
    arrives at [z_s(c_θ + c_o) + ½ z_s(s_θ²/c_θ + s_o²/c_o) − ½ z_s (s_θ·s_o)(1/c_θ + 1/c_o)]/c0, which is the
    specular 2 z_s c for s_o = s_θ and the ray's 2 z_s/c for exact retro-reflection s_o = −s_θ, at every age;
    its share of the halo is symmetric under the reciprocal swap (o, θ) ↔ (−θ, −o)."""
    from fpcore.simulate.diffuse import HaloGeometry

    lay = ScatteringLayer(z_surface=5e-3, ls=1.8e-3, envelope="diffusion", cbs=True, angular="halo")
    si = np.array([[0.0, 0.0], [0.3, 0.0], [0.2, -0.1]])
    so = np.concatenate([si, -si, [[0.5, 0.2]]])
    geo = HaloGeometry(lay, so, si, 2e-3, 3, C0)
    t = np.linspace(0.0, 40e-6, 400)
    tau = geo.age(t, lay.ls)
    k, a2 = 4 * lay.ls / 3 * C0, geo.a_g2
    beta = k * np.maximum(tau, 0.0)
    u = (a2 + beta) / (2 * a2 + beta)
    resid = tau + geo.t_spec[:, :, None] + u * geo.t_rays[:, :, None] - t[None, None, :]
    assert np.abs(resid).max() < 1e-9
    c = cosines(si)
    for i in range(si.shape[0]):
        onset = geo.t_spec[i, i] + 0.5 * geo.t_rays[i, i]  # specular: o = i
        assert onset == pytest.approx(2 * lay.z_surface * c[i] / C0, rel=1e-6)
        retro = si.shape[0] + i  # s_o = −s_θ: no dependence on u
        assert geo.t_rays[retro, i] == pytest.approx(0.0, abs=1e-12)
        assert geo.t_spec[retro, i] == pytest.approx(2 * lay.z_surface / c[i] / C0, rel=1e-6)
    share = geo.share(np.full((so.shape[0], si.shape[0], 1), 5e-6, np.float32), lay.ls, 0.01, cbs=True)
    # (o, θ) = (−s_1, s_2) and its partner (−s_2, s_1): rows 3 + 1 and 3 + 2.
    assert share[3 + 1, 2, 0] == pytest.approx(share[3 + 2, 1, 0], rel=1e-5)
    # paired=True computes only the pairs (s_out[n], sines[n]): the same numbers as the full table's entries,
    # with the finite medium's walls too (the reciprocal block's envelopes, `DiffuseBackground`).
    walled = ScatteringLayer(z_surface=5e-3, ls=1.8e-3, envelope="diffusion", cbs=True, angular="halo", width=12e-3)
    o_idx, i_idx = np.array([0, 3, 4, 6, 6]), np.array([0, 0, 2, 1, 2])
    for layer in (lay, walled):
        full = HaloGeometry(layer, so, si, 2e-3, 3, C0)
        pair = HaloGeometry(layer, so[o_idx], si[i_idx], 2e-3, 3, C0, paired=True)
        tau_full, tau_pair = full.age(t, layer.ls), pair.age(t, layer.ls)
        np.testing.assert_allclose(tau_pair[:, 0], tau_full[o_idx, i_idx], rtol=1e-6, atol=1e-12)
        sh_full = full.share(tau_full, layer.ls, 0.01, cbs=True)
        np.testing.assert_allclose(
            pair.share(tau_pair, layer.ls, 0.01, cbs=True)[:, 0], sh_full[o_idx, i_idx], rtol=1e-5
        )
    with pytest.raises(ValueError, match="sines: expected 7 directions"):
        HaloGeometry(lay, so, si, 2e-3, 3, C0, paired=True)


@pytest.mark.parametrize("dim", [2, 3])
def test_first_order_reflectance_is_the_single_scattering_paths_flux(dim: int) -> None:
    """ρ₁(s) = κ_d e^{−s/ℓ_s}/ℓ_s (medium.first_order_reflectance) against a Monte Carlo of first scatterings:
    a normally incident plane wave scatters first at depth z ~ Exp(ℓ_s), isotropically (3D: μ uniform in [−1, 1];
    2D: angle uniform in [0, 2π)); an upward path leaves with weight e^{−z/(ℓ_s μ)} after s = z(1 + 1/μ). The
    histogram of s is ρ₁; the diffusion envelope without its first order is what is left, never negative."""
    from fpcore.simulate.medium import first_order_reflectance

    ls, n = 1.8e-3, 2_000_000
    rng = np.random.default_rng(7)
    z = rng.exponential(ls, n)
    mu = rng.uniform(-1.0, 1.0, n) if dim == 3 else np.sin(rng.uniform(0.0, 2 * np.pi, n))
    up = mu > 1e-9
    z, mu = z[up], mu[up]
    s = z * (1 + 1 / mu)
    w = np.exp(-z / (ls * mu))
    edges = np.linspace(0.0, 4 * ls, 41)
    hist, _ = np.histogram(s, edges, weights=w)
    density = hist / n / np.diff(edges)
    centres = 0.5 * (edges[1:] + edges[:-1])
    exact = [
        float(np.mean(first_order_reflectance(np.linspace(a, b, 201), ls, dim)))
        for a, b in zip(edges[:-1], edges[1:], strict=True)
    ]
    np.testing.assert_allclose(density, exact, rtol=0.03)
    kappa = (1 - np.log(2)) / 2 if dim == 3 else (np.pi - 2) / (2 * np.pi)
    assert w.sum() / n == pytest.approx(kappa, rel=0.01)
    lay = ScatteringLayer(z_surface=5e-3, ls=ls, envelope="diffusion")
    rest = lay.reflectance_density(centres, orders_from=2, dim=dim)
    assert np.all(rest >= 0.0)
    np.testing.assert_allclose(
        rest, np.maximum(lay.reflectance_density(centres, dim=dim) - first_order_reflectance(centres, ls, dim), 0.0)
    )


def test_skipped_restarted_and_cached_backgrounds_give_the_sequential_frames() -> None:
    """`skip` makes the draws of `next` without computing the frame; `restart` and `cached` (tables shared
    with an earlier background of the same rig) start again from a generator: every route gives, bit for
    bit, the frames of a freshly built background run in order — with moving grains and the beads' field."""
    kw = {"single_scattering": "field", "frame_displacement": 2e-6}
    bg, probe, seq, band, win = _small_2d(**kw)
    ref = [bg.next() for _ in range(3)]
    assert not np.allclose(ref[1], ref[2])  # the grains move: frames differ
    again, _, _, _, _ = _small_2d(**kw)
    again.skip()
    again.skip()
    np.testing.assert_array_equal(again.next(), ref[2])
    again.restart(np.random.default_rng(3))
    np.testing.assert_array_equal(again.next(), ref[0])
    args = (bg.layer, probe.positions, seq.sines, win, band, C0, 2, 0.5 * probe.aperture[0])
    first = DiffuseBackground.cached(*args, np.random.default_rng(3))
    second = DiffuseBackground.cached(*args, np.random.default_rng(3))
    assert second.envelopes[0] is first.envelopes[0]  # one set of tables
    np.testing.assert_array_equal(first.next(), ref[0])
    np.testing.assert_array_equal(first.next(), ref[1])
    np.testing.assert_array_equal(second.next(), ref[0])  # its own state, untouched by the first's frames
    # Copies in two threads at once (they share the beads' NUFFT plans behind one lock): the same frames.
    from concurrent.futures import ThreadPoolExecutor

    forks = [DiffuseBackground.cached(*args, np.random.default_rng(3)) for _ in range(2)]
    with ThreadPoolExecutor(2) as pool:
        runs = list(pool.map(lambda b: [b.next() for _ in range(3)], forks))
    for run in runs:
        for got, want in zip(run, ref, strict=True):
            np.testing.assert_array_equal(got, want)


def test_speckle_beam_carries_the_power_of_the_synthesised_plane_wave() -> None:
    """A plane wave synthesised by an N × N aperture D (elements as monopoles of weight 2ik p², the reference's
    transmit) sends a power ∫∫|p|² dx dy through each depth that stays ≈ D² as the beam spreads; the speckle's beam
    (`beam_half_width`, `beam_gain`) carries the same within 25 %, where a flat beam as wide as its spread carried
    (1 + λz/D²)² times it."""
    from fpcore.simulate.paths import Synthesised
    from fpcore.simulate.single_scattering import _edge, beam_gain, beam_half_width

    lam = C0 / 2.2e6
    k, pitch, n = 2 * np.pi / lam, lam / 2, 12
    u = (np.arange(n) - (n - 1) / 2) * pitch
    ex, ey = (a.ravel() for a in np.meshgrid(u, u, indexing="ij"))
    elements = np.stack([ex, ey, np.zeros_like(ex)], axis=1)
    q = Synthesised(np.zeros((1, 2)), pitch).weights(k, elements, 3)[:, 0]  # the reference's transmit weights
    aperture = n * pitch
    for z in (5e-3, 10e-3, 20e-3):
        hw = float(beam_half_width(aperture, z, lam))
        g = np.arange(-(3 * hw + 2e-3), 3 * hw + 2e-3, lam / 5)
        x, y = np.meshgrid(g, g, indexing="ij")
        field = np.zeros(x.shape, complex)
        for a, b, qv in zip(ex, ey, q, strict=True):
            r = np.sqrt((x - a) ** 2 + (y - b) ** 2 + z**2)
            field += np.exp(-1j * k * r) / (4 * np.pi * r) * qv
        exact = np.sum(np.abs(field) ** 2) * (g[1] - g[0]) ** 2
        profile = _edge(g, hw, 0.15 * hw)
        model = (np.sum((profile * beam_gain(aperture, z, lam)) ** 2) * (g[1] - g[0])) ** 2
        flat = (np.sum(profile**2) * (g[1] - g[0])) ** 2
        assert 0.75 < model / exact < 1.05, (z, model / exact)
        assert flat / exact > 1.25  # the flat beam's excess, which this test would catch


def test_a_deep_focal_return_cell_gives_its_green_function_without_the_output_grids_images(monkeypatch) -> None:
    """With the focal return in 3-D the grid reaches deep, and the output grid, coarsened to MAX_DIRECTIONS, repeats
    each source laterally every λ/Δs: a deep cell's images come in at small sines. Each depth chunk is summed over the
    directions its sources reach (`_depth_chunks`, docs/design.md §6.6), so one deep cell lit as at a fixed depth is
    its Born echo t e^{−ik(a·x + c_a z)} G(u, r) at the elements; summed over every direction it is not."""
    lay = _layer(single_scattering="field")
    probe = Probe.matrix(8, 8, 0.34e-3, 2.2e6, 0.8e6)
    si = np.array([[-0.2, 0.0], [0.0, 0.0], [0.15, 0.1]])
    f = np.linspace(1.8e6, 2.6e6, 4)
    ap = (8 * 0.34e-3, 8 * 0.34e-3)
    light = np.full(1, 1e-3)

    def echo_error(depth: float, every_direction: bool) -> float:
        ss = SingleScatteringField(
            lay, si, f, np.ones((1, f.size)), np.array([2.2e6]), C0, 3, ap, 20e-3, np.random.default_rng(0)
        )
        assert ss.axes is not None and ss.keep is not None
        assert C0 / f.max() / ss.ds < 20e-3  # the images are nearer than the cell's range
        lit_at = np.repeat(light, ss.nz)
        ss.add_focal_return(np.ones((1, ss.nz)), None, lit_at)
        if every_direction:
            monkeypatch.setattr(ss, "_depth_chunks", lambda: [(0, ss.nz, np.arange(ss.n_o), None)])
        else:
            assert len(ss._depth_chunks()) > 1
        ss.draw_beads = False
        ss.advance()
        assert ss.fr_state is not None
        ix, iy, iz = ss.nx // 2, ss.ny // 2, int(np.argmin(np.abs(ss.depths - depth)))
        ss.fr_state[:] = 0
        ss.fr_state[ix, iy, iz] = 1.0
        got = project_plane_waves(ss.spectrum(), f, C0, probe.positions, ss.s_out, ss.axes, ss.keep)
        r = np.array([[ss._xs[ix], ss._ys[iy], lay.z_surface + ss.depths[iz]]])
        t = ss._t_r * np.sqrt(ss._cell) * np.ones((1, f.size), dtype=np.complex64)
        ref = radiate_points(r, t, probe.positions, si, f, C0, 3)
        ref = ref * np.array([ss.beam(i, lit_at)[ix, iy, iz] for i in range(si.shape[0])])[None, None, :]
        return float(np.linalg.norm(got - ref) / np.linalg.norm(ref))

    for depth in (10e-3, 17e-3):
        assert echo_error(depth, every_direction=False) < 0.12  # 4–10 %, as a shallow cell on the full grid
        assert echo_error(depth, every_direction=True) > 0.5  # 127–197 %: its images
