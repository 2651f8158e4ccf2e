"""SLAM core on the handheld_desk scenario: dropped frames, a textureless interval and recovery."""
from __future__ import annotations

import numpy as np
import pytest

from ar_tracking.core.slam.system import SlamSystem
from ar_tracking.sim import handheld_desk
from slam_synth import umeyama_sim3

W, H = 320, 240
TRACKED = ('tracking', 'relocalised')


@pytest.fixture(scope='module')
def frames():
    return list(handheld_desk.frames(1, 5.0, W, H))


def _camera():
    return handheld_desk.desk_camera(W, H).slam_camera()


def _position_error_after_alignment(est: np.ndarray, truth: np.ndarray) -> float:
    """RMS position error after a similarity alignment (Umeyama), in truth units."""
    sc, R, t = umeyama_sim3(est, truth)
    return float(np.sqrt((((sc * est @ R.T + t) - truth) ** 2).sum(1).mean()))


def _replay(system: SlamSystem, frames, skipped, white):
    """Feed the frames to the system, leaving out ``skipped`` and replacing ``white`` ones by a
    textureless image; yields (index, frame, result, keyframes before it)."""
    for k, f in enumerate(frames):
        if k in skipped:
            continue
        img = np.full((H, W), 250, np.uint8) if k in white else f.image
        before = len(system.map.keyframes)
        res = system.process(img, int(f.stamp_ns) + 1)
        system.wait_for_mapping()
        yield k, f, res, before


def _assert_within_one_percent_of_the_path(est: list, truth: list) -> None:
    est, truth = np.array(est), np.array(truth)
    path = float(np.linalg.norm(np.diff(truth, axis=0), axis=1).sum())
    assert _position_error_after_alignment(est, truth) < 0.01 * path


def test_dropped_frames_and_a_white_wall_do_not_break_tracking(frames):
    dropped = set(range(60, 66))            # 300 ms without frames (after initialisation at ~2 s)
    white = set(range(75, 80))              # a textureless interval
    states: dict[int, str] = {}
    est, truth = [], []
    with SlamSystem(_camera()) as system:
        for k, f, res, keyframes_before in _replay(system, frames, dropped, white):
            states[k] = res.state
            if k in white:
                assert res.R_c_w is None and res.state not in TRACKED
                assert not res.keyframe_added and len(system.map.keyframes) == keyframes_before
            elif res.state in TRACKED:
                est.append(-res.R_c_w.T @ res.t_c_w)
                truth.append(f.p_w_c)
    assert states[59] in TRACKED, 'initialised and tracking before the gap'
    assert states[66] in TRACKED, 'the frame right after 300 ms of dropped frames is tracked'
    assert sum(states[k] in TRACKED for k in range(80, 90)) >= 8, 'tracking comes back after the white frames'
    assert all(states[k] in TRACKED for k in range(90, len(frames)))
    _assert_within_one_percent_of_the_path(est, truth)


def test_relocalises_after_a_long_gap_in_another_place():
    """4.5 s without frames (the camera moved on) then white frames: lost, then relocalised
    against the keyframes (Klein & Murray's keyframe relocaliser), on the same map and scale."""
    frames = list(handheld_desk.frames(1, 20.0, W, H))
    gap, white = range(200, 290), range(290, 295)
    states: dict[int, str] = {}
    est, truth = [], []
    with SlamSystem(_camera()) as system:
        for k, f, res, _ in _replay(system, frames, gap, white):
            states[k] = res.state
            if res.state in TRACKED and k not in white:
                est.append(-res.R_c_w.T @ res.t_c_w)
                truth.append(f.p_w_c)
        relocalised = system.tracker.stats['relocalised']
    assert relocalised >= 1
    assert all(states[k] in TRACKED for k in range(310, len(frames)))
    _assert_within_one_percent_of_the_path(est, truth)
