"""The transport Monte Carlo of the multiple scattering (fpcore.simulate.paths, docs/design.md §6.6)."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore.simulate import paths as P
from fpcore.simulate.foldy_lax import cross_section, passive_strength
from fpcore.simulate.waves import green


def _walks(dim: int, n: int = 4000, seed: int = 0, **kw: float) -> P.Paths:
    args = dict(l_max=40e-3, z_top=5e-3, start_half_width=2e-3, start_depth=4e-3)
    args.update(kw)
    return P.draw_paths(np.random.default_rng(seed), dim, 1.8e-3, n, **args)  # type: ignore[arg-type]


@pytest.mark.parametrize("dim", [2, 3])
def test_transport_kernel_is_a_probability_density(dim: int) -> None:
    """n|t|²|G(d)|² e^{−d/ℓ_s} integrates to 1 over the plane (2-D) or space (3-D): the walk's exponential step and
    isotropic direction are the ladder's own measure (module doc), for resonant point scatterers of any k."""
    k, ls = 2 * np.pi * 2.2e6 / 1500.0, 1.8e-3
    t = complex(passive_strength(np.zeros(1), k, dim)[0])
    n = 1.0 / (float(cross_section(t, k, dim)) * ls)
    d = np.linspace(1e-9, 40 * ls, 2000001)
    g2 = np.abs(green(k, d, dim)) ** 2  # the exact Green function
    shell = 4 * np.pi * d**2 if dim == 3 else 2 * np.pi * d
    total = np.trapezoid(n * abs(t) ** 2 * g2 * np.exp(-d / ls) * shell, d)
    # 3-D: exact; 2-D: the far-field |G|² = 1/(8πkd) of the walk, 1.8 % above the Hankel function's near field
    assert total == pytest.approx(1.0, rel=0.025 if dim == 2 else 1e-5)


@pytest.mark.parametrize("dim", [2, 3])
def test_walks_take_exponential_isotropic_steps_and_stay_in_the_medium(dim: int) -> None:
    p = _walks(dim, thickness=8e-3, half_width=6e-3)
    assert np.all(np.diff(p.walk) >= 0)
    assert np.all((p.end[:, 2] > 5e-3) & (p.end[:, 2] < 13e-3) & (np.abs(p.end[:, 0]) <= 6e-3))
    assert np.all(p.length <= 40e-3)
    # consecutive events of one walk: orders step by one, the step is the length increment
    same = p.walk[1:] == p.walk[:-1]
    assert np.all(p.order[1:][same] == p.order[:-1][same] + 1)
    steps = np.diff(p.length)[same]
    vec = np.diff(p.end, axis=0)[same]
    np.testing.assert_allclose(np.linalg.norm(vec, axis=1), steps, rtol=1e-9)
    # unbiased only in an unbounded medium: there, mean step ℓ_s and isotropic directions
    q = _walks(dim, n=20000, thickness=np.inf, start_depth=0.5, l_max=4e-3, z_top=-1.0)
    first = q.order == 2
    d = q.end[first] - q.start[q.walk[first]]
    r = np.linalg.norm(d, axis=1)
    sel = q.length[first] < 4e-3  # the cut at l_max: compare with the truncated exponential's mean
    trunc = 1.8e-3 - 4e-3 * np.exp(-4 / 1.8) / (1 - np.exp(-4 / 1.8))
    assert r[sel].mean() == pytest.approx(trunc, rel=0.03)
    cos_z = d[:, 2] / r
    assert abs(cos_z.mean()) < 0.03
    assert (cos_z**2).mean() == pytest.approx(1 / 3 if dim == 3 else 1 / 2, abs=0.02)


def test_start_density_is_the_importance_weight() -> None:
    """With start_decay, 1/(N_w π₁) integrates the same as uniform starts: Σ start_weight = the start volume."""
    vol = (4e-3) ** 2 * 4e-3
    for decay in (None, 1.5e-3):
        p = _walks(3, n=20000, start_decay=decay)  # type: ignore[arg-type]
        assert p.start_weight.sum() == pytest.approx(vol, rel=0.05 if decay else 1e-9)


