"""The union of the unweighted and time-weighted statistics (docs/design.md §4.14, eq. W2): its PFA stays
calibrated whatever the maps' dependence, and it keeps a target that the weighting loses."""

from __future__ import annotations

import numpy as np
import pytest

import fpcore
from fpcore import locate_union, union_pfa
from fpcore.locate import union_null, union_of


@pytest.mark.parametrize("dependence", ["identical", "independent", "antithetic"])
@pytest.mark.parametrize("alpha", [0.05, 0.01])
def test_the_union_pfa_is_calibrated_whatever_the_dependence(dependence: str, alpha: float) -> None:
    """Two calibrated PFAs (uniform under the null), the most significant taken with eq. (W2): the rate below α is
    α/2 for identical maps, α − α²/4 for independent ones and α exactly for antithetic ones (p₁ = 1 − p₀), the
    Bonferroni bound's worst case; never above α."""
    rng = np.random.default_rng(7)
    p0 = rng.uniform(size=100_000)
    p1 = {"identical": p0, "independent": rng.uniform(size=p0.size), "antithetic": 1.0 - p0}[dependence]
    union = np.array([union_pfa(min(a, b), 2) for a, b in zip(p0, p1, strict=True)])
    expected = {"identical": alpha / 2, "independent": alpha - alpha**2 / 4, "antithetic": alpha}[dependence]
    rate = float(np.mean(union < alpha))
    sigma = np.sqrt(expected * (1 - expected) / p0.size)
    assert abs(rate - expected) < 5 * sigma
    assert rate < alpha + 5 * sigma


def test_bad_pfas_are_refused() -> None:
    with pytest.raises(ValueError, match="pfa: expected a probability"):
        union_pfa(1.5, 2)
    with pytest.raises(ValueError, match="n_maps: expected at least 1"):
        union_pfa(0.1, 0)
    with pytest.raises(ValueError, match="imagers: expected one or more"):
        locate_union([], None, None)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="found: expected one or more"):
        union_of([])


def test_the_union_keeps_a_marker_that_rules_its_frame() -> None:
    """A Born marker over sparse speckle (services.sources.born_frames) rules its frame's energy: the weighting
    takes its echo for background and loses it (docs/validation.md, ninth session). The union takes the unweighted
    map, whose node is the more significant, at twice its PFA."""
    from services.sources import born_frames

    frames, cal = born_frames(1)
    (frame,) = frames
    band = frame.default_band()
    grid = fpcore.Grid.for_acquisition(frame, band, x_range=(-4e-3, 4e-3), z_range=(12e-3, 20e-3), spacing=0.25e-3)
    imagers = [fpcore.Imager(fpcore.ImagingConfig(grid, band, 16, time_weighting=w)) for w in (False, True)]
    r0 = np.asarray(cal.ground_truth.r0)
    fp = fpcore.from_calibration(cal, r0, imagers[0].out_sines_for(cal), band, 16, diameter=1.6e-3)
    alone = [fpcore.locate(im, frame, fp, max_pfa=None).detections[0] for im in imagers]
    truth = np.asarray(frame.ground_truth.targets[0].position)
    assert alone[0].pfa < 1e-8 and np.linalg.norm(np.asarray(alone[0].position_m) - truth) < 0.5e-3
    assert alone[1].pfa > 1e3 * alone[0].pfa  # the weighting's cost where a target rules the frame
    found, chosen = locate_union(imagers, frame, fp)
    assert chosen == 0
    (d,) = found.detections
    assert d.pfa == pytest.approx(2 * alone[0].pfa)
    assert d.position_m == alone[0].position_m


