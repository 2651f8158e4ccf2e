"""Tracker and SlamSystem end to end on the synthetic desk (Klein & Murray 2009 sec. 4, 5)."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.slam.initialiser import WAIT_ROTATION_MSG
from ar_tracking.core.slam.system import SlamConfig, SlamSystem
from slam_synth import DeskScene, look_at, make_camera, sideways_then_6dof, umeyama_sim3

DT = 50_000_000


def test_bad_input_is_lost_and_map_untouched() -> None:
    cam = make_camera(320, 240)
    with SlamSystem(cam, SlamConfig(threaded=False)) as s:
        for img, word in ((np.zeros((100, 100), np.uint8), 'match'),
                          (np.zeros((240, 320), np.float32), 'uint8'),
                          (np.zeros((240, 320, 3), np.uint8), 'single-channel'),
                          (np.full((240, 320), 90, np.uint8), 'textureless'),
                          ('not an image', 'array')):
            r = s.process(img, 0)
            assert r.state == 'lost' and word in r.message and r.R_c_w is None
        assert len(s.map.keyframes) == 0 and len(s.map.points) == 0
        assert s.stats()['bad_input'] == 5


def test_initialises_and_tracks_6dof() -> None:
    cam = make_camera(320, 240)
    scene = DeskScene(0)
    poses = sideways_then_6dof(n_side=30, n_free=40, seed=3)
    gt, est, states = [], [], []
    with SlamSystem(cam, SlamConfig(threaded=False)) as s:
        for i, (R, t) in enumerate(poses):
            r = s.process(scene.render(cam, R, t, supersample=2), i * DT)
            states.append(r.state)
            if r.state in ('tracking', 'relocalised'):
                gt.append(-R.T @ t)
                est.append(-r.R_c_w.T @ r.t_c_w)
        st = s.stats()
        assert len(s.keyframe_poses()) >= 3 and len(s.map_points()) > 50
        assert len(s.path) == len(est)
    first = states.index('tracking')
    assert first < 30
    assert 'lost' not in states[first:]
    gt, est = np.array(gt), np.array(est)
    sc, Ra, ta = umeyama_sim3(est, gt)
    err = np.linalg.norm(sc * est @ Ra.T + ta - gt, axis=1)
    length = np.sum(np.linalg.norm(np.diff(gt, axis=0), axis=1))
    assert np.sqrt(np.mean(err ** 2)) < 0.02 * length
    assert st['keyframes_added'] >= 1 and st['waited_on_mapper'] >= 0


def test_pure_rotation_start_waits() -> None:
    cam = make_camera(320, 240)
    scene = DeskScene(0)
    eye = np.array([0.0, -0.15, 0.5])
    with SlamSystem(cam, SlamConfig(threaded=False)) as s:
        res = [s.process(scene.render(cam, *look_at(eye, np.array([0.12 * np.sin(a), 0, 0])), supersample=2), i * DT)
               for i, a in enumerate(np.linspace(0, 1.2, 20))]
        assert len(s.map.keyframes) == 0
    assert res[-1].state == 'waiting' and res[-1].message == WAIT_ROTATION_MSG