def _rig(dim: int) -> tuple[P.StraightRays, P.Synthesised, np.ndarray, np.ndarray]:
    n = 4
    x = (np.arange(n) - 1.5) * 0.34e-3
    el = np.stack([x, np.zeros(n), np.zeros(n)], axis=1)
    sines = np.stack([np.array([-0.3, -0.1, 0.1, 0.3]), np.zeros(4)], axis=1)
    freqs = np.linspace(2.0e6, 2.4e6, 9)
    ls = np.full(freqs.size, 1.8e-3)
    return P.StraightRays(el, 5e-3, dim), P.Synthesised(sines, 0.34e-3), freqs, ls


@pytest.mark.parametrize("dim", [2, 3])
def test_the_field_is_reciprocal(dim: int) -> None:
    """K(u, v) = K(v, u) in the element basis (each path with its reversed partner, module doc): recovered from
    the synthesised transmits R = K q through the invertible weights q."""
    rays, tx, freqs, ls = _rig(dim)
    p = _walks(dim, n=300, thickness=6e-3, half_width=5e-3)
    r = P.path_spectra(p, freqs, 1500.0, ls, rays, tx)
    for m in (0, 4, 8):
        k = 2 * np.pi * freqs[m] / 1500.0
        kk = r[m] @ np.linalg.inv(tx.weights(k, rays.receivers, dim).astype(np.complex128))
        assert np.abs(kk - kk.T).max() < 1e-4 * np.abs(kk).max()


def test_compiled_sums_equal_the_direct_evaluation() -> None:
    rays, tx, freqs, ls = _rig(3)
    freqs = np.linspace(2.0e6, 2.4e6, 33)
    ls = 1.8e-3 * (freqs / 2.2e6) ** 2
    p = _walks(3, n=120, thickness=6e-3, half_width=5e-3)
    fast = P.path_spectra(p, freqs, 1500.0, ls, rays, tx, la=8e-3)
    saved, P.nb = P.nb, None
    try:
        slow = P.path_spectra(p, freqs, 1500.0, ls, rays, tx, la=8e-3)
    finally:
        P.nb = saved
    assert np.abs(fast - slow).max() < 1e-2 * np.abs(slow).max()


def test_first_order_is_the_born_intensity_of_the_medium() -> None:
    """The walks' starts as single scatterers (weight n|t|²/(N_w π₁)) give on average the first order's intensity
    ∫ n|t|² |G_c(u, r)|² |G_c(r, u)|² d³r over the start box, source and receiver one element, by quadrature."""
    el = np.array([[0.0, 0.0, 0.0]])
    rays = P.StraightRays(el, 5e-3, 3)
    freqs = np.array([2.2e6])
    k = 2 * np.pi * 2.2e6 / 1500.0
    ls = 1.8e-3

    class Point(P.Synthesised):
        def weights(self, k: float, receivers: np.ndarray, dim: int) -> np.ndarray:
            return np.ones((1, 1), dtype=np.complex64)  # the element itself as the source: I = G_c(r, v)

    tx = Point(np.zeros((1, 2)), 1.0)
    acc = []
    for seed in range(40):
        p = _walks(3, n=400, seed=seed, l_max=1e-4)
        acc.append(np.abs(P.path_spectra(p, freqs, 1500.0, ls, rays, tx, la=np.inf, first_order=True)[0, 0, 0]) ** 2)
    # quadrature over the start box |x|, |y| ≤ 2 mm, 5 ≤ z ≤ 9 mm, with the legs' own extinction e^{−d_b/ℓ_s}
    g = np.linspace(-2e-3, 2e-3, 41)
    z = np.linspace(5e-3, 9e-3, 41)
    xx, yy, zz = np.meshgrid(g, g, z, indexing="ij")
    d = np.sqrt(xx**2 + yy**2 + zz**2)
    below = d * (zz - 5e-3) / zz
    integrand = (4 * np.pi / ls) * (np.abs(green(k, d, 3)) ** 2 * np.exp(-below / ls)) ** 2
    exact = np.trapezoid(np.trapezoid(np.trapezoid(integrand, z, axis=2), g, axis=1), g, axis=0)
    assert np.mean(acc) == pytest.approx(exact, rel=0.1)


def test_bad_arguments_name_the_field() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="dim"):
        P.draw_paths(rng, 4, 1e-3, 10, 1e-2, 0.0, 1e-3, 1e-3)
    with pytest.raises(ValueError, match="ls_ref"):
        P.draw_paths(rng, 3, 0.0, 10, 1e-2, 0.0, 1e-3, 1e-3)
    with pytest.raises(ValueError, match="start_depth"):
        P.draw_paths(rng, 3, 1e-3, 10, 1e-2, 0.0, 1e-3, 2e-3, thickness=1e-3)
    with pytest.raises(ValueError, match="n_walks"):
        P.draw_paths(rng, 3, 1e-3, 0, 1e-2, 0.0, 1e-3, 1e-3)


