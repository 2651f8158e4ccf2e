"""Annotation re-detection measures of an output bag (Langlotz 2011 sec. 6.1, Fig. 7).

Everything is paired by header stamp (the capture time), never by bag log time: the truth
``/ground_truth/orientation`` (enu -> camera, with the camera position) is slerped to the
``/panorama/orientation`` stamps, R_enu_pano = R_enu_cam(t) R_pano_cam(t)^T averaged over them
(chordal mean), and the ``/ground_truth/annotations`` anchors (ENU) are seen, in the browsing
panorama frame, from the browsing session's standing spot (:func:`standing_spot`): the images
of a sweep are rendered from the spot where the person turns (the simulator renders by
rotation only, sim/rotation_sweep.py), while the camera position of the truth also carries the
phone's lever arm in front of the turning axis (0.2-0.4 m, hard profile) and the hand's sway; an
anchor 30-40 m away seen from the camera position instead of the spot is up to 0.4-0.8 deg off
where every frame and the map show it. The placements: the TEXT markers of each ``/annotations/markers`` array, matched to the truth by
their text. Labels in the ``approximate`` namespace (shown marked as uncertain, before the
alignment is supported) are not counted as placements. Measures (DESIGN sec. 8, area
``annotations``):

* ``redetection_rate`` / ``wrong_rate``: share of the true annotations placed (last array)
  within / more than 1 degree off the truth;
* ``time_to_first_s``: from the first panorama frame to the first array with a correct placement;
* ``wrong_label_time_share``: what a user sees - each array is on screen from its stamp to the
  next one's (the last until the last panorama frame); of the label-time shown (labels x
  seconds, ``label_time_s``), the share with the label more than 1 degree off;
* ``labels`` (optional): score only these anchors - the ones the user could annotate (what the
  authoring store holds); ``n`` counts them, ``anchors`` every anchor of the bag;
* also ``n``, ``placed``, ``matched``, ``inferred``, ``approximate``, ``median_error_deg``.

:func:`simulated_user_positions` is the evaluation's stand-in for a user who clicks on the
anchors in the authoring panorama (the truth says where they appear): only on anchors that a
frame of the authoring panorama saw (a user can only click on what the panorama shows), at the
direction seen from the authoring spot. It is what ``ar-tracking annotate --simulated-user``
uses - the authoring code itself never reads the truth.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable, Iterable

import numpy as np

from ..core.rotations import interpolate_rotations, nearest_rotation, quat_xyzw_to_matrix
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
        samples = sorted(samples, key=lambda s: s[0])
        self.t = np.array([s[0] for s in samples], np.int64)
        self.p = np.array([s[2] for s in samples], float)
        self.R_samples = quat_xyzw_to_matrix(np.array([s[1] for s in samples]))

    def inside(self, t: int) -> bool:
        return bool(self.t[0] <= t <= self.t[-1])

    def R(self, ts: list[int]) -> np.ndarray:
        R, inside = interpolate_rotations(self.t.astype(float), self.R_samples, np.asarray(ts, float))
        if not inside.all():
            raise ValueError('truth orientation asked outside its time span')
        return R

    def standing_spot(self) -> np.ndarray:
        """:func:`standing_spot` of these samples."""
        return standing_spot(self.p, self.R(list(self.t)))


def standing_spot(positions: np.ndarray, R_enu_cam: np.ndarray, min_turn_deg: float = 60.0) -> np.ndarray:
    """Where the person stands: the turning axis of a sweep, from the true camera positions
    (N, 3) and orientations (N, 3, 3; optical axis z). The phone is held a lever arm L in front
    of the axis, along the horizontal heading h(t) of the optical axis: c(t) = spot + L h(t) +
    the hand's zero-mean sway; (spot_e, spot_n, L) by least squares, the height the mean. With
    less than ``min_turn_deg`` of heading covered the fit is ill-posed: the mean position."""
    p = np.asarray(positions, float).reshape(-1, 3)
    z = np.asarray(R_enu_cam, float).reshape(-1, 3, 3)[:, :, 2]
    h = z[:, :2]
    norm = np.linalg.norm(h, axis=1)
    ok = norm > 1e-6
    spot = p.mean(axis=0)
    if ok.sum() < 3:
        return spot
    h = h[ok] / norm[ok, None]
    heading = np.unwrap(np.arctan2(h[:, 0], h[:, 1]))
    if np.degrees(np.ptp(heading)) < min_turn_deg:
        return spot
    A = np.zeros((2 * len(h), 3))
    A[0::2, 0] = 1.0
    A[1::2, 1] = 1.0
    A[:, 2] = h.reshape(-1)
    x, *_ = np.linalg.lstsq(A, p[ok, :2].reshape(-1), rcond=None)
    return np.array([x[0], x[1], spot[2]])


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


def _scored_arrays(path: str | Path, labels_wanted: Iterable[str] | None = None
                   ) -> tuple[int, int, dict[str, np.ndarray], list[tuple[int, Any]], int] | None:
    """(first and last panorama stamp, truth direction per label in the browsing panorama frame,
    the marker arrays sorted by stamp, the number of anchors in the bag), or None without what
    scoring needs. ``labels_wanted``: keep only these anchors."""
    with BagReader(path) as bag:
        topics = bag.topics
        if TOPIC_MARKERS not in topics or not {TOPIC_GT, TOPIC_GT_ANN, TOPIC_PANO} <= set(topics):
            return None
        labels, positions = _anchors(bag)
        truth_rot = _read_truth(bag)
        pano = [(_ns(m.header), quat_xyzw_to_matrix(_q(m.transform.rotation))) for _, m in bag.read_all(TOPIC_PANO)]
        arrays = [m for _, m in bag.read_all(TOPIC_MARKERS)]
    n_anchors = len(labels)
    if labels_wanted is not None:
        keep = set(labels_wanted)
        idx = [i for i, lab in enumerate(labels) if lab in keep]
        labels, positions = [labels[i] for i in idx], positions[idx].reshape(-1, 3)
    if not labels or not pano or truth_rot is None:
        return None
    pano.sort(key=lambda x: x[0])
    inside = [(t, R) for t, R in pano if truth_rot.inside(t)]
    if not inside:
        return None
    R_enu_cam = truth_rot.R([t for t, _ in inside])
    R_enu_pano = nearest_rotation(np.sum([Rc @ Rp.T for Rc, (_, Rp) in zip(R_enu_cam, inside)], axis=0))
    spot = truth_rot.standing_spot()
    truth = {}
    for label, p in zip(labels, positions):
        d = np.asarray(p, float) - spot
        truth[label] = R_enu_pano.T @ (d / np.linalg.norm(d))
    stamped = sorted(((_ns(m.markers[0].header), m) for m in arrays if m.markers), key=lambda x: x[0])
    return pano[0][0], pano[-1][0], truth, stamped, n_anchors


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


def label_timeline(path: str | Path, labels: Iterable[str] | None = None
                   ) -> tuple[int, int, list[str], list[tuple[int, int, dict[str, tuple[float, str]]]]] | None:
    """(first panorama stamp, last, the true labels, [(from, to, label -> (error deg, ns))]): what
    was on screen when (each array until the next one, the last until the last panorama frame),
    ``labels``: only these anchors."""
    got = _scored_arrays(path, labels)
    if got is None:
        return None
    t0, t_end, truth, stamped, _ = got
    spans = []
    for k, (t, msg) in enumerate(stamped):
        t_next = stamped[k + 1][0] if k + 1 < len(stamped) else max(t_end, t)
        spans.append((t, t_next, label_states(msg, truth)))
    return t0, t_end, sorted(truth), spans


def evaluate_annotations(path: str | Path, correct_deg: float = CORRECT_DEG,
                         labels: Iterable[str] | None = None) -> dict[str, Any] | None:
    """The measures of the module docstring, or None when the bag has no annotation markers or
    no ground truth to score them. ``labels``: score only these anchors (those the user could
    annotate; default every anchor of the bag)."""
    got = _scored_arrays(path, labels)
    if got is None:
        return None
    t0, t_end, truth, stamped, n_anchors = got

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
        'anchors': n_anchors,
        'placed': len(final),
        'matched': sum(s == 'matched' for _, s in final.values()),
        'inferred': sum(s == 'inferred' for _, s in final.values()),
        'approximate': approx,
        'median_error_deg': round(float(np.median(errors)), 3) if errors else None,
        'errors_deg': {k: round(v[0], 3) for k, v in sorted(final.items())},
    }


TOPIC_INFO = '/camera/camera_info'


def _frames(bag: BagReader) -> tuple[np.ndarray, np.ndarray, tuple[int, int]] | None:
    """(the camera frames' header stamps, K, (h, w)) from ``/camera/camera_info``, or None."""
    msgs = bag.read_all(TOPIC_INFO) if TOPIC_INFO in bag.topics else []
    if not msgs:
        return None
    info = msgs[0][1]
    return (np.array(sorted(_ns(m.header) for _, m in msgs), np.int64), np.asarray(info.k, float).reshape(3, 3),
            (int(info.height), int(info.width)))


def simulated_user_positions(bag_path: str | Path, border_px: float = 2.0) -> Callable[[int], list[Any]]:
    """Evaluation only: a function of the authoring panorama's first-frame stamp (ns) giving the
    ``azel`` positions (panorama frame) where the simulator's anchors appear in that panorama -
    a user who clicks exactly on them, and only on what the panorama shows: an anchor is offered
    when a camera frame from that stamp on saw it (``border_px`` inside the image, the mapper's
    frame border), at its direction from the authoring spot (:func:`standing_spot`; the frames
    are rendered from there). Anchors no frame saw are not offered (the user cannot click on
    them; without ``/camera/camera_info`` every anchor is). Reads ``/ground_truth/orientation``,
    ``/ground_truth/annotations`` and ``/camera/camera_info`` (the frame stamps) of the
    authoring bag (header stamps)."""
    from ..annotate import Position
    from ..io.bags import BagError

    with BagReader(bag_path) as bag:
        if not {TOPIC_GT, TOPIC_GT_ANN} <= set(bag.topics):
            raise BagError(f'{bag_path}: --simulated-user needs {TOPIC_GT} and {TOPIC_GT_ANN} (a simulated bag)')
        labels, positions = _anchors(bag)
        truth = _read_truth(bag)
        frames = _frames(bag)
    if truth is None or not labels:
        raise BagError(f'{bag_path}: no ground-truth anchors or orientation to simulate the user with')
    spot = truth.standing_spot()

    def seen_by(first_stamp_ns: int) -> Callable[[np.ndarray], bool]:
        """Whether a frame from ``first_stamp_ns`` on sees a point from the spot (the frames'
        orientations slerped once for every anchor)."""
        if frames is None:
            return lambda p: True
        stamps, K, (h, w) = frames
        ts = stamps[(stamps >= first_stamp_ns) & (stamps <= truth.t[-1])]
        if ts.size == 0:
            return lambda p: False
        R_cam_enu = truth.R(list(ts)).transpose(0, 2, 1)

        def seen(p: np.ndarray) -> bool:
            d = R_cam_enu @ (p - spot)  # camera coordinates
            z = d[:, 2]
            with np.errstate(divide='ignore', invalid='ignore'):
                x = K[0, 0] * d[:, 0] / z + K[0, 2]
                y = K[1, 1] * d[:, 1] / z + K[1, 2]
            return bool(np.any((z > 0) & (x >= border_px) & (x <= w - 1 - border_px)
                               & (y >= border_px) & (y <= h - 1 - border_px)))
        return seen

    def at(first_stamp_ns: int) -> list[Any]:
        R_enu_pano = truth.R([first_stamp_ns])[0]  # the panorama frame is the first frame's camera
        seen = seen_by(first_stamp_ns)
        out = []
        for label, p in zip(labels, positions):
            if not seen(p):
                continue
            d = R_enu_pano.T @ (p - spot)
            out.append(Position(label, math.degrees(math.atan2(d[0], d[2])),
                                math.degrees(math.atan2(-d[1], math.hypot(d[0], d[2]))), 'azel'))
        return out
    return at
