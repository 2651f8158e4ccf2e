"""Annotation re-detection measures of an output bag (Langlotz 2011 sec. 6.1, Fig. 7).

Everything is paired by header stamp (the capture time), never by bag log time: the truth
``/ground_truth/orientation`` (enu -> camera, with the camera position) is slerped to the
``/panorama/orientation`` stamps, R_enu_pano = R_enu_cam(t) R_pano_cam(t)^T averaged over them
(chordal mean), and the ``/ground_truth/annotations`` anchors (ENU) are seen from where the
browsing camera stands at the first panorama frame, in the browsing panorama frame. The
placements: the TEXT markers of each ``/annotations/markers`` array, matched to the truth by
their text. Labels in the ``approximate`` namespace (shown marked as uncertain, before the
alignment is supported) are not counted as placements. Measures (DESIGN sec. 8, area
``annotations``):

* ``redetection_rate`` / ``wrong_rate``: share of the true annotations placed (last array)
  within / more than 1 degree off the truth;
* ``time_to_first_s``: from the first panorama frame to the first array with a correct placement;
* ``wrong_label_time_share``: what a user sees - each array is on screen from its stamp to the
  next one's (the last until the last panorama frame); of the label-time shown (labels x
  seconds, ``label_time_s``), the share with the label more than 1 degree off;
* also ``n``, ``placed``, ``matched``, ``inferred``, ``approximate``, ``median_error_deg``.

:func:`simulated_user_positions` is the evaluation's stand-in for a user who clicks on the
anchors in the authoring panorama (the truth says where they appear); it is what
``ar-tracking annotate --simulated-user`` uses - the authoring code itself never reads the truth.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..core.rotations import nearest_rotation, quat_xyzw_to_matrix
from ..io.bags import BagReader

TOPIC_MARKERS = '/annotations/markers'
TOPIC_PANO = '/panorama/orientation'
TOPIC_GT = '/ground_truth/orientation'
TOPIC_GT_ANN = '/ground_truth/annotations'
CORRECT_DEG = 1.0
#: Namespaces of the labels a user is shown as placed (``approximate`` ones are marked uncertain).
CONFIDENT_NS = ('matched', 'inferred')


def _q(r: Any) -> np.ndarray:
    return np.array([r.x, r.y, r.z, r.w], float)


def _ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


class _Truth:
    """The ground-truth orientation and position, slerped / interpolated at header stamps."""

    def __init__(self, samples: list[tuple[int, np.ndarray, tuple[float, float, float]]]) -> None:
        from scipy.spatial.transform import Rotation, Slerp

        samples = sorted(samples, key=lambda s: s[0])
        self.t = np.array([s[0] for s in samples], np.int64)
        self.p = np.array([s[2] for s in samples], float)
        self.slerp = Slerp(self.t.astype(float), Rotation.from_quat(np.array([s[1] for s in samples])))

    def inside(self, t: int) -> bool:
        return bool(self.t[0] <= t <= self.t[-1])

    def R(self, ts: list[int]) -> np.ndarray:
        return self.slerp(np.asarray(ts, float)).as_matrix()

    def position(self, t: int) -> np.ndarray:
        return np.array([np.interp(float(t), self.t.astype(float), self.p[:, i]) for i in range(3)])


def _read_truth(bag: BagReader) -> _Truth | None:
    samples = []
    for _, tf in bag.read_all(TOPIC_GT):
        tr = tf.transform.translation
        samples.append((_ns(tf.header), _q(tf.transform.rotation), (tr.x, tr.y, tr.z)))
    return _Truth(samples) if len(samples) >= 2 else None


def _anchors(bag: BagReader) -> tuple[list[str], np.ndarray]:
    msgs = bag.read_all(TOPIC_GT_ANN)
    if not msgs:
        return [], np.zeros((0, 3))
    labels = [mk.text for mk in msgs[0][1].markers]
    pos = np.array([(mk.pose.position.x, mk.pose.position.y, mk.pose.position.z) for mk in msgs[0][1].markers], float)
    return labels, pos.reshape(-1, 3)


def _scored_arrays(path: str | Path) -> tuple[int, int, dict[str, np.ndarray], list[tuple[int, Any]]] | None:
    """(first and last panorama stamp, truth direction per label in the browsing panorama frame,
    the marker arrays sorted by stamp), or None without what scoring needs."""
    with BagReader(path) as bag:
        topics = bag.topics
        if TOPIC_MARKERS not in topics or not {TOPIC_GT, TOPIC_GT_ANN, TOPIC_PANO} <= set(topics):
            return None
        labels, positions = _anchors(bag)
        truth_rot = _read_truth(bag)
        pano = [(_ns(m.header), quat_xyzw_to_matrix(_q(m.transform.rotation))) for _, m in bag.read_all(TOPIC_PANO)]
        arrays = [m for _, m in bag.read_all(TOPIC_MARKERS)]
    if not labels or not pano or truth_rot is None:
        return None
    pano.sort(key=lambda x: x[0])
    inside = [(t, R) for t, R in pano if truth_rot.inside(t)]
    if not inside:
        return None
    R_enu_cam = truth_rot.R([t for t, _ in inside])
    R_enu_pano = nearest_rotation(np.sum([Rc @ Rp.T for Rc, (_, Rp) in zip(R_enu_cam, inside)], axis=0))
    spot = truth_rot.position(inside[0][0])
    truth = {}
    for label, p in zip(labels, positions):
        d = np.asarray(p, float) - spot
        truth[label] = R_enu_pano.T @ (d / np.linalg.norm(d))
    stamped = sorted(((_ns(m.markers[0].header), m) for m in arrays if m.markers), key=lambda x: x[0])
    return pano[0][0], pano[-1][0], truth, stamped


def label_states(msg: Any, truth: dict[str, np.ndarray]) -> dict[str, tuple[float, str]]:
    """label -> (error in deg, namespace) of every ADD marker of one array whose text is a true
    label (approximate ones included)."""
    out = {}
    for mk in msg.markers:
        if mk.action != 0 or mk.text not in truth:
            continue
        d = np.array([mk.pose.position.x, mk.pose.position.y, mk.pose.position.z])
        n = np.linalg.norm(d)
        if not np.isfinite(n) or n == 0:
            continue
        out[mk.text] = (float(np.degrees(np.arccos(np.clip(d / n @ truth[mk.text], -1.0, 1.0)))), mk.ns)
    return out


def label_timeline(path: str | Path) -> tuple[int, int, list[str], list[tuple[int, int, dict[str, tuple[float, str]]]]] | None:
    """(first panorama stamp, last, the true labels, [(from, to, label -> (error deg, ns))]): what
    was on screen when (each array until the next one, the last until the last panorama frame)."""
    got = _scored_arrays(path)
    if got is None:
        return None
    t0, t_end, truth, stamped = got
    spans = []
    for k, (t, msg) in enumerate(stamped):
        t_next = stamped[k + 1][0] if k + 1 < len(stamped) else max(t_end, t)
        spans.append((t, t_next, label_states(msg, truth)))
    return t0, t_end, sorted(truth), spans


def evaluate_annotations(path: str | Path, correct_deg: float = CORRECT_DEG) -> dict[str, Any] | None:
    """The measures of the module docstring, or None when the bag has no annotation markers or
    no ground truth to score them."""
    got = _scored_arrays(path)
    if got is None:
        return None
    t0, t_end, truth, stamped = got

    def placements(msg: Any) -> tuple[dict[str, tuple[float, str]], int]:
        states = label_states(msg, truth)
        shown = {k: v for k, v in states.items() if v[1] in CONFIDENT_NS}
        return shown, len(states) - len(shown)

    first = None
    shown_s = wrong_s = 0.0
    for k, (t, msg) in enumerate(stamped):
        pl, _ = placements(msg)
        if first is None and any(e <= correct_deg for e, _ in pl.values()):
            first = t
        t_next = stamped[k + 1][0] if k + 1 < len(stamped) else max(t_end, t)
        dt = max(0, t_next - t) * 1e-9
        shown_s += dt * len(pl)
        wrong_s += dt * sum(e > correct_deg for e, _ in pl.values())
    final, approx = placements(stamped[-1][1]) if stamped else ({}, 0)
    n = len(truth)
    errors = [e for e, _ in final.values()]
    return {
        'redetection_rate': round(sum(e <= correct_deg for e in errors) / n, 4),
        'wrong_rate': round(sum(e > correct_deg for e in errors) / n, 4),
        'time_to_first_s': round((first - t0) * 1e-9, 3) if first is not None else None,
        'wrong_label_time_share': round(wrong_s / shown_s, 4) if shown_s > 0 else None,
        'label_time_s': round(shown_s, 3),
        'n': n,
        'placed': len(final),
        'matched': sum(s == 'matched' for _, s in final.values()),
        'inferred': sum(s == 'inferred' for _, s in final.values()),
        'approximate': approx,
        'median_error_deg': round(float(np.median(errors)), 3) if errors else None,
        'errors_deg': {k: round(v[0], 3) for k, v in sorted(final.items())},
    }


def simulated_user_positions(bag_path: str | Path) -> Callable[[int], list[Any]]:
    """Evaluation only: a function of the authoring panorama's first-frame stamp (ns) giving the
    ``azel`` positions (panorama frame) where the simulator's anchors appear in that panorama -
    a user who clicks exactly on them. Reads ``/ground_truth/orientation`` and
    ``/ground_truth/annotations`` of the authoring bag (header stamps)."""
    from ..annotate import Position
    from ..io.bags import BagError

    with BagReader(bag_path) as bag:
        if not {TOPIC_GT, TOPIC_GT_ANN} <= set(bag.topics):
            raise BagError(f'{bag_path}: --simulated-user needs {TOPIC_GT} and {TOPIC_GT_ANN} (a simulated bag)')
        labels, positions = _anchors(bag)
        truth = _read_truth(bag)
    if truth is None or not labels:
        raise BagError(f'{bag_path}: no ground-truth anchors or orientation to simulate the user with')

    def at(first_stamp_ns: int) -> list[Any]:
        R_enu_pano = truth.R([first_stamp_ns])[0]  # the panorama frame is the first frame's camera
        spot = truth.position(first_stamp_ns)
        out = []
        for label, p in zip(labels, positions):
            d = R_enu_pano.T @ (p - spot)
            out.append(Position(label, math.degrees(math.atan2(d[0], d[2])),
                                math.degrees(math.atan2(-d[1], math.hypot(d[0], d[2]))), 'azel'))
        return out
    return at
