"""evaluate_annotations on a small synthetic output bag with known placements."""
from __future__ import annotations

import numpy as np

from ar_tracking.core.rotations import rot_y, rot_z
from ar_tracking.eval.annotation_metrics import evaluate_annotations
from ar_tracking.io.bags import BagWriter
from ar_tracking.sim.bagmaker import _Msgs
from bagfactory import truth_msg

T0 = 1_700_000_000_000_000_000
LABELS = ['door', 'sign', 'window']
POS = [np.array([10.0, 20.0, 1.0]), np.array([-15.0, 5.0, 3.0]), np.array([0.0, -30.0, 2.0])]


def write(path, placements_per_array, log_delay_ns: int = 0, ns: str = 'matched', rate_rad_s: float = 1.0):
    """Truth, panorama orientations and marker arrays (one every 0.2 s); every message is logged
    ``log_delay_ns`` after its header stamp (a recorder that stamps on arrival)."""
    m = _Msgs()
    R_enu_pano = rot_z(0.3) @ rot_y(0.1)
    with BagWriter(path) as bag:
        bag.write('/ground_truth/annotations', T0, m.markers(T0, LABELS, POS))
        for k in range(100):
            t = T0 + k * 10_000_000
            R_pano_cam = rot_y(rate_rad_s * 0.01 * k)
            bag.write('/ground_truth/orientation', t, truth_msg(t, R_enu_pano @ R_pano_cam))
            if k % 3 == 0:
                bag.write('/panorama/orientation', t + log_delay_ns, truth_msg(t, R_pano_cam))
        for j, placements in enumerate(placements_per_array):
            t = T0 + (j + 1) * 200_000_000
            labels = list(placements)
            dirs = [R_enu_pano.T @ placements[name] * 10.0 for name in labels]
            arr = m.markers(t, labels, dirs)
            for mk in arr.markers:
                mk.ns = ns
            bag.write('/annotations/markers', t + log_delay_ns, arr)
    return path


def unit(v):
    return v / np.linalg.norm(v)


def test_rates_and_time_to_first(tmp_path):
    off = rot_z(np.radians(2.0))
    first = {'door': unit(off @ POS[0])}  # 2 deg off: wrong
    final = {'door': unit(POS[0]), 'sign': unit(off @ POS[1])}  # window never placed
    m = evaluate_annotations(write(tmp_path / 'o.mcap', [first, final]))
    assert m['n'] == 3 and m['placed'] == 2 and m['matched'] == 2
    assert m['redetection_rate'] == round(1 / 3, 4) and m['wrong_rate'] == round(1 / 3, 4)
    assert m['time_to_first_s'] == 0.4  # the second array, 0.4 s after the first panorama frame
    assert m['errors_deg']['door'] < 0.01 and 1.9 < m['errors_deg']['sign'] < 2.1


def test_no_markers_means_no_area(tmp_path):
    path = tmp_path / 'n.mcap'
    with BagWriter(path) as bag:
        bag.write('/ground_truth/orientation', T0, truth_msg(T0, np.eye(3)))
    assert evaluate_annotations(path) is None


def test_pairing_is_by_header_stamp_not_log_time(tmp_path):
    """Logged 33 ms after capture while turning at 1 rad/s: correct labels stay correct (log-time
    pairing put them ~1.9 deg off) and the time to the first correct one is the stamps'."""
    final = {'door': unit(POS[0]), 'sign': unit(POS[1])}
    m = evaluate_annotations(write(tmp_path / 'd.mcap', [final], log_delay_ns=33_000_000))
    assert m['redetection_rate'] == round(2 / 3, 4) and m['wrong_rate'] == 0.0
    assert max(m['errors_deg'].values()) < 0.01
    assert m['time_to_first_s'] == 0.2


def test_wrong_label_time_share_weighs_labels_by_the_time_shown(tmp_path):
    off = rot_z(np.radians(2.0))
    arrays = [{'door': unit(off @ POS[0]), 'sign': unit(POS[1])},  # 0.2-0.4 s: 1 of 2 wrong
              {'door': unit(POS[0]), 'sign': unit(POS[1])}]  # 0.4-0.99 s (last panorama frame): right
    m = evaluate_annotations(write(tmp_path / 'w.mcap', arrays))
    shown = 2 * 0.2 + 2 * 0.59
    assert abs(m['label_time_s'] - shown) < 1e-6
    assert m['wrong_label_time_share'] == round(0.2 / shown, 4)
    assert m['redetection_rate'] == round(2 / 3, 4)


def test_approximate_labels_are_not_placements(tmp_path):
    m = evaluate_annotations(write(tmp_path / 'a.mcap', [{'door': unit(POS[0])}], ns='approximate'))
    assert m['placed'] == 0 and m['approximate'] == 1 and m['redetection_rate'] == 0.0
    assert m['wrong_label_time_share'] is None and m['time_to_first_s'] is None


def test_label_timeline_figure(tmp_path):
    from ar_tracking.eval.annotation_figures import label_timeline
    from ar_tracking.eval.annotation_metrics import label_timeline as data

    off = rot_z(np.radians(2.0))
    bag = write(tmp_path / 't.mcap', [{'door': unit(off @ POS[0])}, {'door': unit(POS[0]), 'sign': unit(POS[1])}])
    t0, t_end, labels, spans = data(bag)
    assert labels == sorted(LABELS) and len(spans) == 2 and spans[0][2]['door'][0] > 1.9
    png = label_timeline(bag, tmp_path / 't.png')
    assert png is not None and png.stat().st_size > 5_000
    assert label_timeline(write(tmp_path / 'e.mcap', []), tmp_path / 'e.png') is None  # no markers: no figure