def test_a_null_model_chosen_among_maps_reports_the_union_pfa() -> None:
    """`fpcore.locate.union_null`: the same map and significance, every PFA it reports (the field of view's, a gate's)
    n_maps × its own, capped at 1, and `threshold` inverts that (eq. W2)."""
    from services.sources import born_frames

    frames, cal = born_frames(1)
    (frame,) = frames
    band = frame.default_band()
    grid = fpcore.Grid.for_acquisition(frame, band, x_range=(-4e-3, 4e-3), z_range=(12e-3, 20e-3), spacing=0.25e-3)
    im = fpcore.Imager(fpcore.ImagingConfig(grid, band, 16))
    fp = fpcore.from_calibration(cal, np.asarray(cal.ground_truth.r0), im.out_sines_for(cal), band, 16, diameter=1.6e-3)
    nm = fpcore.locate(im, frame, fp, max_pfa=None).null
    twice = union_null(nm, 2)
    assert twice.significance is nm.significance and nm.n_maps == 1 and twice.n_maps == 2
    for s in (6.0, 12.0, 25.0):
        assert twice.pfa(s) == pytest.approx(min(1.0, 2 * nm.pfa(s)))
        gate = np.array([4.0, 4.0])
        assert twice.gate_pfa(s, gate) == pytest.approx(min(1.0, 2 * nm.gate_pfa(s, gate)))
    assert twice.pfa(0.5) == 1.0  # capped
    t1, t2 = nm.threshold(1e-3), twice.threshold(1e-3)
    assert t2 > t1 and twice.pfa(t2) == pytest.approx(1e-3, rel=1e-6)
    with pytest.raises(ValueError, match="n_maps: expected at least 1"):
        union_null(nm, 0)


def _pipelines(frames, specs, **config):
    """Per configuration (as recorded, weighted, union) the results of a fresh Pipeline on `frames`."""
    from services.pipeline import Pipeline, PipelineConfig

    out = {}
    for label, extra in (("plain", {}), ("weighted", {"time_weighting": True}), ("union", {"union": True})):
        pipe = Pipeline(PipelineConfig(publish_image=False, max_pfa=1.0, **config, **extra), specs)
        out[label] = [pipe.process(acq) for acq in frames]
    return out


def test_the_pipeline_union_takes_the_weighted_map_in_the_fog_at_twice_its_pfa() -> None:
    """The 2-D sinking cylinders 2 ℓ_s deep (quick): the weighting finds both (docs/validation.md), the frame as
    recorded neither. With PipelineConfig.union the processor keeps the weighted maps: each detection and each
    track's measurement at exactly twice the weighted pipeline's PFA, its null model carrying the factor; the wire
    messages name the map and its normalisation is the weighted frame's."""
    from services.convert import frame_messages
    from services.sources import SimulatorSource

    src = SimulatorSource("sinking-cylinder", n_frames=2, quick=True, depth_ls=2)
    frames = [src.scenario.frame(i) for i in range(2)]
    runs = _pipelines(frames, src.fingerprint_specs())
    for plain, weighted, union in zip(runs["plain"], runs["weighted"], runs["union"], strict=True):
        assert union.statistic == {"cylinder1": "weighted", "cylinder2": "weighted"}
        assert all(nm.n_maps == 2 for nm in union.nulls.values())
        assert all(d.pfa > 1e-3 for d, _ in plain.detections)  # the frame as recorded: nothing found
        for (d, err), (w, _) in zip(union.detections, weighted.detections, strict=True):
            assert d.fingerprint == w.fingerprint and d.position_m == pytest.approx(w.position_m, abs=1e-7)
            assert d.pfa == pytest.approx(2 * w.pfa, rel=1e-3) and d.pfa < 1e-10 and err is not None and err < 0.5e-3
        for t, tw in zip(union.tracks, weighted.tracks, strict=True):
            assert t.pfa == pytest.approx(2 * tw.pfa, rel=1e-3)
    assert [t.status for t in runs["union"][-1].tracks] == ["confirmed", "confirmed"]
    msgs = frame_messages(runs["union"][0], 0, frames[0].timestamp)
    assert {d.statistic for d in msgs["detections"].detections} == {"weighted"}
    (g,) = [m for m in msgs["gamma"] if m.fingerprint == "cylinder1"]
    w_pw = runs["union"][0].weighted_pw
    assert g.statistic == "weighted" and g.normalisation.r_energy == pytest.approx(np.vdot(w_pw.data, w_pw.data).real)
    assert all(d.statistic is None for d in frame_messages(runs["plain"][0], 0, 0.0)["detections"].detections)


