"""Annotation re-detection measures of an output bag (Langlotz 2011 sec. 6.1, Fig. 7).

The truth: ``/ground_truth/annotations`` (anchor positions relative to the authoring spot, ENU)
seen from where the browsing camera stands (``/ground_truth/orientation`` translation), rotated
into the browsing panorama frame with R_enu_pano = R_enu_cam(t) R_pano_cam(t)^T averaged over
the ``/panorama/orientation`` messages (ground truth interpolated to their stamps). The
placements: the TEXT markers of the last ``/annotations/markers`` array, matched to the truth by
their text. Measures (DESIGN sec. 8, area ``annotations``):

* ``redetection_rate``: share of the true annotations placed within 1 degree of the truth;
* ``wrong_rate``: share placed more than 1 degree off;
* ``time_to_first_s``: from the first panorama frame to the first array with a correct placement;
* also ``n``, ``placed``, ``matched``, ``inferred``, ``median_error_deg``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..core.rotations import nearest_rotation, quat_xyzw_to_matrix
from ..io.bags import BagReader

TOPIC_MARKERS = '/annotations/markers'
TOPIC_PANO = '/panorama/orientation'
TOPIC_GT = '/ground_truth/orientation'
TOPIC_GT_ANN = '/ground_truth/annotations'
CORRECT_DEG = 1.0


def _q(r: Any) -> np.ndarray:
    return np.array([r.x, r.y, r.z, r.w], float)


def evaluate_annotations(path: str | Path, correct_deg: float = CORRECT_DEG) -> dict[str, Any] | None:
    """The measures of the module docstring, or None when the bag has no annotation markers or
    no ground truth to score them."""
    from scipy.spatial.transform import Rotation, Slerp

    with BagReader(path) as bag:
        topics = bag.topics
        if TOPIC_MARKERS not in topics or not {TOPIC_GT, TOPIC_GT_ANN, TOPIC_PANO} <= set(topics):
            return None
        truth_ann = bag.read_all(TOPIC_GT_ANN)
        gt_t, gt_q, gt_p = [], [], []
        for m in bag.messages([TOPIC_GT]):
            tf = bag.deserialize(m)
            gt_t.append(m.log_time_ns)
            gt_q.append(_q(tf.transform.rotation))
            tr = tf.transform.translation
            gt_p.append((tr.x, tr.y, tr.z))
        pano = [(t, quat_xyzw_to_matrix(_q(m.transform.rotation))) for t, m in bag.read_all(TOPIC_PANO)]
        arrays = bag.read_all(TOPIC_MARKERS)
    if not truth_ann or not pano or len(gt_t) < 2:
        return None
    labels, positions = [], []
    for mk in truth_ann[0][1].markers:
        labels.append(mk.text)
        positions.append((mk.pose.position.x, mk.pose.position.y, mk.pose.position.z))
    order = np.argsort(gt_t)
    gt_t_arr = np.asarray(gt_t)[order]
    slerp = Slerp(gt_t_arr.astype(float), Rotation.from_quat(np.asarray(gt_q)[order]))
    inside = [(t, R) for t, R in pano if gt_t_arr[0] <= t <= gt_t_arr[-1]]
    if not inside:
        return None
    R_enu_cam = slerp([float(t) for t, _ in inside]).as_matrix()
    R_enu_pano = nearest_rotation(np.sum([Rc @ Rp.T for Rc, (_, Rp) in zip(R_enu_cam, inside)], axis=0))
    spot = np.asarray(gt_p)[order][int(np.searchsorted(gt_t_arr, inside[0][0]).clip(0, len(gt_t_arr) - 1))]
    truth = {}
    for label, p in zip(labels, positions):
        d = np.asarray(p, float) - spot
        truth[label] = R_enu_pano.T @ (d / np.linalg.norm(d))
    t0 = pano[0][0]

    def placements(msg: Any) -> dict[str, tuple[float, str]]:
        out = {}
        for mk in msg.markers:
            if mk.action != 0 or mk.text not in truth:
                continue
            d = np.array([mk.pose.position.x, mk.pose.position.y, mk.pose.position.z])
            n = np.linalg.norm(d)
            if not np.isfinite(n) or n == 0:
                continue
            err = float(np.degrees(np.arccos(np.clip(d / n @ truth[mk.text], -1.0, 1.0))))
            out[mk.text] = (err, mk.ns)
        return out

    first = None
    for _, msg in arrays:
        pl = placements(msg)
        if any(e <= correct_deg for e, _ in pl.values()):
            first = (int(msg.markers[-1].header.stamp.sec) * 1_000_000_000 + int(msg.markers[-1].header.stamp.nanosec)
                     if msg.markers else None)
            break
    final = placements(arrays[-1][1]) if arrays else {}
    n = len(truth)
    errors = [e for e, _ in final.values()]
    return {
        'redetection_rate': round(sum(e <= correct_deg for e in errors) / n, 4),
        'wrong_rate': round(sum(e > correct_deg for e in errors) / n, 4),
        'time_to_first_s': round((first - t0) * 1e-9, 3) if first is not None else None,
        'n': n,
        'placed': len(final),
        'matched': sum(s == 'matched' for _, s in final.values()),
        'inferred': sum(s == 'inferred' for _, s in final.values()),
        'median_error_deg': round(float(np.median(errors)), 3) if errors else None,
        'errors_deg': {k: round(v[0], 3) for k, v in sorted(final.items())},
    }
