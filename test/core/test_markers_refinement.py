"""Marker corners (Caarls 2009 sec. 2.4): log-parabola, lens model eq. 2, refinement, pose."""
from __future__ import annotations

import numpy as np
import pytest

from ar_tracking.core.markers import MarkerError
from ar_tracking.core.markers.detection import MarkerDetector, quad_shape_problem
from ar_tracking.core.markers.edge_refinement import RefinedQuad, log_parabola_offset
from ar_tracking.core.markers.lens_model import LensModel, eq2_distort, eq2_undistort
from ar_tracking.core.markers.photometry import gamma_from_levels, linearize
from ar_tracking.core.markers.pose import MapMarker, MarkerMap, estimate_camera_pose
from ar_tracking.eval.vi_metrics import marker_corner_accuracy
from ar_tracking.sim import robot_arcs as ra


def test_log_parabola_is_exact_for_a_gaussian_gradient_profile():
    for x_edge in np.linspace(-0.5, 0.5, 11):
        for s in (0.7, 1.0, 1.6):
            g = np.exp(-0.5 * ((np.array([-1.0, 0.0, 1.0]) - x_edge) / s) ** 2)
            assert np.isclose(log_parabola_offset(g[:1], g[1:2], g[2:])[0], x_edge, atol=1e-9)
            plain = 0.5 * (g[0] - g[2]) / (g[0] - 2 * g[1] + g[2])
            if 0.2 < abs(x_edge) < 0.45:  # the plain parabola is biased where the log one is exact
                assert abs(plain - x_edge) > 1e-3


def test_eq2_lens_model_round_trip_and_opencv_model():
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.6, 0.6, (50, 2))
    for k in ([0.1, -0.02, 0.003], [-0.2, 0.05, 0.0]):
        d = eq2_distort(p, np.array(k))
        assert np.allclose(eq2_undistort(d, np.array(k)), p, atol=1e-10)
    K = ra.Camera().K
    for lens in (LensModel(K, 'opencv', np.array([-0.1, 0.02, 0.001, -0.001, 0.0])),
                 LensModel(K, 'caarls_eq2', eq2_k=np.array([0.08, -0.01, 0.0]))):
        px = lens.distort(p * 0.5)
        assert np.allclose(lens.undistort(px), p * 0.5, atol=1e-7)
    with pytest.raises(MarkerError):
        LensModel(K, 'fisheye')


def test_seed_refinement_beats_opencv_subpix_and_bias_is_small():
    res = marker_corner_accuracy(seed=1, n_poses=6, n_noisy=1)
    assert res['n_corners'] >= 16
    assert res['corner_rmse_px']['caarls'] <= res['corner_rmse_px']['opencv_subpix']
    assert res['corner_bias_px']['caarls'] < 0.02
    assert res['corner_rmse_px']['caarls'] < res['corner_rmse_px']['none']


def test_gamma_images_corners_unbiased_once_the_response_is_undone():
    """A display gamma of 2.2 puts edge-model corners ~0.4 px inward; undoing the response
    (estimated from the marker's levels) brings the mean outward offset within 0.05 px."""
    res = marker_corner_accuracy(seed=2, n_poses=6, n_noisy=1, display_gamma=2.2)
    assert res['n_corners'] >= 16
    assert abs(res['corner_outward_px']['caarls']) < 0.05
    assert abs(res['corner_outward_px']['caarls_given_gamma']) < 0.05
    assert res['corner_outward_px']['opencv_subpix'] < -0.2   # OpenCV's sub-pixel corners go inward
    assert res['corner_rmse_px']['caarls'] < res['corner_rmse_px']['opencv_subpix']


def test_gamma_from_levels_and_linearize():
    assert gamma_from_levels(255 * (25 / 255) ** (1 / 2.2), 255 * (225 / 255) ** (1 / 2.2), 9.0) == pytest.approx(2.2, rel=1e-6)
    assert gamma_from_levels(100.0, 90.0, 9.0) is None          # white darker than black
    lin = linearize(np.array([[0, 128, 255]], np.uint8), 2.2)
    assert lin[0, 0] == 0 and lin[0, 2] == pytest.approx(255) and lin[0, 1] == pytest.approx(255 * (128 / 255) ** 2.2, rel=1e-5)
    with pytest.raises(MarkerError):
        MarkerDetector(response_gamma=-1.0)