def test_the_pipeline_union_keeps_a_marker_that_rules_its_frame_and_its_shards_carry_the_factor() -> None:
    """The Born marker (above): the union pipeline keeps the map as recorded, at twice its PFA; a sharded worker's
    null models keep the factor through the FPSHARD1 payload, so the merger's tracker gates are the union's."""
    from services.nodes.worker import ShardResult, decode_shard, encode_shard
    from services.registry import FingerprintSpec
    from services.sources import born_frames

    frames, cal = born_frames(1)
    config = {"x_range": (-5e-3, 5e-3), "z_range": (10e-3, 22e-3), "spacing": 0.25e-3, "n_freq": 24}
    runs = _pipelines(frames, [FingerprintSpec("marker", calibration=cal)], **config)
    (plain,), (union,) = runs["plain"], runs["union"]
    assert union.statistic == {"marker": "as recorded"}
    (d, err), (p, _) = union.detections[0], plain.detections[0]
    assert (
        d.position_m == pytest.approx(p.position_m, abs=1e-7)
        and d.pfa == pytest.approx(2 * p.pfa, rel=1e-3)
        and d.pfa < 1e-8
        and err < 0.5e-3
    )
    sent = ShardResult(0, 0.0, "w-1", "result", [], union.nulls, {}, union.grid)
    back = decode_shard(encode_shard(sent)).nulls["marker"]
    assert back.n_maps == 2 and isinstance(back.n_maps, int)
    assert back.pfa(12.0) == pytest.approx(union.nulls["marker"].pfa(12.0))


def test_the_union_and_the_weighting_together_are_refused() -> None:
    from services.pipeline import PipelineConfig

    with pytest.raises(ValueError, match="--union: maps each frame both"):
        PipelineConfig(union=True, time_weighting=True)
    with pytest.raises(ValueError, match="--track-integrate: expected 1 with --union"):
        PipelineConfig(union=True, track_integrate=3)


def test_the_union_searches_velocities_on_the_frame_of_the_kept_map() -> None:
    """With a velocity dictionary (docs/design.md §4.13) the union pipeline searches each detection's velocities on the
    frame its kept map was made from, as the pipeline of that statistic alone does: the tracker then gates the motion
    measurement against that map's null model, not the other frame's. The 2-D cylinders 2 ℓ_s deep keep the weighted
    maps (above), so the search must run on the weighted frame."""
    import dataclasses

    from services.cli.fingerprint_args import parse_velocity_grid
    from services.sources import SimulatorSource

    src = SimulatorSource("sinking-cylinder", n_frames=1, quick=True, depth_ls=2)
    vg = parse_velocity_grid("0.1,0.1:0.1")
    specs = [dataclasses.replace(s, velocity_grid=vg) for s in src.fingerprint_specs()[:1]]
    acq = src.scenario.frame(0)
    acq = dataclasses.replace(acq, sequence=dataclasses.replace(acq.sequence, prf=1e3))  # the transmit times
    runs = _pipelines([acq], specs)
    (union,), (alone,) = runs["union"], runs["weighted"]
    assert set(union.statistic.values()) == {"weighted"}
    assert union.velocities and alone.velocities
    for u, a in zip(union.velocities, alone.velocities, strict=True):
        assert u is not None and a is not None
        np.testing.assert_allclose(u.velocity_m_s, a.velocity_m_s)
        assert u.gamma == pytest.approx(a.gamma, rel=1e-4)