def test_focal_overlap_counts_a_point_twice_and_separated_ends_not() -> None:
    a_t, a_r = np.array([0.7e-3, 0.7e-3]), np.full((4, 2), 0.9e-3)
    d = np.array([[0.0, 0.0], [0.3e-3, 0.0], [1e-3, 1e-3], [6e-3, 0.0]])
    w = P.focal_overlap(d, a_t, a_r)
    assert w[0] == pytest.approx(2.0)
    assert np.all(np.diff(w) < 0) and w[-1] < 1e-10


def test_defocus_lowers_the_focal_overlap() -> None:
    """Eq. F2: ends off the focal plane by Δz see wider, weaker foci (Gaussian beams, z_R = k a²): W is 2 at Δz = 0
    and falls monotonically with Δz, as 1/Δz² in 3-D far out of focus (one factor ∝ 1/Δz per lateral axis)."""
    k = 2 * np.pi / 0.68e-3
    a_t, a_r = np.array([0.7e-3, 0.7e-3]), np.full((4, 2), 0.9e-3)
    d = np.zeros((4, 2))
    dz = np.array([0.0, 2e-3, 5e-3, 20e-3])
    w = P.focal_overlap(d, a_t, a_r, dz, dz, k)
    assert w[0] == pytest.approx(2.0)
    assert np.all(np.diff(w) < 0)
    far = P.focal_overlap(d[:2], a_t, a_r[:2], np.array([40e-3, 80e-3]), np.array([40e-3, 80e-3]), k)
    assert far[0] / far[1] == pytest.approx(4.0, rel=0.05)


def _one_path(delta_x: float) -> P.Paths:
    return P.Paths(
        dim=3,
        start=np.array([[0.0, 0.0, 6e-3]]),
        walk=np.array([0]),
        end=np.array([[delta_x, 0.0, 7e-3]]),
        order=np.array([2], dtype=np.int32),
        length=np.array([3e-3]),
        ls_ref=1.8e-3,
        start_weight=np.array([2e-9]),
        start_area=1e-6,
    )


def test_focal_return_of_one_path_is_twice_its_intensity_at_its_apparent_depth() -> None:
    """Eq. F1: a path whose ends coincide laterally scatters like a point at d = (d₁ + d_n + L)/2 with twice its
    intensity |A|² = n|t|² sw w e^{−(d₁ + d_n)/ℓ_ext}, per unit area and depth; ends far apart, not at all."""
    depths = np.arange(0, 40) * 0.25e-3
    ls, la = 1.8e-3, 8e-3
    # foci wide enough (a_t ≈ 7 mm, a_r ≈ 3 mm) that the ends' 1–2 mm of defocus do not matter (< 0.1 %)
    ages = np.arange(0, 40) * 0.5e-3
    args = (
        depths,
        ages,
        np.array([2.2e6]),
        np.array([ls]),
        la,
        1500.0,
        np.array([0.05] * 2),
        np.array([1e-3] * 2),
        5e-3,
    )
    v = P.focal_return(_one_path(0.0), *args)[0][0]
    d1, dn, length = 1e-3, 2e-3, 3e-3
    j = int(np.argmax(v))
    assert depths[j] == pytest.approx((d1 + dn + length) / 2)
    lext = 1 / (1 / ls + 1 / la)
    q_in, q_out = 1 + 2 * 0.05**2 / 24, 1 + 2 * 1e-3**2 / 24 / (5e-3 + dn) ** 2  # the legs' mean obliquity
    expected = 2 * (4 * np.pi / ls) * (2e-9 / 1e-6) * np.exp(-length / la - (q_in * d1 + q_out * dn) / lext) / 0.25e-3
    assert v[j] == pytest.approx(expected, rel=2e-3)
    assert v.sum() == pytest.approx(v[j])
    # F3: its energy moved from the Gaussian field at its length d₁ + L + d_n (all of it: W = 2), none apart
    kept = P.focal_return(_one_path(0.0), *args)[1][0]
    assert kept[int(np.argmin(np.abs(ages - (d1 + dn + length))))] == pytest.approx(0.0, abs=2e-3)
    assert np.sum(kept < 1) == 1
    far_var, far_kept, _ = P.focal_return(_one_path(80e-3), *args)
    assert far_var.max() < 1e-8 * expected and np.all(far_kept > 1 - 1e-8)