def test_blur_and_occlusion_raise_the_corner_sigmas():
    det = MarkerDetector(corner_sigma_px=0.05, blur_sigma_gain=0.25)
    sharp = RefinedQuad(np.zeros((4, 2)), np.zeros((4, 2)), 100, 0.05, np.ones(4), np.ones(4), np.full(4, 0.05))
    blurred = RefinedQuad(np.zeros((4, 2)), np.zeros((4, 2)), 100, 0.05, np.array([6.0, 1.0, 1.0, 1.0]), np.ones(4), np.full(4, 0.05))
    occluded = RefinedQuad(np.zeros((4, 2)), np.zeros((4, 2)), 100, 0.05, np.ones(4), np.array([1.0, 1.0, 0.4, 1.0]), np.full(4, 0.05))
    s0, sb, so = det.corner_sigmas(sharp), det.corner_sigmas(blurred), det.corner_sigmas(occluded)
    assert np.all(s0 < 0.1)
    assert sb[0] > 5 * s0[0] and sb[1] > 5 * s0[1] and sb[2] == pytest.approx(s0[2])   # side 0 joins corners 0 and 1
    assert so[2] > 2 * s0[2] and so[3] > 2 * s0[3] and so[0] == pytest.approx(s0[0])


def test_edge_on_and_tiny_quads_are_rejected():
    square = np.array([[0, 0], [50, 0], [50, 50], [0, 50]], float)
    assert quad_shape_problem(square, 25, 12) is None
    sliver = np.array([[0, 0], [50, 0], [52, 6], [2, 6]], float)
    assert 'edge-on' in quad_shape_problem(sliver, 25, 5)
    assert 'small' in quad_shape_problem(square / 10, 25, 12)


def _map() -> MarkerMap:
    mapped, _ = ra.wall_markers()
    return MarkerMap('enu', {m.id: MapMarker(m.id, m.size_m, m.position, m.R_world_marker) for m in mapped})


def test_pose_from_all_markers_with_covariance_and_unknown_id_rejected():
    cam = ra.Camera()
    lens = LensModel(cam.K)
    mapped, unknown = ra.wall_markers()
    sched = ra.ArcSchedule.make(5.0)
    tr = ra.truth_at(sched, np.array([2.0]))
    img, _ = ra.render_frame(cam, tr.R_enu_cam[0], tr.position[0], mapped + unknown, np.random.default_rng(3))
    mm = _map()
    obs, rej = MarkerDetector().detect(img, lens, mm.ids)
    assert sorted(o.id for o in obs) == [0, 1, 2, 3]
    assert [r.id for r in rej] == [17] and 'not in the marker map' in rej[0].reason
    est = estimate_camera_pose(obs, mm, lens.focal_px)
    assert est is not None and est.n_points == 16
    assert np.linalg.norm(est.p_map_cam - tr.position[0]) < 0.01
    assert np.all(np.linalg.eigvalsh(est.cov) > 0)
    sig = np.sqrt(np.diag(est.cov)[:3])
    assert np.all(sig < 0.05) and np.all(sig > 1e-5)
    one = estimate_camera_pose(obs[:1], mm, lens.focal_px)
    assert one is not None and np.linalg.norm(one.p_map_cam - tr.position[0]) < 0.05
    assert np.trace(one.cov[:3, :3]) > np.trace(est.cov[:3, :3])  # more markers, more precise


def test_marker_map_text_and_errors(tmp_path):
    doc = ra.marker_map_doc(ra.wall_markers()[0])
    import yaml
    path = tmp_path / 'm.yaml'
    path.write_text(yaml.safe_dump(doc))
    assert MarkerMap.from_yaml(path).ids == {0, 1, 2, 3}
    with pytest.raises(MarkerError):
        MarkerMap.from_text('markers: [{id: 1, size_m: -1, position: [0, 0, 0]}]')
    with pytest.raises(MarkerError):
        MarkerMap.from_text('[1, 2')
    with pytest.raises(MarkerError):
        MarkerMap.from_arrays([1, 1], [0.1, 0.1], [0, 0, 0, 0, 0, 0, 1] * 2)


