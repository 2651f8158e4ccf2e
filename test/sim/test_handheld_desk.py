"""handheld_desk scenario: determinism, ground truth vs rendering, rolling shutter, motion, texture, bag."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from ar_tracking.io.bags import BagReader, BagWriter, stamp_to_ns
from ar_tracking.sim import handheld_desk as hd
from ar_tracking.sim.bagmaker import START_NS


def test_same_seed_same_images_other_seed_other_images():
    a = list(hd.frames(3, 0.15, 160, 120))
    b = list(hd.frames(3, 0.15, 160, 120))
    c = list(hd.frames(4, 0.15, 160, 120))
    assert len(a) == 3 and [f.stamp_ns for f in a] == [0, 50_000_000, 100_000_000]
    for fa, fb, fc in zip(a, b, c, strict=True):
        assert fa.image.dtype == np.uint8 and fa.image.shape == (120, 160)
        assert np.array_equal(fa.image, fb.image)
        assert not np.array_equal(fa.image, fc.image)
        R, p = hd.trajectory(3, 0.15, np.array([fa.stamp_ns * 1e-9]))
        assert np.allclose(R[0], fa.R_w_c) and np.allclose(p[0], fa.p_w_c)
    # skipping frames gives the same frames
    late = next(hd.frames(3, 0.15, 160, 120, start_index=2))
    assert np.array_equal(late.image, a[2].image)


def _dot_centroids(scene, cam, pose_fn, t, points):
    """Centroids of dots painted at world points (white-dot render minus black-dot render)."""
    white, _ = hd.render_image(scene.with_dots(points, 0.004, 255), cam, pose_fn, t, optical_blur=False)
    black, _ = hd.render_image(scene.with_dots(points, 0.004, 0), cam, pose_fn, t, optical_blur=False)
    return white.astype(float) - black.astype(float)


def _project_rolling(cam, seed, t, X):
    """Pixel of world point X in the frame whose centre row is captured at t (row-time iteration)."""
    v = (cam.height - 1) / 2
    for _ in range(5):
        R, p = hd.trajectory(seed, 30.0, np.array([t + cam.row_time_offset_s(v)]))
        Xc = R[0].T @ (X - p[0])
        uv = Xc[:2] / Xc[2] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
        v = uv[1]
    return uv


@pytest.mark.parametrize('t', [1.2, 8.0])
def test_ground_truth_projects_where_the_renderer_draws(t):
    seed = 0
    cam = hd.desk_camera(320, 240, exposure_s=0.0)  # readout 30 ms: each row its own pose
    scene = hd.desk_scene(seed)
    motion = hd.desk_motion(seed)
    pts = np.array([[x, y, 0.0] for x in np.linspace(-0.55, 0.55, 15) for y in np.linspace(-0.35, 0.38, 10)])
    diff = np.clip(_dot_centroids(scene, cam, motion.pose, t, pts), 0, None)
    errs = []
    for X in pts:
        uv = _project_rolling(cam, seed, t, X)
        if not (8 < uv[0] < cam.width - 9 and 8 < uv[1] < cam.height - 9):
            continue
        u0, v0 = int(round(uv[0])), int(round(uv[1]))
        win = diff[v0 - 7:v0 + 8, u0 - 7:u0 + 8]
        if win.sum() < 1000:  # hidden behind a box
            continue
        yy, xx = np.mgrid[v0 - 7:v0 + 8, u0 - 7:u0 + 8]
        errs.append(np.hypot((win * xx).sum() / win.sum() - uv[0], (win * yy).sum() / win.sum() - uv[1]))
    errs = np.array(errs)
    assert len(errs) >= 10
    assert np.median(errs) < 0.1 and np.mean(errs < 0.25) > 0.8


def test_rolling_shutter_rows_see_different_poses():
    """Panning right at 60 deg/s: with a 30 ms readout the bottom rows (captured later) are shifted
    left relative to the top rows by f * w * dt (vertical edges slant); not with a global shutter."""
    seed = 1
    scene = hd.desk_scene(seed)
    R0, p0 = hd.trajectory(seed, 5.0, np.array([0.0]))
    w = math.radians(60.0)

    def pan(t):
        t = np.atleast_1d(t)
        R = np.stack([R0[0] @ Rotation.from_rotvec([0.0, wt, 0.0]).as_matrix() for wt in w * t])
        return R, np.repeat(p0, len(t), axis=0)

    shifts = {}
    for readout in (0.0, 0.03):
        cam = hd.desk_camera(320, 240, exposure_s=0.0, readout_s=readout)
        still, _ = hd.render_image(scene, cam, lambda t: pan(np.zeros_like(np.atleast_1d(t))), 0.0)
        moving, _ = hd.render_image(scene, cam, pan, 0.0)
        band = []
        for r0 in (10, 180):
            a = np.float32(still[r0:r0 + 50]) * np.float32(cv2.createHanningWindow((320, 50), cv2.CV_32F))
            b = np.float32(moving[r0:r0 + 50]) * np.float32(cv2.createHanningWindow((320, 50), cv2.CV_32F))
            (dx, _), _ = cv2.phaseCorrelate(a, b)
            band.append(dx)
        shifts[readout] = band[1] - band[0]
    cam = hd.desk_camera(320, 240, readout_s=0.03)
    expected = -cam.fx * w * 0.03 * 170 / 240  # rows 35 -> 205, camera turning right (+y rotation)
    assert abs(shifts[0.0]) < 0.3
    assert abs(shifts[0.03] - expected) < 0.2 * abs(expected)


def test_motion_is_hand_held_and_keeps_the_desk_in_view():
    for seed in (0, 5):
        m = hd.desk_motion(seed)
        t = np.arange(0.0, 90.0, 0.01)
        v, w = hd._rates(m, t)
        assert v.max() <= 0.3 and math.degrees(w.max()) <= 60
        assert v.max() > 0.12 and math.degrees(w.max()) > 20  # it does move like a hand
        R, p = m.pose(t)
        assert p[:, 2].min() > 0.3 and p[:, 1].max() < -0.35  # above the desk, in front of the boxes
        d = R[:, :, 2]
        hit = p - (p[:, 2] / d[:, 2])[:, None] * d
        assert np.all(d[:, 2] < 0) and np.all(np.abs(hit[:, 0]) < 0.5) and np.all(np.abs(hit[:, 1]) < 0.35)
        for box in hd.desk_scene(seed).boxes:
            assert np.min(np.linalg.norm(p[:, :2] - box.centre, axis=1)) > 0.3
        # initialisation: 10-15 cm sideways in the first 2.3 s with little rotation
        i = int(2.3 / 0.01)
        shift = p[i] - p[0]
        assert 0.10 <= abs(shift[0]) <= 0.15 + 1e-9 and np.linalg.norm(shift[1:]) < 1e-9
        assert np.degrees(Rotation.from_matrix(R[0].T @ R[:i]).magnitude()).max() < 5
        # the pure rotation variant turns on the spot first
        R2, p2 = hd.trajectory(seed, 10.0, t[:i], pure_rotation_start=True)
        assert np.allclose(p2, p2[0]) and np.degrees(Rotation.from_matrix(R2[0].T @ R2[-1]).magnitude()) > 8


def test_texture_has_corners_at_quarter_resolution():
    for f in hd.frames(2, 6.0, 640, 480, start_index=110):
        quarter = cv2.pyrDown(cv2.pyrDown(f.image))
        corners = cv2.goodFeaturesToTrack(quarter, 500, 0.01, 3)
        assert corners is not None and len(corners) > 100
        full = cv2.goodFeaturesToTrack(f.image, 2000, 0.01, 5)
        assert len(full) > 400


def test_bag_topics_stamps_and_sidecar(tmp_path):
    out = tmp_path / 'desk.mcap'
    with BagWriter(out, storage='mcap') as bag:
        hd.write_handheld_desk_bag(bag, 7, 0.5, 'compressed', width=320, height=240)
    hd.write_sidecars(tmp_path / 'desk.params.yaml', out, 7)
    again = tmp_path / 'again.mcap'
    with BagWriter(again, storage='mcap') as bag:
        hd.write_handheld_desk_bag(bag, 7, 0.5, 'compressed', width=320, height=240)
    assert again.read_bytes() == out.read_bytes()
    side = yaml.safe_load((tmp_path / 'desk.params.yaml').read_text())
    assert side['keyframe_slam_mapper']['ros__parameters']['readout_s'] == pytest.approx(0.03)
    with BagReader(out) as bag:
        topics = bag.topics
        assert {'/camera/image_raw/compressed', '/camera/camera_info', '/ground_truth/pose',
                '/imu/data_raw', '/tf_static'} <= set(topics)
        imgs = [bag.deserialize(m) for m in bag.messages(['/camera/image_raw/compressed'])]
        infos = [bag.deserialize(m) for m in bag.messages(['/camera/camera_info'])]
        gt = [(m.log_time_ns, bag.deserialize(m)) for m in bag.messages(['/ground_truth/pose'])]
        imu = [bag.deserialize(m) for m in bag.messages(['/imu/data_raw'])]
    assert len(imgs) == len(infos) == 10 and len(gt) == 50 and len(imu) == 50
    cam_stamps = [stamp_to_ns(m.header.stamp) for m in imgs]
    assert cam_stamps[0] == START_NS and np.all(np.diff(cam_stamps) == 50_000_000)
    gt_stamps = {stamp_to_ns(m.header.stamp) for _, m in gt}
    assert set(cam_stamps) <= gt_stamps and all(log == stamp_to_ns(m.header.stamp) for log, m in gt)
    assert gt[0][1].header.frame_id == 'world'
    info = infos[0]
    cam = hd.desk_camera(320, 240)
    assert info.width == 320 and np.allclose(info.k, cam.K.ravel()) and info.distortion_model == 'plumb_bob'
    img = cv2.imdecode(np.frombuffer(imgs[3].data, np.uint8), cv2.IMREAD_UNCHANGED)
    frame = next(hd.frames(7, 0.5, 320, 240, start_index=3))
    assert np.array_equal(img, frame.image)
    # the pose at a camera stamp is the frame's pose
    m = next(m for _, m in gt if stamp_to_ns(m.header.stamp) == cam_stamps[3])
    q = m.pose.orientation
    assert np.allclose(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), frame.R_w_c, atol=1e-9)
    assert np.allclose([m.pose.position.x, m.pose.position.y, m.pose.position.z], frame.p_w_c)
    # still at the start: the accelerometer reads gravity
    acc = np.array([[i.linear_acceleration.x, i.linear_acceleration.y, i.linear_acceleration.z] for i in imu[:25]])
    assert abs(np.linalg.norm(acc.mean(0)) - 9.80665) < 0.2