def test_the_focal_return_option_is_refused_without_the_beads_grid_or_a_focus() -> None:
    from fpcore.acquisition import PlaneWaveSequence, Probe
    from fpcore.simulate.diffuse import DiffuseBackground
    from fpcore.simulate.medium import ScatteringLayer
    from fpcore.simulate.waves import Band, TimeWindow

    with pytest.raises(ValueError, match="focal_return"):
        ScatteringLayer(z_surface=10e-3, ls=1.8e-3, focal_return=True)  # single_scattering="envelope"
    with pytest.raises(ValueError, match="focal_return_shallow: expected focal_return=True"):
        ScatteringLayer(z_surface=10e-3, ls=1.8e-3, single_scattering="field", focal_return_shallow=True)
    with pytest.raises(ValueError, match="focal_return_excess: expected focal_return=True"):
        ScatteringLayer(z_surface=10e-3, ls=1.8e-3, single_scattering="field", focal_return_excess=True)
    with pytest.raises(ValueError, match="focal_return_excess: expected confocal_notch=False"):
        ScatteringLayer(
            z_surface=10e-3,
            ls=1.8e-3,
            single_scattering="field",
            focal_return=True,
            confocal_notch=True,
            focal_return_excess=True,
        )
    probe = Probe.linear(16, 0.34e-3, 2.2e6, 0.8e6)
    lay = ScatteringLayer(z_surface=10e-3, ls=1.8e-3, la=8e-3, single_scattering="field", focal_return=True)
    win = TimeWindow.covering(10.4e6, 16e-6, 30e-6, guard=10e-6)
    one = PlaneWaveSequence.uniform_sines(1, 0.0)
    with pytest.raises(ValueError, match="focal_return: expected at least 2 transmits"):
        DiffuseBackground(
            lay, probe.positions, one.sines, win, Band(1.8e6, 2.6e6), 1500.0, 2, 2.7e-3, np.random.default_rng(0)
        )


def test_the_focal_return_draws_its_variance_and_takes_its_energy_from_the_gaussian_field() -> None:
    """docs/design.md §6.6: with focal_return the beads' grid carries a second, non-negative variance profile down to
    the record's end (a table of the rig: equal for two backgrounds), the Gaussian field's envelopes are lowered by
    the kept share κ ∈ [0, 1] (F3), and the frames' two orders come out finite."""
    from fpcore.acquisition import PlaneWaveSequence, Probe
    from fpcore.simulate.diffuse import DiffuseBackground
    from fpcore.simulate.medium import ScatteringLayer
    from fpcore.simulate.waves import Band, TimeWindow

    probe = Probe.linear(32, 0.34e-3, 2.2e6, 0.8e6)
    seq = PlaneWaveSequence.uniform_sines(7, 0.2)
    win = TimeWindow.covering(10.4e6, 14e-6, 30e-6, guard=10e-6)
    band = Band(1.8e6, 2.6e6)

    def build(fr: bool, shallow: bool = False, excess: bool = False) -> DiffuseBackground:
        lay = ScatteringLayer(
            z_surface=10e-3,
            ls=1.8e-3,
            la=8e-3,
            envelope="diffusion",
            single_scattering="field",
            focal_return=fr,
            focal_return_shallow=shallow,
            focal_return_excess=excess,
        )
        return DiffuseBackground(
            lay, probe.positions, seq.sines, win, band, 1500.0, 2, 0.5 * probe.aperture[0], np.random.default_rng(5)
        )

    plain, with_fr, again = build(False), build(True), build(True)
    ss = with_fr.single
    assert ss is not None and ss._fr_var is not None and with_fr._fr_kept is not None
    assert np.all(ss._fr_var >= 0) and ss._fr_var.max() > 0
    assert ss.depths[-1] >= 0.5 * 1500.0 * 30e-6 - 10e-3 - ss.hz  # the record's end (30 µs)
    np.testing.assert_array_equal(ss._fr_var, again.single._fr_var)  # type: ignore[union-attr]
    kept = with_fr._fr_kept[1]
    assert np.all((kept >= 0) & (kept <= 1)) and kept.min() < 0.99
    e_plain = sum(float(np.sum(e**2)) for e in plain.envelopes)
    e_fr = sum(float(np.sum(e**2)) for e in with_fr.envelopes)
    assert e_fr < e_plain
    multiple, single = with_fr.next_orders()
    assert single is not None and np.all(np.isfinite(multiple)) and np.all(np.isfinite(single))
    # focal_return_shallow: the focal return on the beads' own grid only (its depths as without a focal return), the
    # Gaussian field keeping the deeper paths' energy (more than with the whole record's grid, less than without)
    shallow = build(True, shallow=True)
    assert shallow.single is not None and plain.single is not None and shallow.single._fr_var is not None
    assert shallow.single.nz == plain.single.nz < ss.nz and shallow.single._fr_var.max() > 0
    e_shallow = sum(float(np.sum(e**2)) for e in shallow.envelopes)
    assert e_fr < e_shallow < e_plain
    # focal_return_excess (F5): on the same grid, only the share e ∈ [0, 1] of the focal return that the Gaussian field
    # does not already carry at the foci — all of it just under the surface, where the field is faint — and the
    # field keeps the rest of its energy (between the shallow focal return's and none)
    excess = build(True, excess=True)
    assert excess.single is not None and excess.single._fr_var is not None and shallow.single._fr_var is not None
    assert excess.single.nz == shallow.single.nz
    full_var = shallow.single._fr_var
    assert np.all(excess.single._fr_var <= full_var * (1 + 1e-12))
    top = full_var[:, :3] > 0
    np.testing.assert_allclose(excess.single._fr_var[:, :3][top], full_var[:, :3][top], rtol=0.2)
    e_excess = sum(float(np.sum(e**2)) for e in excess.envelopes)
    assert e_shallow <= e_excess <= e_plain
    multiple, single = excess.next_orders()
    assert single is not None and np.all(np.isfinite(multiple)) and np.all(np.isfinite(single))


