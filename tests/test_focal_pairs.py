"""The focal return drawn as two-point paths (`ScatteringLayer(focal_return_pairs=True)`, F6 of docs/design.md §6.6):
the grid's pairing of cells, the pair's field against the two-point path and its reversed partner, and the tables."""

from __future__ import annotations

import numpy as np
import pytest

from fpcore.acquisition import Probe
from fpcore.simulate import paths as P
from fpcore.simulate.diffuse import project_plane_waves
from fpcore.simulate.medium import ScatteringLayer
from fpcore.simulate.reciprocity import ElementReciprocity
from fpcore.simulate.single_scattering import SingleScatteringField, pair_layout, pair_offsets
from fpcore.simulate.waves import radiate_points

C0 = 1500.0


def test_every_cell_is_paired_with_its_partner_and_the_separations_follow_their_shares() -> None:
    """`pair_offsets`: the partner's partner is the cell, inside the grid; a depth whose separations are all 0 pairs
    every cell with itself, one all at 3 steps along x pairs every cell 3 steps away but at the grid's edge; on a
    wide grid the share of cells per separation is the one asked for (the share of the paths' energy), per axis and
    jointly."""
    nx, ny, nz = 300, 200, 32
    q = np.array([0.2, 0.1, 0.3, 0.0, 0.4, 0.0])
    sep = np.zeros((nz, 6, 6))
    sep[0, 0, 0] = 1.0  # all coincident
    sep[1, 0, 3] = 1.0  # 3 steps along x
    sep[2:] = np.outer(q[::-1] / q.sum(), q)  # a mix, separable: one tiling per depth, so the shares hold over depths
    off = pair_offsets((nx, ny, nz), sep, np.random.default_rng(1))
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    for z in range(nz):
        px, py = ix + off[0, :, :, z], iy + off[1, :, :, z]
        assert px.min() >= 0 and px.max() < nx and py.min() >= 0 and py.max() < ny
        np.testing.assert_array_equal(off[0, px, py, z], -off[0, :, :, z])
        np.testing.assert_array_equal(off[1, px, py, z], -off[1, :, :, z])
    assert np.all(off[:, :, :, 0] == 0)
    assert np.all(off[1, :, :, 1] == 0) and np.mean(np.abs(off[0, :, :, 1]) == 3) > 0.98
    for axis, want in ((0, q), (1, q[::-1] / q.sum())):
        got = np.bincount(np.abs(off[axis, :, :, 2:]).ravel(), minlength=6) / (nx * ny * (nz - 2))
        np.testing.assert_allclose(got, want, atol=0.03)
    partner, primary, _, gain = pair_layout(off)
    cells = np.arange(nx * ny * nz)
    np.testing.assert_array_equal(partner[partner], cells)
    np.testing.assert_array_equal(primary, np.minimum(cells, partner))
    assert np.all(gain[:, :, 0] == np.float32(np.sqrt(2.0))) and np.all(gain[:, :, 1] == 1.0)


def test_the_pairs_separations_are_drawn_jointly_not_per_axis() -> None:
    """Paths whose ends lie 4 steps apart along x or along y, never both nor neither: the drawn pairs keep that
    joint law (no cell is its own partner, none 4 steps apart on both axes), where the product of the two marginals
    would put a quarter of the cells at each; the joint shares of a non-separable mix hold within 0.03."""
    nx, ny, nz = 240, 240, 8
    ring = np.zeros((nz, 5, 5))
    ring[:, 0, 4] = ring[:, 4, 0] = 0.5
    off = pair_offsets((nx, ny, nz), ring, np.random.default_rng(2))
    ax, ay = np.abs(off[0]), np.abs(off[1])
    interior = (slice(8, nx - 8), slice(8, ny - 8))  # away from the edges, where tiles shrink
    both = ((ax == 4) & (ay == 4))[interior].mean()
    neither = ((ax == 0) & (ay == 0))[interior].mean()
    assert both == 0.0 and neither < 0.02
    np.testing.assert_allclose(((ax == 4) & (ay == 0))[interior].mean(), 0.5, atol=0.03)
    mix = np.zeros((nz, 3, 3))
    mix[:, 0, 0], mix[:, 0, 2], mix[:, 1, 1], mix[:, 2, 0] = 0.1, 0.3, 0.4, 0.2
    off = pair_offsets((nx, ny, nz), mix, np.random.default_rng(3))
    code = np.abs(off[1]) * 3 + np.abs(off[0])
    got = np.bincount(code.ravel(), minlength=9).reshape(3, 3) / code.size
    np.testing.assert_allclose(got, mix[0], atol=0.03)