def _decelerating_edge_image(x_mid: float, v_px_s: float, a_px_s2: float, exposure_s: float = 0.012,
                             cell_px: float = 7.0, height: int = 40, width: int = 80) -> np.ndarray:
    """Light image of a vertical marker edge (white quiet zone left, a black border strip one
    cell wide, then a white code bit) moving right with constant deceleration over the
    exposure; x_mid is the edge at mid-exposure. Each pixel integrates over its area and time."""
    xs = np.arange(width)[None, :] + (np.arange(16)[:, None] + 0.5) / 16 - 0.5   # pixel sub-samples
    img = np.zeros(width)
    ts = (np.arange(400) + 0.5) / 400 * exposure_s - exposure_s / 2
    for t in ts:
        e = x_mid + v_px_s * t + 0.5 * a_px_s2 * t * t
        black = (xs >= e) & (xs < e + cell_px)
        img += np.mean(np.where(black, 0.11, 1.0), axis=0)
    img /= len(ts)
    return np.tile(img, (height, 1)).astype(np.float32)


def test_blurred_side_is_located_at_its_mid_exposure_position():
    """A decelerating edge (the end of a quick pan: ~7 px of blur, the speed halving within the
    exposure) is found where it was at mid-exposure by the half level, while the gradient peak
    sits towards where it lingered; a code bit one cell inside does not move the half level."""
    from ar_tracking.core.markers.edge_refinement import (edge_points_along_side, gaussian_gradient,
                                                          relocate_blurred_side)
    for x_mid in (30.0, 30.3, 30.7):
        img = _decelerating_edge_image(x_mid, v_px_s=620.0, a_px_s2=-35000.0)
        gx, gy = gaussian_gradient(img, 1.0)
        mag = np.sqrt(gx * gx + gy * gy)
        a, b = np.array([x_mid, 35.0]), np.array([x_mid, 5.0])   # the side runs up: outward is -x
        found = edge_points_along_side(gx, gy, mag, a, b)
        assert len(found) > 10
        peak_err = float(np.mean(found[:, 0]) - x_mid)
        moved = relocate_blurred_side(img, a, b, found, 0.5 * (1.0 + 0.11), 0.9 * 7.0)
        half_err = float(np.mean(moved[:, 0]) - x_mid)
        assert abs(half_err) < 0.05, (x_mid, half_err)
        assert abs(peak_err) > 0.2, (x_mid, peak_err)


def test_a_marker_that_misses_the_others_pose_is_left_out():
    """Four markers with 0.02 px corner noise; one has a side bent by an occluder (two corners
    0.5 px off): the pose leaves it out (and is as good as without it). Sigmas too small for
    every marker alike drop none."""
    from ar_tracking.core.markers.detection import MarkerObservation

    cam = ra.Camera()
    lens = LensModel(cam.K)
    mm = _map()
    sched = ra.ArcSchedule.make(5.0)
    tr = ra.truth_at(sched, np.array([2.0]))
    R, p = tr.R_enu_cam[0], tr.position[0]
    rng = np.random.default_rng(11)

    def observations(bent: bool, sigma: float) -> list:
        out = []
        for mid, m in sorted(mm.markers.items()):
            uv, _ = ra.project(cam.K, R, p, m.corners_map())
            uv = uv + rng.normal(scale=0.02, size=uv.shape)
            if bent and mid == 3:
                uv[[0, 3], 0] += np.array([-0.15, 0.5])
            out.append(MarkerObservation(mid, uv, lens.undistort(uv), uv, np.full(4, sigma)))
        return out

    err_gated, err_kept = [], []
    for _ in range(30):
        bent = observations(True, 0.06)
        est = estimate_camera_pose(bent, mm, lens.focal_px, 0.06)
        assert est.ids == (0, 1, 2)
        kept = estimate_camera_pose(bent, mm, lens.focal_px, 0.06, marker_gate_chi2=0.0)
        assert kept.ids == (0, 1, 2, 3)
        err_gated.append(np.linalg.norm(est.p_map_cam - p))
        err_kept.append(np.linalg.norm(kept.p_map_cam - p))
    assert np.sqrt(np.mean(np.square(err_gated))) < 0.7 * np.sqrt(np.mean(np.square(err_kept)))
    # every marker 10x worse than its sigma: nobody is singled out
    tight = observations(False, 0.002)
    assert estimate_camera_pose(tight, mm, lens.focal_px, 0.002).ids == (0, 1, 2, 3)