def test_without_the_beads_the_grid_carries_the_focal_return_alone() -> None:
    """`SingleScatteringField.draw_beads = False` (bench/transport_paths.py --focal-split): the same draws, the beads'
    reflectivity zero, so the beads' field and the focal return alone add up to the whole grid's field, and a grid
    without a focal return gives nothing."""
    from fpcore.acquisition import PlaneWaveSequence, Probe
    from fpcore.simulate.diffuse import DiffuseBackground
    from fpcore.simulate.medium import ScatteringLayer
    from fpcore.simulate.waves import Band, TimeWindow

    probe = Probe.linear(32, 0.34e-3, 2.2e6, 0.8e6)
    seq = PlaneWaveSequence.uniform_sines(7, 0.2)
    win = TimeWindow.covering(10.4e6, 14e-6, 30e-6, guard=10e-6)

    def single(fr: bool, beads: bool, focal: bool = True) -> np.ndarray:
        lay = ScatteringLayer(
            z_surface=10e-3, ls=1.8e-3, la=8e-3, envelope="diffusion", single_scattering="field", focal_return=fr
        )
        bg = DiffuseBackground(
            lay, probe.positions, seq.sines, win, Band(1.8e6, 2.6e6), 1500.0, 2, 0.5 * probe.aperture[0],
            np.random.default_rng(5),
        )  # fmt: skip
        ss = bg.single
        assert ss is not None
        ss.draw_beads = beads
        if fr and not focal:
            ss._fr_var = np.zeros_like(ss._fr_var)
        return ss.spectrum()

    whole, alone, beads = single(True, True), single(True, False), single(True, True, focal=False)
    assert np.abs(alone).max() > 0.05 * np.abs(whole).max()
    np.testing.assert_allclose(beads + alone, whole, rtol=0, atol=1e-4 * np.abs(whole).max())
    assert not np.any(single(False, False))
    # the depths at which the focal return is lit: one per grid depth
    lay = ScatteringLayer(z_surface=10e-3, ls=1.8e-3, la=8e-3, single_scattering="field", focal_return=True)
    bg = DiffuseBackground(
        lay, probe.positions, seq.sines, win, Band(1.8e6, 2.6e6), 1500.0, 2, 0.5 * probe.aperture[0],
        np.random.default_rng(5),
    )  # fmt: skip
    assert bg.single is not None and bg.single._fr_light is not None
    assert bg.single._fr_light.shape == (bg.single.nz,)
    with pytest.raises(ValueError, match="light: expected a depth per grid depth"):
        bg.single.add_focal_return(bg.single._fr_var, None, np.zeros(3))
    # scaling it (focal_return_excess): per depth, non-negative, and the next spectrum takes it
    before = bg.single.spectrum()
    with pytest.raises(ValueError, match="factor: expected finite, non-negative"):
        bg.single.scale_focal_return(np.full(bg.single.nz, -1.0))
    assert bg.single.state is not None
    bg.single.state[...] = 0  # the beads' reflectivity zero: the focal return alone
    bg.single.scale_focal_return(np.zeros(bg.single.nz))
    assert np.abs(before).max() > 0 and not np.any(bg.single.spectrum())