def test_a_pair_of_cells_is_the_two_point_path_with_its_reversed_partner() -> None:
    """(F6): a pair of cells with one amplitude is, at the elements, the path received at each end and transmitted
    from the other — t [G(u, r_a) e^{−ik(a·x_b + c z)} b_θ(r_b) + G(u, r_b) e^{−ik(a·x_a + c z)} b_θ(r_a)], each
    transmit lit by its beam at the end it leaves from — and so reciprocal as the array measures it (R1); two points
    at the same cells, each received where it is transmitted, are not the path."""
    lay = ScatteringLayer(z_surface=5e-3, ls=1.8e-3, la=8e-3, single_scattering="field", focal_return=True)
    probe = Probe.matrix(8, 8, 0.34e-3, 2.2e6, 0.8e6)
    s1 = np.array([-0.15, 0.0, 0.15])
    sy, sx = np.meshgrid(s1, s1, indexing="ij")
    si = np.stack([sx.ravel(), sy.ravel()], 1)
    f = np.array([2.2e6])  # one frequency: the pairs' phases are exact at the sub-band's centre
    ap = (8e-3, 8e-3)  # beams wider than the array: both ends in every beam's flat part (the element field's R1)
    ss = SingleScatteringField(lay, si, f, np.ones((1, 1)), f, C0, 3, ap, 6e-3, np.random.default_rng(0))
    assert ss.axes is not None and ss.keep is not None
    light = np.full(ss.nz, 1e-3)
    coincident = np.zeros((ss.nz, 41, 41))
    coincident[:, 0, 0] = 1.0
    ss.add_focal_return(np.ones((1, ss.nz)), None, light, coincident)
    ss.draw_beads = False
    ss.advance()
    assert ss.fr_state is not None
    iz = int(np.argmin(np.abs(ss.depths - 3e-3)))
    a, step = (ss.nx // 2 - 2, ss.ny // 2 - 1), (4, 3)
    b = (a[0] + step[0], a[1] + step[1])
    off = np.zeros((2, ss.nx, ss.ny, ss.nz), dtype=np.int16)
    off[:, a[0], a[1], iz], off[:, b[0], b[1], iz] = step, (-step[0], -step[1])
    ss._pairs = pair_layout(off)
    ss.fr_state[:] = 0
    ss.fr_state[a[0], a[1], iz] = 1.0  # the pair's primary: its partner takes the same amplitude
    got = project_plane_waves(ss.spectrum(), f, C0, probe.positions, ss.s_out, ss.axes, ss.keep)
    z = lay.z_surface + ss.depths[iz]
    r_a, r_b = (np.array([[ss._xs[c[0]], ss._ys[c[1]], z]]) for c in (a, b))
    t = ss._t_r * np.sqrt(ss._cell) * np.ones((1, 1), dtype=np.complex64)
    k = 2 * np.pi * f[0] / C0
    beam_a = np.array([ss.beam(i, light)[a[0], a[1], iz] for i in range(si.shape[0])])
    beam_b = np.array([ss.beam(i, light)[b[0], b[1], iz] for i in range(si.shape[0])])
    shift = np.exp(-1j * k * si @ (r_b[0, :2] - r_a[0, :2]))  # the transmit's phase at b instead of a
    ref = radiate_points(r_a, t, probe.positions, si, f, C0, 3) * (shift * beam_b)[None, None, :]
    ref += radiate_points(r_b, t, probe.positions, si, f, C0, 3) * (np.conj(shift) * beam_a)[None, None, :]
    assert np.linalg.norm(got - ref) / np.linalg.norm(ref) < 0.12  # the grid's own accuracy (a single cell: 4–10 %)
    recip = ElementReciprocity(probe.positions, si, f, C0)
    np.testing.assert_allclose(beam_a, beam_b)
    # as reciprocal as one point is through this small array (R1's figure 0.6 for a point off the axis: the element
    # sums are not the plane waves there), where the reversed term transmitted from the wrong end is not at all
    one = recip.symmetry(radiate_points(r_a, t, probe.positions, si, f, C0, 3))
    wrong = radiate_points(r_a, t, probe.positions, si, f, C0, 3) * np.conj(shift * beam_b)[None, None, :]
    wrong += radiate_points(r_b, t, probe.positions, si, f, C0, 3) * (shift * beam_a)[None, None, :]
    assert recip.symmetry(got) > one - 0.05 and recip.symmetry(ref) > one - 0.05 and recip.symmetry(wrong) < 0.3
    points = radiate_points(np.concatenate([r_a, r_b]), np.repeat(t, 2, 0), probe.positions, si, f, C0, 3)
    assert np.linalg.norm(points * beam_a[None, None, :] - ref) / np.linalg.norm(ref) > 0.5  # two points: not the path


def _path(dx: float) -> P.Paths:
    """One path from (0, 0, 7 mm) to (dx, 0, 7 mm), internal length 1 µm (its apparent depth is its ends')."""
    return P.Paths(3, np.array([[0.0, 0.0, 7e-3]]), np.array([0]), np.array([[dx, 0.0, 7e-3]]),
                   np.array([2], dtype=np.int32), np.array([1e-6]), 1.8e-3, np.array([2e-9]), 1e-6)  # fmt: skip


def test_the_pairs_tables_take_the_paths_intensity_and_leave_its_separation_to_the_grid() -> None:
    """`paths.focal_pairs` (F6): a path whose ends coincide in focus has ν' = ν/2 of (F2′) (D = 1: the grid's pair
    carries the factor 2) and moves all its energy out of the Gaussian field; the same path with its ends 0.6 mm
    apart keeps ν' (the defocus, not the separation) and its separation lands in the histogram's bin 0.6 mm / step."""
    s1 = np.linspace(-0.2, 0.2, 5)
    sy, sx = np.meshgrid(s1, s1, indexing="ij")
    rig = P.FocalRig.from_grid(np.stack([sx.ravel(), sy.ravel()], 1), np.array([1e-3, 1e-3]), 3, None, 0.68e-3)
    assert rig is not None
    depths = np.arange(0, 40) * 0.25e-3
    args = (depths, np.arange(0, 40) * 0.5e-3, np.array([2.2e6]), np.array([1.8e-3]), np.inf, 1500.0)
    tail = (np.array([0.5, 0.5]), np.array([1e-3, 1e-3]), 5e-3, rig)
    var_f2p, _, _ = P.focal_return(_path(0.0), *args, *tail)
    var, kept, light, sep = P.focal_pairs(_path(0.0), *args, *tail, 0.2e-3)
    j = int(np.argmax(var[0]))
    assert depths[j] == pytest.approx(2e-3) and light[j] == pytest.approx(2e-3)
    assert var[0, j] == pytest.approx(var_f2p[0, j] / 2, rel=1e-9)
    assert kept.min() == pytest.approx(0.0, abs=1e-6) and np.sum(kept < 1) == 1
    n = P.PAIR_MAX_STEPS + 1
    assert sep.shape == (depths.size, n, n) and np.allclose(sep.sum(axis=(1, 2)), 1.0)
    var_apart, kept_apart, _, sep_apart = P.focal_pairs(_path(0.6e-3), *args, *tail, 0.2e-3)
    np.testing.assert_allclose(var_apart, var, rtol=1e-9)
    np.testing.assert_allclose(kept_apart, kept, atol=1e-9)
    assert sep_apart[j, 0, 3] == pytest.approx(1.0)  # 3 steps along x, none along y
    with pytest.raises(ValueError, match="spacing"):
        P.focal_pairs(_path(0.0), *args, *tail, 0.0)


def test_the_pairs_option_needs_the_focal_return_and_refuses_the_notch_and_the_excess() -> None:
    base = dict(z_surface=10e-3, ls=1.8e-3, single_scattering="field")
    with pytest.raises(ValueError, match="focal_return_pairs: expected focal_return=True"):
        ScatteringLayer(**base, focal_return_pairs=True)  # type: ignore[arg-type]
    for other in ("confocal_notch", "focal_return_excess"):
        with pytest.raises(ValueError, match="focal_return_pairs: expected confocal_notch=False"):
            ScatteringLayer(**base, focal_return=True, focal_return_pairs=True, **{other: True})  # type: ignore[arg-type]


def test_each_row_pair_of_a_strip_draws_its_own_tiling() -> None:
    """`pair_offsets` (docs/validation.md, tenth session): the rows y and y + m_y of a strip pair with each other and
    share one tiling along x, but the strip's other row pairs draw their own, so that pairs of one separation do not
    lie side by side over the whole strip (a structured reflectivity that made the detector's maps heavier-tailed
    under the surface); the shares of the separations stay the ones asked for."""
    nx, ny, nz = 400, 240, 4
    sep = np.zeros((nz, 4, 4))
    sep[:, 3, 1], sep[:, 3, 3] = 0.5, 0.5  # every path 3 steps along y, 1 or 3 along x
    off = pair_offsets((nx, ny, nz), sep, np.random.default_rng(4))
    interior = slice(8, nx - 8)
    same_pair, other_pairs = [], []
    for z in range(nz):
        for y0 in range(0, ny - 6, 6):  # strips of height 2 m_y = 6
            rows = off[0, interior, y0 : y0 + 6, z]
            same_pair.append(np.array_equal(rows[:, 0], rows[:, 3]))
            other_pairs.append(np.array_equal(rows[:, 0], rows[:, 1]))
    assert all(same_pair) and not any(other_pairs)
    got = np.bincount(np.abs(off[0, interior]).ravel(), minlength=4) / off[0, interior].size
    np.testing.assert_allclose(got[[1, 3]], [0.5, 0.5], atol=0.03)
