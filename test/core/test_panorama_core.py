"""Panorama core (Langlotz 2011 sec. 3.1, 4.1): cylinder geometry, map, tracking, EDR, seams.

Synthetic, seeded frames of a textured cylinder (exact truth) from test/panorama_synth.py.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from ar_tracking.core.panorama import MapConfig, MapperConfig, PanoramaMap, PanoramaMapper
from ar_tracking.core.panorama.cylinder import CylinderGeometry, rotation_about_axis_y
from ar_tracking.core.panorama.tracker import TrackerConfig
from ar_tracking.core.panorama.tracker import kabsch
from panorama_synth import (DT, H, K, W, CylinderWorld, angle_deg, render_all, rot, run, run_frames, sweep,
                            two_plane_frame)


@pytest.fixture(scope='module')
def world() -> CylinderWorld:
    return CylinderWorld(1)


# -- geometry --------------------------------------------------------------------------------

@settings(max_examples=60, deadline=None)
@given(st.floats(-3.1, 3.1), st.floats(-0.7, 0.7))
def test_cylinder_project_unproject_round_trip(theta, h):
    geo = CylinderGeometry()
    d = np.array([math.sin(theta), h, math.cos(theta)])
    u, v = geo.project(d)
    assert 0 <= u < geo.width
    np.testing.assert_allclose(geo.unproject(u, v), d / np.linalg.norm(d), atol=1e-9)


def test_cylinder_scale_and_axis():
    geo = CylinderGeometry()
    assert geo.f * 2 * math.pi == pytest.approx(2048)
    assert 360 / geo.width == pytest.approx(0.17578125)
    u0, v0 = geo.project(np.array([0.0, 0.0, 1.0]))
    assert (u0, v0) == (1024.0, 256.0)  # first optical axis at the map centre
    # A rotation about the cylinder axis is a pure column shift, across the wrap too.
    d = geo.unproject(np.array([2000.0]), np.array([100.0]))
    u1, v1 = geo.project(d @ rotation_about_axis_y(math.radians(20)).T)
    assert (u1[0] - (2000 + 20 / 360 * 2048)) % 2048 == pytest.approx(0, abs=1e-6)
    assert v1[0] == pytest.approx(100.0)


def test_cylinder_distances_go_the_short_way_across_the_wrap():
    geo = CylinderGeometry()
    assert geo.column_distance(2040.0, 8.0) == pytest.approx(16.0)
    assert geo.column_distance(8.0, 2040.0) == pytest.approx(16.0)
    assert geo.column_distance(np.array([0.0, 1024.0]), 1000.0) == pytest.approx([1000.0, 24.0])
    assert geo.map_distance(2046.0, 10.0, 2.0, 13.0) == pytest.approx(5.0)


def test_kabsch_recovers_rotation():
    rng = np.random.default_rng(0)
    R = rot('y', 33) @ rot('x', -7) @ rot('z', 4)
    b = rng.normal(size=(20, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    np.testing.assert_allclose(kabsch(b, b @ R.T), R, atol=1e-12)


# -- map -------------------------------------------------------------------------------------

def test_map_writes_only_unmapped_pixels_and_finishes_tiles(world):
    pano = PanoramaMap(MapConfig())
    img = world.render(np.eye(3))
    n1 = pano.map_frame(img, K, np.eye(3), 1)
    assert 50_000 < n1 < 120_000
    assert pano.map_frame(img, K, np.eye(3), 2) == 0  # nothing new: nothing mapped
    n3 = pano.map_frame(img, K, rot('y', 2.0), 3)
    assert 0 < n3 < 0.1 * n1  # only the sliver the pan uncovered (sec. 3.1)
    assert pano.mapped.sum() == n1 + n3
    assert set(np.unique(pano.contribution[pano.mapped])) == {1, 3}
    finished = pano.finished_tiles()
    assert finished.size >= 6
    ts = pano.config.tile_size
    tw = pano.tiles_shape[1]
    for t in finished:
        assert pano.mapped[(t // tw) * ts:(t // tw + 1) * ts, (t % tw) * ts:(t % tw + 1) * ts].all()
    tiles = pano.tiles_image()
    assert tiles.shape == (8, 32) and set(np.unique(tiles)) <= {0, 255}
    # Keypoints only come from the background queue, within its budget.
    assert pano.keypoints()[0].shape[0] == 0
    assert pano.process_queue(2) == 2
    assert len(pano.queue) == finished.size - 2
    pano.process_queue(100)
    dirs, uv, _ = pano.keypoints()
    assert dirs.shape[0] > 50
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0)
    assert pano.mapped[uv[:, 1].astype(int), uv[:, 0].astype(int)].all()


def test_edr_map_stores_offsets_without_clipping(world):
    img = world.render(np.eye(3))
    edr = PanoramaMap(MapConfig(edr=True))
    edr.map_frame(img, K, np.eye(3), 1, offset=-40.0)
    plain = PanoramaMap(MapConfig(edr=False))
    plain.map_frame(img, K, np.eye(3), 1, offset=-40.0)  # ignored without EDR
    assert edr.stored.dtype == np.uint16 and plain.stored.dtype == np.uint8
    m = edr.mapped
    v_edr, v_plain = edr.values()[m, 0], plain.values()[m, 0]
    np.testing.assert_allclose(v_edr - v_plain, -40.0, atol=0.6)
    assert v_edr.min() < 0  # below the 8-bit range, kept (16 bits per channel)
    tm = edr.tone_mapped(16)
    assert tm.dtype == np.uint16 and tm[m].min() == 0 and tm[m].max() == 65535 and (tm[~m] == 0).all()


# -- tracking --------------------------------------------------------------------------------

def test_tracks_a_full_turn_through_the_wrap(world):
    Rs = sweep(200, 2.0)  # 400 degrees about the vertical, with pitch / roll wobble
    mapper = PanoramaMapper()
    res = run(mapper, world, Rs)
    assert all(r.R_pano_cam is not None for r in res)
    errs = [angle_deg(r.R_pano_cam, Rs[0].T @ R) for r, R in zip(res, Rs)]
    assert max(errs) < 0.15
    assert math.sqrt(np.mean(np.square(errs))) < 0.05
    assert res[0].status == 'initialised' and res[-1].status == 'tracked'
    assert mapper.map.mapped[200:300].all(axis=1).any()  # the map closed on itself (360 deg)


def test_deterministic(world):
    Rs = sweep(40, 1.5, seed=2)
    a = run(PanoramaMapper(), world, Rs)
    b = run(PanoramaMapper(), world, Rs)
    assert all(np.array_equal(x.R_pano_cam, y.R_pano_cam) for x, y in zip(a, b))


def test_relocalises_after_a_jump_and_loses_on_a_white_wall(world, pan_of_120):
    Rs, frames = pan_of_120
    mapper = PanoramaMapper()
    run_frames(mapper, frames)
    t = 200 * DT
    white = np.full((H, W), 230, np.uint8)
    lost = mapper.process(white, K, t)
    assert lost.R_pano_cam is None and lost.status == 'lost' and 'texture' in lost.reason
    target = Rs[0].T @ Rs[0] @ rot('y', 100.0) @ rot('x', 3.0)
    res = mapper.process(world.render(Rs[0] @ rot('y', 100.0) @ rot('x', 3.0)), K, t + DT)
    assert res.status == 'relocalised'
    assert angle_deg(res.R_pano_cam, target) < 0.1


@pytest.mark.parametrize('roll_deg', [4.0, -8.0])
def test_relocalises_after_a_fast_pan_that_also_rolled_and_tilted_the_phone(world, pan_of_120, roll_deg):
    """After a fast pan the hand has also rolled and tilted the phone by a few degrees: at the
    frame's edges that is more than the wide search, so a hypothesis that only shifts the last
    orientation (yaw and tilt) fails to verify; one fitted on every tile match (a full rotation)
    does."""
    Rs, frames = pan_of_120
    mapper = PanoramaMapper()
    run_frames(mapper, frames)
    t = 200 * DT
    assert mapper.process(np.full((H, W), 230, np.uint8), K, t).status == 'lost'
    R_new = Rs[0] @ rot('y', 60.0) @ rot('x', 4.0) @ rot('z', roll_deg)
    res = mapper.process(world.render(R_new), K, t + DT)
    assert res.status == 'relocalised', res.reason
    assert angle_deg(res.R_pano_cam, Rs[0].T @ R_new) < 0.1


def test_translating_camera_is_reported_lost():
    mapper = PanoramaMapper()
    statuses = []
    for i, tx in enumerate(np.linspace(0.0, 0.3, 20)):
        statuses.append(mapper.process(two_plane_frame(tx), K, (i + 1) * DT).status)
        mapper.background()
    assert statuses[0] == 'initialised'
    assert statuses[-5:] == ['lost'] * 5  # parallax: no rotation explains the matches


def test_a_camera_lost_to_parallax_is_held_without_relocalising_every_frame():
    """A translating camera's frames are found in the map but rejected by the ratio tests: the
    first lost frame relocalises, the next ones are tried where its view was found and lost
    without a relocalisation (hold_parallax_frames); every status, and the rotation when the
    camera is back where the map was made, is what relocalising every frame gives."""
    def run_hold(hold: int) -> tuple[list[str], int, np.ndarray]:
        mapper = PanoramaMapper(MapperConfig(hold_parallax_frames=hold))
        calls = []
        hypotheses = mapper.relocaliser.hypotheses
        mapper.relocaliser.hypotheses = lambda *a, **k: calls.append(1) or hypotheses(*a, **k)  # type: ignore[method-assign]
        statuses = []
        for i, tx in enumerate([*np.linspace(0.0, 0.3, 20), 0.0, 0.0]):
            res = mapper.process(two_plane_frame(tx), K, (i + 1) * DT)
            mapper.background()
            statuses.append(res.status)
        return statuses, len(calls), res.R_pano_cam

    held, held_calls, R_held = run_hold(30)
    every, every_calls, R_every = run_hold(0)
    assert held[1:20] == ['lost'] * 19 and held[20:] == ['relocalised', 'tracked']
    assert held == every
    assert (held_calls, every_calls) == (2, 20)  # the loss's first frame and the one that came back
    assert np.allclose(R_held, R_every, atol=1e-6) and angle_deg(R_held, np.eye(3)) < 0.1


def _weaken(img: np.ndarray, k: int, share: float = 0.45, sigma: float = 3.5) -> np.ndarray:
    """The frame with its detail blurred in a random ``share`` of 32 px cells (motion blur over
    fine branches or grass: the content is there, weaker)."""
    rng = np.random.default_rng(100 + k)
    out = img.copy()
    blurred = cv2.GaussianBlur(img, (0, 0), sigma)
    for y in range(0, H, 32):
        for x in range(0, W, 32):
            if rng.random() < share:
                out[y:y + 32, x:x + 32] = blurred[y:y + 32, x:x + 32]
    return out


def test_detail_weakened_by_blur_keeps_tracking(world):
    """After 30 sharp frames, 45 % of every frame is blurred (sigma 3.5 px): many keypoints there
    fail min_ncc, but their weaker correlation still peaks where the rotation puts them, so they
    agree with it. None is lost, each within 0.2 deg; counting only the inliers (a weak_ncc no
    peak reaches) loses frames. The translating camera above is still lost."""
    Rs = sweep(90, 1.0, seed=2)
    statuses = {}
    for name, cfg in (('weak agreements', TrackerConfig()), ('inliers only', TrackerConfig(weak_ncc=1.01))):
        mapper = PanoramaMapper(MapperConfig(tracker=cfg))
        statuses[name] = []
        for k, R in enumerate(Rs):
            img = world.render(R, rng=np.random.default_rng(k))
            res = mapper.process(img if k < 30 else _weaken(img, k), K, (k + 1) * DT)
            mapper.background()
            statuses[name].append(res.status)
            if name == 'weak agreements' and k >= 30:
                assert res.R_pano_cam is not None and angle_deg(res.R_pano_cam, Rs[0].T @ R) < 0.2, k
    assert 'lost' not in statuses['weak agreements'] and statuses['weak agreements'][30:].count('tracked') >= 58, statuses
    assert statuses['inliers only'][30:].count('lost') >= 5, statuses


@pytest.fixture(scope='module')
def pan_of_120(world) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """sweep(120, 2.0, seed=4) and its frames (render_all), rendered once for the three
    relocalisation tests that map it before their jump."""
    Rs = sweep(120, 2.0, seed=4)
    return Rs, render_all(world, Rs)


@pytest.fixture(scope='module')
def exposure_step(world):
    """400 degrees about the vertical (sweep(200, 2.0, seed=5)) with an exposure jump (gain 1.35)
    half-way, rendered once, and ``mapped(edr, correction)``: (gains, mapper, results) of a
    PanoramaMapper of that EDR setting run over it, once per module. The two tests below ask for
    six runs, four of them different: the EDR 'offset' run is both tests', and the 8-bit map
    takes no EDR correction (PanoramaMapper._correction: (0, 1) without edr), so its run is one
    whatever the correction asked for."""
    gains = [1.0 if k < 100 else 1.35 for k in range(200)]
    frames = render_all(world, sweep(200, 2.0, seed=5), gains=gains)
    runs: dict[tuple[bool, str | None], tuple[PanoramaMapper, list]] = {}

    def mapped(edr: bool, correction: str) -> tuple[list[float], PanoramaMapper, list]:
        key = (edr, correction if edr else None)
        if key not in runs:
            cfg = MapperConfig(map=MapConfig(edr=edr), edr_correction=correction) if edr \
                else MapperConfig(map=MapConfig(edr=False))
            mapper = PanoramaMapper(cfg)
            runs[key] = mapper, run_frames(mapper, frames)
        return (gains, *runs[key])

    return mapped


@pytest.mark.parametrize('correction', ['overlap', 'offset'])
def test_edr_corrects_exposure_steps(exposure_step, correction):
    # 360+ degrees with an exposure jump (gain 1.35) half-way: the revisited part of the map
    # meets the first frames' contribution, where the 8-bit map shows the step.
    results = {}
    for edr in (True, False):
        gains, mapper, res = exposure_step(edr, correction)
        assert all(r.R_pano_cam is not None for r in res)
        results[edr] = mapper.seam_error(min_gap=30, flat_max=np.inf)['step']
        if edr and correction == 'offset':
            offs = [r.intensity_offset for r in res]
            assert abs(np.mean(offs[10:90])) < 2.0 and np.mean(offs[120:]) < -20
        if edr and correction == 'overlap':
            # Gain and offset together map each frame that adds pixels back to the first
            # frame's levels.
            levels = np.array([60.0, 120.0, 180.0])
            mapping = [(r, g) for r, g in zip(res[10:], gains[10:]) if r.mapped_pixels > 0]
            assert len(mapping) > 150
            for r, g in mapping:
                np.testing.assert_allclose(r.intensity_gain * levels * g + r.intensity_offset, levels, atol=2.0)
    assert results[True] < 0.5 * results[False]


# -- EDR exposure model and photo mode ----------------------------------------------------------

def test_exposure_filter_smooths_noise_and_follows_jumps():
    from ar_tracking.core.panorama import ExposureConfig, ExposureFilter

    rng = np.random.default_rng(7)
    truth = np.where(np.arange(300) < 150, 0.0, math.log(1 / 1.35))
    z = truth + rng.normal(0, 0.01, truth.size)
    filt = ExposureFilter(ExposureConfig())
    raw = ExposureFilter(ExposureConfig(smooth=False))
    est = np.array([filt.update(v, 0.01, 1 / 30) for v in z])
    est_raw = np.array([raw.update(v, 0.01, 1 / 30) for v in z])
    np.testing.assert_allclose(est_raw, z)  # unsmoothed: each frame's own estimate
    steady = np.r_[20:150, 170:300]
    assert np.std(est[steady] - truth[steady]) < 0.5 * np.std(z[steady] - truth[steady])
    assert abs(est[150] - truth[150]) < 0.04  # the jump is followed at once, not averaged in
    assert filt.jumps >= 1
    assert filt.update(float('nan'), float('inf'), 1 / 30) == est[-1]  # no information: kept


def test_gain_model_corrects_multiplicative_exposure_better_than_offset(exposure_step):
    # A gain of 1.35 (an exposure change) half-way round the turn: the log-domain estimate
    # recovers 1 / 1.35; a single offset fits only the keypoints' mean brightness. Compared by
    # the pixel-wise difference at the revisit boundaries (same texture in both maps): the step
    # measure has only ~14 short segments there on this busy texture, too noisy to rank them.
    seams = {}
    for model in ('gain', 'offset'):
        gains, mapper, res = exposure_step(True, model)  # the default EDR map
        assert all(r.R_pano_cam is not None for r in res)
        seams[model] = mapper.seam_error(min_gap=30)['pixelwise']
        if model == 'gain':
            g = np.array([r.intensity_gain for r in res])
            assert np.all(np.abs(g[5:95] - 1.0) < 0.01)
            assert np.all(np.abs(g[110:] * 1.35 - 1.0) < 0.02)
    assert seams['gain'] < seams['offset']
    with pytest.raises(ValueError):
        MapperConfig(edr_correction='affine')


def test_photo_mode_tracks_photos_20_degrees_apart(world):
    from ar_tracking.core.panorama.cylinder import rotation_about_axis_y
    from ar_tracking.eval.bench_panorama import photo_config

    Rs = [rot('y', -20.0 * k) @ rot('x', 1.0 * math.sin(k)) for k in range(18)]  # 360 deg
    mapper = PanoramaMapper(photo_config())
    last = None
    yaws = []
    for k, R in enumerate(Rs):
        img = world.render(R, gain=1.0 + 0.1 * math.sin(k), rng=np.random.default_rng(k))
        prior = None if last is None else last @ rotation_about_axis_y(math.radians(-20.0))
        res = mapper.process(img, K, (k + 1) * 1_000_000_000, prior=prior)
        mapper.background()
        assert res.R_pano_cam is not None, (k, res.reason)
        assert angle_deg(res.R_pano_cam, Rs[0].T @ R) < 0.3
        last = res.R_pano_cam
        yaws.append(math.degrees(math.atan2(last[0, 2], last[2, 2])))
    steps = np.mod(np.diff(yaws), 360) - 360
    np.testing.assert_allclose(steps, -20.0, atol=0.3)


def test_relocaliser_consensus_finds_the_rotation_most_tile_matches_agree_on():
    """Tile matches as correspondences: 12 agree on one rotation (a few tenths of a pixel of
    noise), 5 look-alikes agree on another 20 deg away, 6 are scattered; the hypotheses are the
    two rotations, the larger consensus first, each refitted to well within the consensus."""
    from ar_tracking.core.panorama.relocalise import _consensus_rotations

    rng = np.random.default_rng(7)
    f = 326.0
    R_a, R_b = rot('y', 35.0) @ rot('x', 4.0) @ rot('z', -3.0), rot('y', 55.0)
    rays = rng.normal(size=(23, 3)) * [0.3, 0.2, 0.0] + [0.0, 0.0, 1.0]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    d = np.empty_like(rays)
    d[:12] = rays[:12] @ R_a.T + rng.normal(scale=0.3 / f, size=(12, 3))
    d[12:17] = rays[12:17] @ R_b.T
    d[17:] = rng.normal(size=(6, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hyps = _consensus_rotations(rays, d, 6.0 / f, 3, 3)
    assert len(hyps) == 2
    assert angle_deg(hyps[0], R_a) < 0.2 and angle_deg(hyps[1], R_b) < 0.2  # the roll is the least sure
    assert _consensus_rotations(rays[17:], d[17:], 6.0 / f, 3, 3) == []  # nothing agrees


def test_the_coarse_to_fine_tile_search_finds_what_the_whole_warp_search_finds(world, pan_of_120):
    """After a 60 deg jump with tilt and roll, the relocaliser's coarse-to-fine tile search
    (half resolution over the whole warp, then full resolution around the peak) gives the
    hypothesis the exhaustive search gives, near the truth."""
    from ar_tracking.core.panorama.relocalise import Relocaliser, RelocaliserConfig

    Rs, frames = pan_of_120
    mapper = PanoramaMapper()
    run_frames(mapper, frames)
    R_new = Rs[0] @ rot('y', 60.0) @ rot('x', 4.0) @ rot('z', 4.0)
    frame, hint = world.render(R_new), Rs[0].T @ Rs[-1]
    fast = Relocaliser(RelocaliserConfig()).hypotheses(frame, K, hint, mapper.map)
    whole = Relocaliser(RelocaliserConfig(refine_px=0)).hypotheses(frame, K, hint, mapper.map)
    assert fast and whole
    assert angle_deg(fast[0], whole[0]) < 0.05
    assert angle_deg(fast[0], Rs[0].T @ R_new) < 0.5


@pytest.fixture(scope='module')
def unseen_scene(world) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]:
    """30 frames of a 30 deg pan, then the views Rs of a scene the map never saw (another
    texture): (first frames, Rs, their frames), rendered once for both restart settings."""
    elsewhere = CylinderWorld(7)
    Rs = [rot('y', 0.3 * k) @ rot('x', 2 * math.sin(0.1 * k)) for k in range(100)]
    return render_all(world, sweep(30, 1.0, seed=2)), Rs, render_all(elsewhere, Rs)


@pytest.mark.parametrize('restart_lost_s', [0.0, 2.0])
def test_a_new_panorama_starts_when_the_camera_stays_where_the_map_never_was(unseen_scene, restart_lost_s):
    """After 30 deg mapped, the camera looks at a scene the map never saw (another texture) and
    stays there: with ``restart_lost_s`` a new panorama starts from the frame 2 s into the loss
    and the frames after it track in it (their rotations from that frame exact); with 0 the
    mapper waits for its old map and every one of them is lost."""
    first, Rs, frames = unseen_scene
    mapper = PanoramaMapper(MapperConfig(restart_lost_s=restart_lost_s))
    run_frames(mapper, first)
    results = []
    for k, img in enumerate(frames):
        results.append(mapper.process(img, K, (40 + k) * DT))
        mapper.background()
    statuses = [r.status for r in results]
    if restart_lost_s == 0.0:
        assert statuses == ['lost'] * len(Rs) and mapper.restarts == 0
        return
    start = statuses.index('initialised')
    assert mapper.restarts == 1 and statuses[:start] == ['lost'] * start
    assert (start - 1) * DT * 1e-9 < restart_lost_s <= start * DT * 1e-9  # 2 s after the first failed frame
    tracked = results[start + 1:]
    assert all(r.status == 'tracked' for r in tracked)
    for k, r in enumerate(tracked, start + 1):
        assert angle_deg(r.R_pano_cam, Rs[start].T @ Rs[k]) < 0.1