def _exact_confocal_ratio(
    first: np.ndarray, last: np.ndarray, length: float, beams: bool
) -> tuple[float, float, P.FocalRig]:
    """The confocal return of one path (ends `first`, `last`, internal length `length`) over that of a point on the
    axis at its apparent range, both by the direct sum — the paths' field at the elements (`path_spectra`, the
    transmits as `PlaneWaveBeams`) delay-and-summed at the focus over a lateral patch, energy per frequency — and
    the band-averaged W′ of `discrete_focal_overlap` with the same weights: a small 8 × 8 rig, 5 × 5 sines."""
    c0, zs, pitch = 1500.0, 10e-3, 0.68e-3
    x = (np.arange(8) - 3.5) * pitch
    yy, xx = np.meshgrid(x, x, indexing="ij")
    el = np.stack([xx.ravel(), yy.ravel(), np.zeros(64)], axis=1)
    s1 = np.linspace(-0.2, 0.2, 5)
    sy, sx = np.meshgrid(s1, s1, indexing="ij")
    sines = np.stack([sx.ravel(), sy.ravel()], axis=1)
    aperture = 8 * pitch
    lam_c = c0 / 2.2e6
    freqs = np.linspace(1.8e6, 2.6e6, 9)
    rays = P.StraightRays(el, zs, 3)
    tx = P.PlaneWaveBeams(sines, aperture if beams else 1.0, zs, lam_c)
    r_app = 0.5 * (first[2] + last[2] + length)
    centre = np.array([0.0, 0.0, r_app])

    def field(a: np.ndarray, b: np.ndarray, ell: float, first_order: bool) -> np.ndarray:
        one = P.Paths(3, a[None], np.array([0]), b[None], np.array([2], dtype=np.int32), np.array([ell]), 1e6,
                      np.array([1.0]), 1.0)  # fmt: skip
        return P.path_spectra(one, freqs, c0, np.full(freqs.size, 1e6), rays, tx, first_order=first_order)

    g = np.linspace(-6e-3, 6e-3, 41)
    py, px = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([px.ravel(), py.ravel(), np.full(px.size, r_app)], axis=1)
    d_out = np.linalg.norm(pts[:, None, :] - el[None], axis=2)
    d_in = pts[:, :2] @ sines.T + r_app * np.sqrt(1 - (sines**2).sum(1))[None]
    k = 2 * np.pi * freqs / c0

    def energy(v: np.ndarray) -> np.ndarray:
        focused = [np.sum((np.exp(1j * k[m] * d_out) @ v[m]) * np.exp(1j * k[m] * d_in), 1) for m in range(k.size)]
        return np.sum(np.abs(np.array(focused)) ** 2, axis=1)

    e_path, e_point = energy(field(first, last, length, False)), energy(field(centre, centre, 0.0, True))
    rig = P.FocalRig.from_grid(sines, np.array([aperture] * 2), 3, np.array([aperture] * 2) if beams else None, lam_c)
    assert rig is not None
    w = np.array([P.discrete_focal_overlap(first[None], last[None], np.array([r_app]), kk, rig)[0] for kk in k])
    return float(e_path.sum() / e_point.sum()), float(np.sum(w * e_point) / e_point.sum()), rig