def test_scores_only_the_given_labels(tmp_path):
    """``labels``: the anchors the user could annotate; the others are neither missed nor counted."""
    final = {'door': unit(POS[0]), 'sign': unit(POS[1])}  # window not annotated
    m = evaluate_annotations(write(tmp_path / 'l.mcap', [final]), labels=['door', 'sign'])
    assert m['n'] == 2 and m['anchors'] == 3 and m['redetection_rate'] == 1.0 and m['wrong_rate'] == 0.0


def _turning_bag(path, spot, lever_m, labels_dirs_from):
    """A full turn about the vertical with the camera ``lever_m`` in front of the turning axis at
    ``spot`` (the images of a sweep are rendered from the spot); one marker array with every
    anchor placed at its direction from ``labels_dirs_from``."""
    m = _Msgs()
    R_enu_cam0 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # x east, y down, z north
    with BagWriter(path) as bag:
        bag.write('/ground_truth/annotations', T0, m.markers(T0, LABELS, POS))
        for k in range(100):
            t = T0 + k * 10_000_000
            R_pano_cam = rot_y(2 * np.pi * k / 100)
            R_enu_cam = R_enu_cam0 @ R_pano_cam
            h = R_enu_cam[:2, 2] / np.linalg.norm(R_enu_cam[:2, 2])
            tf = truth_msg(t, R_enu_cam)
            c = spot + lever_m * np.array([h[0], h[1], 0.0])
            tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = (float(x) for x in c)
            bag.write('/ground_truth/orientation', t, tf)
            bag.write('/panorama/orientation', t, truth_msg(t, R_pano_cam))
        dirs = [R_enu_cam0.T @ unit(p - labels_dirs_from) * 10.0 for p in POS]
        arr = m.markers(T0 + 500_000_000, LABELS, dirs)
        for mk in arr.markers:
            mk.ns = 'matched'
        bag.write('/annotations/markers', T0 + 500_000_000, arr)
    return path


def test_truth_is_seen_from_the_standing_spot_not_the_camera_on_its_lever_arm(tmp_path):
    """The camera 0.3 m in front of the turning axis: labels placed as seen from the spot (where
    the frames are rendered from) are right; the first frame's camera position is not the truth."""
    from ar_tracking.eval.annotation_metrics import standing_spot

    spot = np.array([1.0, -0.5, 0.2])
    m = evaluate_annotations(_turning_bag(tmp_path / 's.mcap', spot, 0.3, spot))
    assert m['redetection_rate'] == 1.0 and max(m['errors_deg'].values()) < 0.01
    first_camera = spot + np.array([0.0, 0.3, 0.0])  # heading north at the first frame
    m = evaluate_annotations(_turning_bag(tmp_path / 'c.mcap', spot, 0.3, first_camera))
    assert max(m['errors_deg'].values()) > 0.3
    # the fit itself, and its fallback (the mean) when the heading barely changes
    t = np.linspace(0, 2 * np.pi, 50)
    h = np.stack([np.sin(t), np.cos(t), 0 * t], 1)
    R = np.zeros((50, 3, 3))
    R[:, :, 2] = h
    assert np.allclose(standing_spot(spot + 0.3 * h, R), spot, atol=1e-6)
    assert np.allclose(standing_spot(spot + 0.3 * h[:5], R[:5]), (spot + 0.3 * h[:5]).mean(0))


def test_simulated_user_clicks_only_on_what_the_panorama_saw_from_the_spot(tmp_path):
    """A quarter turn from north to east with the camera 0.3 m on its lever arm: the anchor to the
    north-east is offered at its direction from the spot, the one to the south (never in a frame)
    is not."""
    from ar_tracking.eval.annotation_metrics import simulated_user_positions
    from ar_tracking.sim.world import PinholeCamera

    m = _Msgs()
    cam = PinholeCamera()
    spot = np.array([0.5, 0.2, 0.0])
    anchors = [np.array([20.0, 20.0, 1.0]), np.array([0.0, -30.0, 1.0])]
    R_enu_cam0 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # facing north
    path = tmp_path / 'u.mcap'
    with BagWriter(path) as bag:
        bag.write('/ground_truth/annotations', T0, m.markers(T0, ['ne', 'south'], anchors))
        for k in range(31):
            t = T0 + k * 33_333_333
            R_enu_cam = R_enu_cam0 @ rot_y(np.pi / 2 * k / 30)
            h = R_enu_cam[:2, 2] / np.linalg.norm(R_enu_cam[:2, 2])
            tf = truth_msg(t, R_enu_cam)
            c = spot + 0.3 * np.array([h[0], h[1], 0.0])
            tf.transform.translation.x, tf.transform.translation.y, tf.transform.translation.z = (float(x) for x in c)
            bag.write('/ground_truth/orientation', t, tf)
            bag.write('/camera/camera_info', t, m.camera_info(t, cam))
    rows = simulated_user_positions(path)(T0)
    assert [r.text for r in rows] == ['ne']
    d = R_enu_cam0.T @ (anchors[0] - spot)  # from the spot, in the panorama (first camera) frame
    assert abs(rows[0].a - np.degrees(np.arctan2(d[0], d[2]))) < 0.01
    assert abs(rows[0].b - np.degrees(np.arctan2(-d[1], np.hypot(d[0], d[2])))) < 0.01
