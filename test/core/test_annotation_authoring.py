"""Authoring pieces without a bag: the panorama's estimated place in the world from the graph's
cores (Langlotz 2011 sec. 5), position forms and files, the device calibration, the PNG grid."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml

from ar_tracking.annotate import (Position, PositionError, load_camera_params, load_device_params, parse_position,
                                  position_direction, read_positions, write_panorama_png)
from ar_tracking.core.annotations.world_orientation import DEFAULT_R_IMU_CAM, PanoramaWorldEstimator
from ar_tracking.core.panorama.cylinder import CylinderGeometry
from ar_tracking.core.rotations import rot_x, rot_y, rot_z, so3_log
from ar_tracking.io.bags import BagError

GEO = CylinderGeometry()
#: ENU from a level panorama (x east, y down, z north), turned 35 deg and tilted 2 deg.
R_ENU_PANO = rot_z(math.radians(35.0)) @ rot_x(math.radians(2.0)) @ np.array(
    [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
FIELD_ENU = 48e-6 * np.array([0.0, math.cos(1.117), -math.sin(1.117)])
G_ENU = np.array([0.0, 0.0, 9.81])


def session(est: PanoramaWorldEstimator, seed: int = 0, with_mag: bool = True, seconds: float = 20.0) -> None:
    """A phone turned about the panorama's vertical at 0.3 rad/s: visual orientations at 30 Hz,
    noisy IMU and field samples at 100 Hz (raw = calibrated here: identity calibration)."""
    rng = np.random.default_rng(seed)
    for k in range(int(seconds * 30)):
        t = k * 1_000_000_000 // 30
        est.add_visual(t, rot_y(0.3 * t * 1e-9))
    for k in range(int(seconds * 100)):
        t = k * 10_000_000
        R_enu_imu = R_ENU_PANO @ rot_y(0.3 * t * 1e-9) @ DEFAULT_R_IMU_CAM.T
        gyro = R_enu_imu.T @ (R_ENU_PANO @ np.array([0.0, 0.3, 0.0])) + rng.normal(0, 0.002, 3)
        est.add_imu(t, gyro, R_enu_imu.T @ G_ENU + rng.normal(0, 0.05, 3))
        if with_mag:
            est.add_mag(t + 1, R_enu_imu.T @ FIELD_ENU + rng.normal(0, 0.3e-6, 3))


def test_estimator_recovers_the_panorama_in_the_world_with_an_honest_covariance():
    est = PanoramaWorldEstimator()
    session(est)
    w = est.estimate()
    assert w is not None and w.source == 'world_alignment' and w.samples > 1500
    err = so3_log(R_ENU_PANO.T @ w.R_enu_pano)
    assert np.degrees(np.linalg.norm(err)) < 0.5
    assert 0 < w.heading_sigma_rad < math.radians(2.0)
    assert abs(err[2]) < 4 * w.heading_sigma_rad + 1e-3  # the heading error is within its sigma's reach
    np.testing.assert_allclose(w.up, R_ENU_PANO[2], atol=0.01)  # ENU up in the panorama frame
    assert np.degrees(w.ahrs_disagreement_rad) < 3.0  # the AHRS's mean agrees


def test_estimator_without_visual_samples_or_field_says_so():
    est = PanoramaWorldEstimator()
    assert est.estimate() is None
    no_vision = PanoramaWorldEstimator()
    session(no_vision)
    no_vision.visual.clear()
    assert no_vision.estimate() is None
    blind = PanoramaWorldEstimator()
    session(blind, with_mag=False, seconds=5.0)
    assert blind.estimate() is None  # no heading from anything: nothing is invented
    bad = PanoramaWorldEstimator()
    bad.add_imu(0, [np.nan, 0, 0], [0, 0, 9.8])
    bad.add_mag(0, [0, 0, 0])
    assert bad.imu == [] and bad.mag == []


def test_position_forms_agree_on_one_direction():
    u, v = 1300.0, 180.0
    d_px = position_direction(Position('a', u, v, 'pixel'), GEO, None)
    az = math.degrees((u - GEO.width / 2) / GEO.f)
    el = math.degrees(math.atan((GEO.height / 2 - v) / GEO.f))
    d_az = position_direction(Position('a', az, el, 'azel'), GEO, None)
    np.testing.assert_allclose(d_px, d_az, atol=1e-12)
    e = R_ENU_PANO @ d_px
    bearing = math.degrees(math.atan2(e[0], e[1]))
    elevation = math.degrees(math.asin(e[2]))
    np.testing.assert_allclose(position_direction(Position('a', bearing, elevation, 'bearing'), GEO, R_ENU_PANO),
                               d_px, atol=1e-12)
    assert position_direction(Position('a', bearing, elevation, 'bearing'), GEO, None) is None
    uu, vv = GEO.project(d_az)
    assert abs(uu - u) < 1e-9 and abs(vv - v) < 1e-9


def test_positions_file_forms_and_bad_rows(tmp_path):
    f = tmp_path / 'p.txt'
    f.write_text('# pixels first\nChurch, tower,1020.5,200\nno numbers here\n# form: azel\nDoor,-12.5,3\n'
                 'Up,10,95\nNaN,1,nan\n# form: bearing\nMast,273,4.5\nshort,1\n')
    rows, bad = read_positions(f)
    assert rows == [Position('Church, tower', 1020.5, 200.0, 'pixel'), Position('Door', -12.5, 3.0, 'azel'),
                    Position('Mast', 273.0, 4.5, 'bearing')]
    assert len(bad) == 4 and all(line.startswith(f'{f}:') and line.endswith('row skipped') for line in bad)
    assert ':3:' in bad[0] and 'elevation 95' in bad[1] and 'finite' in bad[2]
    (tmp_path / 'x.txt').write_text('# form: polar\na,1,2\n')
    with pytest.raises(PositionError, match='unknown form'):
        read_positions(tmp_path / 'x.txt')
    with pytest.raises(PositionError, match='cannot read'):
        read_positions(tmp_path / 'missing.txt')
    assert parse_position(' Door ', '1, 2', 'pixel') == Position('Door', 1.0, 2.0, 'pixel')
    with pytest.raises(PositionError, match='two numbers'):
        parse_position('Door', '1', 'azel')


def test_device_params_from_either_node_section(tmp_path):
    side = tmp_path / 'b.params.yaml'
    side.write_text(yaml.safe_dump({
        'imu_magnetometer': {'ros__parameters': {'gyro_bias': [0.1, 0.0, 0.0], 'declination_rad': 0.2}},
        'hybrid_orientation_filter': {'ros__parameters': {'accel_bias': [0.0, 0.3, 0.0],
                                                          'imu_to_camera_quat_xyzw': [0.0, 0.0, 0.0, 1.0]}}}))
    cal, R_imu_cam, decl = load_device_params([side])
    assert cal.gyro_bias[0] == 0.1 and cal.accel_bias[1] == 0.3 and decl == 0.2
    np.testing.assert_allclose(R_imu_cam, np.eye(3))
    cal, R_imu_cam, decl = load_device_params([])
    np.testing.assert_allclose(R_imu_cam, DEFAULT_R_IMU_CAM)
    bad = tmp_path / 'bad.yaml'
    bad.write_text('imu_magnetometer: {ros__parameters: {soft_iron_matrix: [0, 0, 0, 0, 0, 0, 0, 0, 0]}}')
    with pytest.raises(BagError, match='singular'):
        load_device_params([bad])


def test_camera_params_give_annotate_the_graphs_rolling_shutter(tmp_path):
    """annotate maps the authoring bag with the rolling shutter the graph's panorama_mapper gets
    (readout, its estimate, the repaint's budget)."""
    side = tmp_path / 'b.params.yaml'
    side.write_text(yaml.safe_dump({'panorama_mapper': {'ros__parameters': {'readout_s': 0.025}}}))
    assert load_camera_params([side]) == {'readout_s': 0.025, 'estimate_readout': True, 'repaint_max_mb': 96.0}
    assert load_camera_params([]) == {'readout_s': 0.0, 'estimate_readout': True, 'repaint_max_mb': 96.0}
    off = tmp_path / 'off.yaml'
    off.write_text('panorama_mapper: {readout_s: 0.01, estimate_readout: false, repaint_max_mb: 0}')
    assert load_camera_params([side, off]) == {'readout_s': 0.01, 'estimate_readout': False, 'repaint_max_mb': 0.0}
    for text, what in (('{readout_s: 2.0}', 'readout_s'), ('{repaint_max_mb: -1}', 'repaint_max_mb')):
        bad = tmp_path / 'bad.yaml'
        bad.write_text(f'panorama_mapper: {{ros__parameters: {text}}}')
        with pytest.raises(BagError, match=what):
            load_camera_params([bad])


def test_panorama_png_has_the_degree_grid(tmp_path):
    gray = np.full((512, 2048), 128, np.uint8)
    mapped = np.zeros((512, 2048), bool)
    mapped[100:400] = True
    out = cv2.imread(str(write_panorama_png(gray, mapped, tmp_path / 'p.png', R_ENU_PANO)))
    assert out.shape == (512, 2048, 3)
    u0 = int(round(GEO.width / 2))  # azimuth 0: a grid line down the middle
    assert tuple(out[300, u0]) != (128, 128, 128) and tuple(out[300, u0 + 20]) == (128, 128, 128)
    v10 = int(round(256 - math.tan(math.radians(10)) * GEO.f))  # elevation +10
    assert tuple(out[v10, 700]) != (128, 128, 128)
    assert tuple(out[50, 700]) == (60, 20, 0)  # unmapped: dark blue (BGR)