@pytest.mark.parametrize(
    ("first", "last", "length", "beams", "tol"),
    [
        ((0.0, 0.0, 14e-3), (0.0, 0.0, 14e-3), 1e-9, True, 0.02),  # a point: W = 2
        ((0.0, 0.0, 12e-3), (0.0, 0.0, 12e-3), 16e-3, False, 0.15),  # a loop seen 8 mm deeper (defocus, spreading)
        ((0.0, 0.0, 12e-3), (0.0, 0.0, 12e-3), 16e-3, True, 0.15),  # the same, the steered beams walked off at depth
        ((-3.4e-3, 0.0, 14e-3), (3.4e-3, 0.0, 14e-3), 6.8e-3, False, 0.25),  # ends λ/Δs apart: a grating lobe each
    ],
)
def test_the_discrete_focal_overlap_is_the_direct_sums_confocal_return(
    first: tuple, last: tuple, length: float, beams: bool, tol: float
) -> None:
    """Eq. F2′ (docs/design.md §6.6) against the direct sum, per path: the confocal return of the path's field over
    that of a point on the axis at its apparent range — where (F2) misses the ends' spreading and the beams' walk-off
    (the loop) and the transmits' grating lobes (ends λ/Δs apart, where F2 is ≈ 0)."""
    exact, w, rig = _exact_confocal_ratio(np.array(first), np.array(last), length, beams)
    assert w == pytest.approx(exact, rel=tol)
    if first == last and length > 1e-6 and beams:  # the walk-off brightens the loop over the unbounded waves'
        assert w > 1.5 * _exact_confocal_ratio(np.array(first), np.array(last), length, False)[1]


def test_the_discrete_focal_overlap_needs_a_grid_of_transmits() -> None:
    """`FocalRig.from_grid`: a full grid of sines along the lateral axes gives the rig (eq. F2′ separates along the
    axes), anything else None."""
    s1 = np.linspace(-0.2, 0.2, 3)
    sy, sx = np.meshgrid(s1, s1, indexing="ij")
    grid = np.stack([sx.ravel(), sy.ravel()], axis=1)
    rig = P.FocalRig.from_grid(grid, np.array([5e-3, 5e-3]), 3, None, 0.68e-3)
    assert rig is not None and [u.size for u in rig.sines] == [3, 3]
    assert P.FocalRig.from_grid(grid[:-1], np.array([5e-3, 5e-3]), 3, None, 0.68e-3) is None
    line = np.stack([s1, np.zeros(3)], axis=1)
    assert P.FocalRig.from_grid(line, np.array([5e-3]), 2, None, 0.68e-3) is not None


def test_with_the_rigs_foci_the_focal_return_is_lit_at_its_ends_depth() -> None:
    """`focal_return` with a `FocalRig` (docs/design.md §6.6, F2′): a path's cell is lit at the mean depth of its
    ends (not at its apparent depth), its variance takes W′ — 2 × its intensity for a point-like path in focus, as (F1)
    with (F2) — and no other cell has any."""
    path = P.Paths(3, np.array([[0.0, 0.0, 7e-3]]), np.array([0]), np.array([[0.0, 0.0, 7e-3]]),
                   np.array([2], dtype=np.int32), np.array([1e-6]), 1.8e-3, np.array([2e-9]), 1e-6)  # fmt: skip
    depths = np.arange(0, 40) * 0.25e-3
    s1 = np.linspace(-0.2, 0.2, 5)
    sy, sx = np.meshgrid(s1, s1, indexing="ij")
    rig = P.FocalRig.from_grid(np.stack([sx.ravel(), sy.ravel()], 1), np.array([1e-3, 1e-3]), 3, None, 0.68e-3)
    args = (depths, np.arange(0, 40) * 0.5e-3, np.array([2.2e6]), np.array([1.8e-3]), np.inf, 1500.0)
    var_f2, _, none = P.focal_return(path, *args, np.array([0.5, 0.5]), np.array([1e-3, 1e-3]), 5e-3)
    var, _, light = P.focal_return(path, *args, np.array([0.5, 0.5]), np.array([1e-3, 1e-3]), 5e-3, rig)
    assert none is None and light is not None
    j = int(np.argmax(var[0]))
    assert depths[j] == pytest.approx(2e-3) and light[j] == pytest.approx(2e-3)
    assert np.count_nonzero(var[0]) == 1
    assert var[0, j] == pytest.approx(var_f2[0, j], rel=1e-3)  # both per unit area of first scatterings


def test_the_rigs_focal_return_of_a_path_does_not_depend_on_where_it_lies_laterally() -> None:
    """(F2′) in a medium invariant across: a path and the same path 2 mm and 1 mm off the axis give the same variance,
    though the steered beams light the two differently — the grid lights the focal return where it lies, so W′ takes
    each path centred on the axis (docs/design.md §6.6; taken as it lay, the beams darkened an off-axis path twice)."""

    def path(dx: float, dy: float) -> P.Paths:
        first, last = np.array([[dx, dy, 7e-3]]), np.array([[dx + 0.5e-3, dy, 7.5e-3]])
        return P.Paths(3, first, np.array([0]), last, np.array([2], dtype=np.int32), np.array([2e-3]), 1.8e-3,
                       np.array([2e-9]), 1e-4)  # fmt: skip

    s1 = np.linspace(-0.2, 0.2, 5)
    sy, sx = np.meshgrid(s1, s1, indexing="ij")
    sines = np.stack([sx.ravel(), sy.ravel()], 1)
    rig = P.FocalRig.from_grid(sines, np.array([5e-3, 5e-3]), 3, np.array([5e-3, 5e-3]), 0.68e-3)  # finite beams
    assert rig is not None
    args = (np.arange(0, 40) * 0.25e-3, np.arange(0, 40) * 0.5e-3, np.array([2.2e6]), np.array([1.8e-3]), np.inf)
    tail = (1500.0, np.array([0.5, 0.5]), np.array([5e-3, 5e-3]), 5e-3, rig)
    var_axis, kept_axis, light_axis = P.focal_return(path(0.0, 0.0), *args, *tail)
    var_off, kept_off, light_off = P.focal_return(path(2e-3, 1e-3), *args, *tail)
    assert var_axis.max() > 0
    np.testing.assert_allclose(var_off, var_axis, rtol=1e-9)
    np.testing.assert_allclose(kept_off, kept_axis, rtol=1e-12)
    assert light_axis is not None and light_off is not None
    np.testing.assert_allclose(light_off, light_axis)


def test_the_compiled_overlap_integral_is_the_tables(monkeypatch) -> None:
    """`_overlap_integral` summed by the compiled rows (the pairs of transmits gathered by their difference, one
    exponential per difference) equals the NumPy tables it replaces, for unequal transmits and receives."""
    rng = np.random.default_rng(5)
    n, s = 3000, np.array([-0.2, -0.1, 0.0, 0.1, 0.2])
    w_f = rng.standard_normal((n, s.size)) + 1j * rng.standard_normal((n, s.size))
    w_g = rng.standard_normal((n, s.size)) + 1j * rng.standard_normal((n, s.size))
    k, r_end = 9.2e3, rng.uniform(15e-3, 30e-3, n)
    rx_f = P._receive(rng.uniform(-2e-3, 2e-3, n), r_end, np.full(n, 22e-3), k, 1e-3)
    rx_g = P._receive(rng.uniform(-2e-3, 2e-3, n), r_end + 1e-3, np.full(n, 22e-3), k, 1e-3)
    pairs = P._pair_differences(s)
    compiled = P._overlap_integral(w_f, rx_f, w_g, rx_g, k, pairs)
    monkeypatch.setattr(P, "nb", None)
    tables = P._overlap_integral(w_f, rx_f, w_g, rx_g, k, pairs)
    assert np.abs(compiled - tables).max() < 1e-9 * np.abs(tables).max()


def test_a_path_beyond_the_grid_keeps_its_energy_in_the_gaussian_field() -> None:
    """(F3) moves a path's point-like share out of the Gaussian field only where the grid draws its focal return: a
    path whose apparent depth lies below the grid's last depth (a grid cut at the beads' depth, `focal_return_shallow`)
    leaves ν empty and κ = 1 at its length, so its energy is not lost."""
    ls = 1.8e-3
    args = (np.array([2.2e6]), np.array([ls]), 8e-3, 1500.0, np.array([0.05] * 2), np.array([1e-3] * 2), 5e-3)
    ages = np.arange(0, 40) * 0.5e-3
    deep_var, deep_kept, _ = P.focal_return(_one_path(0.0), np.arange(0, 40) * 0.25e-3, ages, *args)
    assert deep_var.max() > 0 and deep_kept.min() < 0.01  # drawn: its share moved (test above)
    cut_var, cut_kept, _ = P.focal_return(_one_path(0.0), np.arange(0, 8) * 0.25e-3, ages, *args)  # to 1.75 mm < 3 mm
    assert cut_var.max() == 0 and np.all(cut_kept == 1)
