"""Orientation metrics of an output bag against its ground truth (``ar-tracking evaluate``).

The bag is an output bag of the graph runner (or any bag with the same topics). It holds the
true camera orientation on ``/ground_truth/orientation`` (TransformStamped ``enu`` ->
``camera_optical``) and one or more orientation estimates. Every estimate is brought to the
same quantity, R_enu_cam, composing the body-to-camera rotation from ``/tf_static`` where the
estimate is of another body (e.g. an Imu in the ``imu`` frame); the truth is slerp-interpolated
at the estimate's header stamp and the error rotation ``E = R_est @ R_true^T`` (world frame) is
split into heading (about up) and tilt (the rest).

Which messages count as orientation estimates is decided by a registry of *extractors*, one per
message type: a function that turns a decoded message into an :class:`OrientationSample` (or
``None`` when the message carries no orientation in the world frame). Supporting another
estimate kind is one small function decorated with :func:`register_extractor`.

The output is the nested JSON-able dict of DESIGN.md section 8::

    {"orientation": {"imu/data": {"rmse_deg": .., "heading_rmse_deg": .., "tilt_rmse_deg": ..,
                                  "max_deg": .., "mean_deg": .., "p95_deg": .., "n": ..,
                                  "skipped": .., "outside": ..}},
     "bag": {"path": "...", "duration_s": .., "topics": N}}
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

from ar_tracking.core.rotations import (
    heading_tilt_error_deg,
    interpolate_rotations,
    is_valid_quat,
    nearest_rotation,
    quat_xyzw_to_matrix,
)
from ar_tracking.io.bags import BagError, BagMessage, BagReader, stamp_to_ns
from ar_tracking.io.static_tf import static_transforms
from ar_tracking.errors import ArTrackingError

logger = logging.getLogger(__name__)

GROUND_TRUTH_TOPIC = '/ground_truth/orientation'
DISTURBANCE_TOPIC = '/ground_truth/mag_disturbance'
GROUND_TRUTH_PREFIX = '/ground_truth'
TF_STATIC_TOPIC = '/tf_static'
WORLD_FRAME = 'enu'
CAMERA_FRAME = 'camera_optical'

#: Floats in the JSON output are rounded to this many decimals, so that reruns compare equal.
DECIMALS = 4
#: Largest accepted deviation of a quaternion's norm from 1.
QUAT_NORM_TOL = 1e-3

Array = NDArray[np.float64]


class EvaluationError(ArTrackingError):
    """The bag cannot be evaluated (e.g. it has no ground truth). One line for the user."""


# --------------------------------------------------------------------------------------------
# Extractors: decoded message -> orientation sample of some body frame in the world frame.


@dataclass(frozen=True)
class OrientationSample:
    """One orientation estimate as it is on the wire: R_enu_body as a quaternion (x, y, z, w)."""

    stamp_ns: int
    body_frame: str
    quat_xyzw: tuple[float, float, float, float]


Extractor = Callable[[Any], 'OrientationSample | None']

#: msgtype -> extractor. An extractor returns None for a message that carries no orientation
#: in the world frame (such a message is ignored, not counted as skipped).
EXTRACTORS: dict[str, Extractor] = {}


def register_extractor(msgtype: str) -> Callable[[Extractor], Extractor]:
    """Decorator: make ``fn`` the extractor of messages of type ``msgtype``."""

    def decorate(fn: Extractor) -> Extractor:
        EXTRACTORS[msgtype] = fn
        return fn

    return decorate


def _frame(frame_id: str) -> str:
    """A frame id without the leading slash that tf1-era publishers still add."""
    return frame_id.lstrip('/')


def _quat(q: Any) -> tuple[float, float, float, float]:
    return (float(q.x), float(q.y), float(q.z), float(q.w))


@register_extractor('sensor_msgs/msg/Imu')
def _from_imu(msg: Any) -> OrientationSample | None:
    """Imu: orientation R_enu_B of the body frame B = header.frame_id, unless REP-145's -1
    in orientation_covariance[0] says that the message has no orientation (raw IMU data)."""
    if msg.orientation_covariance[0] == -1:
        return None
    return OrientationSample(
        stamp_to_ns(msg.header.stamp), _frame(msg.header.frame_id), _quat(msg.orientation)
    )


@register_extractor('geometry_msgs/msg/TransformStamped')
def _from_transform(msg: Any) -> OrientationSample | None:
    """TransformStamped enu -> child: R_enu_child. Other parent frames are not world-fixed."""
    if _frame(msg.header.frame_id) != WORLD_FRAME:
        return None
    return OrientationSample(
        stamp_to_ns(msg.header.stamp),
        _frame(msg.child_frame_id),
        _quat(msg.transform.rotation),
    )


@register_extractor('geometry_msgs/msg/PoseStamped')
def _from_pose(msg: Any) -> OrientationSample | None:
    """PoseStamped in enu: a pose has no child frame; by the package's convention it is the
    camera's (e.g. ``slam/pose``)."""
    if _frame(msg.header.frame_id) != WORLD_FRAME:
        return None
    return OrientationSample(
        stamp_to_ns(msg.header.stamp), CAMERA_FRAME, _quat(msg.pose.orientation)
    )


# --------------------------------------------------------------------------------------------
# Data loaded from a bag.


@dataclass
class OrientationSeries:
    """Camera orientations R_enu_cam (N, 3, 3) at header stamps (N,) in integer ns, sorted."""

    stamps_ns: NDArray[np.int64]
    R_enu_cam: Array

    @classmethod
    def empty(cls) -> 'OrientationSeries':
        return cls(np.zeros(0, dtype=np.int64), np.zeros((0, 3, 3)))

    @classmethod
    def from_lists(cls, stamps_ns: list[int], R: list[Array]) -> 'OrientationSeries':
        if not stamps_ns:
            return cls.empty()
        stamps = np.asarray(stamps_ns, dtype=np.int64)
        order = np.argsort(stamps, kind='stable')
        return cls(stamps[order], np.asarray(R, dtype=float)[order])

    def __len__(self) -> int:
        return len(self.stamps_ns)


@dataclass
class EstimateSeries:
    """The usable samples of one estimate topic, how many were skipped, or why it is unusable."""

    topic: str
    series: OrientationSeries = field(default_factory=OrientationSeries.empty)
    skipped: int = 0
    error: str | None = None


@dataclass
class BagOrientations:
    """Everything the metrics and the report need from one bag."""

    path: Path
    duration_s: float
    topic_count: int
    truth: OrientationSeries
    estimates: dict[str, EstimateSeries]
    #: (header stamps ns, compass heading deflection rad) of /ground_truth/mag_disturbance.
    disturbance: tuple[NDArray[np.int64], Array] | None = None


@dataclass
class ErrorSeries:
    """Errors of the scored samples of one estimate (those inside the truth's time span)."""

    stamps_ns: NDArray[np.int64]
    total_deg: Array
    heading_deg: Array
    tilt_deg: Array
    outside: int


class StaticTransforms:
    """Rotations of /tf_static by (parent, child) frame, looked up in either direction."""

    def __init__(self) -> None:
        self._R: dict[tuple[str, str], Array] = {}

    def add_rotation(self, parent: str, child: str, R_parent_child: Array) -> None:
        """One static rotation (rotates child vectors into the parent frame)."""
        self._R[(_frame(parent), _frame(child))] = np.asarray(R_parent_child, dtype=float)

    def add(self, msg: Any) -> None:
        """Add every valid transform of a tf2_msgs/TFMessage."""
        for t in msg.transforms:
            q = _quat(t.transform.rotation)
            parent, child = _frame(t.header.frame_id), _frame(t.child_frame_id)
            if not is_valid_quat(np.array(q), QUAT_NORM_TOL):
                logger.warning('ignoring an invalid static rotation %s -> %s', parent, child)
                continue
            self._R[(parent, child)] = quat_xyzw_to_matrix(np.array(q))

    def rotation(self, parent: str, child: str) -> Array | None:
        """R_parent_child, from the transform parent->child or the inverse of child->parent."""
        if parent == child:
            return np.eye(3)
        if (parent, child) in self._R:
            return self._R[(parent, child)]
        if (child, parent) in self._R:
            return self._R[(child, parent)].T
        return None


# --------------------------------------------------------------------------------------------
# Reading.


def load_orientations(path: str | Path) -> BagOrientations:
    """Read the truth, the static transforms and every orientation estimate of a bag.

    Raises :class:`EvaluationError` when the bag has no usable ground truth; an unreadable bag
    raises :class:`BagError` (from the reader).
    """
    path = Path(path)
    with BagReader(path) as bag:
        topics = bag.topics
        if GROUND_TRUTH_TOPIC not in topics:
            raise EvaluationError(
                f'{path} has no {GROUND_TRUTH_TOPIC}: evaluation needs a bag made by '
                'ar-tracking make-bag or one with ground truth topics'
            )
        tf = _read_static_transforms(bag, topics)
        truth = _read_truth(bag, path)
        disturbance = _read_disturbance(bag, topics)
        estimates = _read_estimates(bag, topics, tf)
        return BagOrientations(
            path=path,
            duration_s=bag.duration_s,
            topic_count=len(topics),
            truth=truth,
            estimates=estimates,
            disturbance=disturbance,
        )


def _decode(bag: BagReader, m: BagMessage) -> Any | None:
    """The decoded message, or None (with a warning) for one that does not decode."""
    try:
        return bag.deserialize(m)
    except BagError as exc:
        logger.warning('%s: skipping an undecodable message: %s', m.topic, exc)
        return None


def _read_static_transforms(bag: BagReader, topics: dict[str, str]) -> StaticTransforms:
    """The bag's /tf_static rotations (read by io.static_tf.static_transforms, as the runner does)."""
    tf = StaticTransforms()
    for t in static_transforms(bag, TF_STATIC_TOPIC):
        tf.add_rotation(t.parent, t.child, t.rotation)
    return tf


def _read_truth(bag: BagReader, path: Path) -> OrientationSeries:
    stamps: list[int] = []
    R: list[Array] = []
    bad = 0
    for m in bag.messages([GROUND_TRUTH_TOPIC]):
        msg = _decode(bag, m)
        q = None if msg is None else np.array(_quat(msg.transform.rotation))
        if q is None or not is_valid_quat(q, QUAT_NORM_TOL):
            bad += 1
            continue
        stamps.append(stamp_to_ns(msg.header.stamp))
        R.append(quat_xyzw_to_matrix(q))
    if bad:
        logger.warning('%s: skipped %d invalid ground truth messages', GROUND_TRUTH_TOPIC, bad)
    if not stamps:
        raise EvaluationError(f'{path}: {GROUND_TRUTH_TOPIC} has no valid orientation')
    return OrientationSeries.from_lists(stamps, R)


def _read_disturbance(
    bag: BagReader, topics: dict[str, str]
) -> tuple[NDArray[np.int64], Array] | None:
    if topics.get(DISTURBANCE_TOPIC) != 'geometry_msgs/msg/Vector3Stamped':
        return None
    stamps: list[int] = []
    values: list[float] = []
    for m in bag.messages([DISTURBANCE_TOPIC]):
        msg = _decode(bag, m)
        if msg is not None and np.isfinite(msg.vector.x):
            stamps.append(stamp_to_ns(msg.header.stamp))
            values.append(float(msg.vector.x))
    if not stamps:
        return None
    order = np.argsort(np.asarray(stamps, dtype=np.int64), kind='stable')
    return np.asarray(stamps, dtype=np.int64)[order], np.asarray(values)[order]


#: Orientation topics that are not of a camera or device body: the hybrid filter's estimate of
#: the panorama frame in the world (a frame relation, scored through orientation/global).
NOT_BODY_ORIENTATIONS = frozenset({'/orientation/panorama_in_world'})


def estimate_topics(topics: dict[str, str]) -> list[str]:
    """Topics whose type has an extractor, apart from the ground truth, in name order."""
    return sorted(
        name
        for name, msgtype in topics.items()
        if msgtype in EXTRACTORS
        and not name.startswith(GROUND_TRUTH_PREFIX)
        and name not in NOT_BODY_ORIENTATIONS
    )


@dataclass
class _Collector:
    """Accumulates one estimate topic while the bag is read."""

    stamps: list[int] = field(default_factory=list)
    R: list[Array] = field(default_factory=list)
    skipped: int = 0
    missing_frames: set[str] = field(default_factory=set)
    seen: bool = False  # at least one message carried an orientation


def _read_estimates(
    bag: BagReader, topics: dict[str, str], tf: StaticTransforms
) -> dict[str, EstimateSeries]:
    names = estimate_topics(topics)
    collectors = {name: _Collector() for name in names}
    for m in bag.messages(names):
        col = collectors[m.topic]
        msg = _decode(bag, m)
        if msg is None:
            col.skipped += 1
            continue
        sample = EXTRACTORS[m.msgtype](msg)
        if sample is not None:
            col.seen = True
            _add_sample(col, sample, tf)
    return {name: _finish(name, col) for name, col in collectors.items() if col.seen}


def _add_sample(col: _Collector, sample: OrientationSample, tf: StaticTransforms) -> None:
    """Convert one sample to R_enu_cam, or count it as skipped (invalid quaternion, no tf)."""
    q = np.array(sample.quat_xyzw)
    if not is_valid_quat(q, QUAT_NORM_TOL):
        col.skipped += 1
        return
    R_body_cam = tf.rotation(sample.body_frame, CAMERA_FRAME)
    if R_body_cam is None:
        col.skipped += 1
        col.missing_frames.add(sample.body_frame)
        return
    col.stamps.append(sample.stamp_ns)
    col.R.append(quat_xyzw_to_matrix(q) @ R_body_cam)


def _finish(topic: str, col: _Collector) -> EstimateSeries:
    missing = ', '.join(sorted(col.missing_frames))
    if not col.stamps and col.missing_frames:
        error = f'no transform {missing} -> {CAMERA_FRAME}'
        logger.warning('%s: skipped: %s', topic, error)
        return EstimateSeries(topic, skipped=col.skipped, error=error)
    if col.missing_frames:
        logger.warning('%s: messages in frame(s) %s skipped: no transform to %s',
                       topic, missing, CAMERA_FRAME)
    if col.skipped:
        logger.warning('%s: skipped %d messages (invalid orientation or frame)',
                       topic, col.skipped)
    return EstimateSeries(topic, OrientationSeries.from_lists(col.stamps, col.R), col.skipped)


# --------------------------------------------------------------------------------------------
# Scoring.


def orientation_errors(truth: OrientationSeries, estimate: OrientationSeries) -> ErrorSeries:
    """Errors of an estimate against the truth slerped at its stamps.

    Times are taken relative to the truth's first stamp before going to float, so that long
    epoch stamps keep their nanosecond precision. Samples outside the truth's span are counted
    in ``outside`` and not scored.
    """
    if len(estimate) == 0:
        empty = np.zeros(0)
        return ErrorSeries(estimate.stamps_ns, empty, empty, empty, 0)
    t0 = int(truth.stamps_ns[0])
    truth_t = (truth.stamps_ns - t0).astype(float)
    est_t = (estimate.stamps_ns - t0).astype(float)
    R_true, inside = interpolate_rotations(truth_t, truth.R_enu_cam, est_t)
    if not inside.any():
        empty = np.zeros(0)
        return ErrorSeries(estimate.stamps_ns[inside], empty, empty, empty, len(estimate))
    total, heading, tilt = heading_tilt_error_deg(estimate.R_enu_cam[inside], R_true)
    return ErrorSeries(
        estimate.stamps_ns[inside],
        np.atleast_1d(total),
        np.atleast_1d(heading),
        np.atleast_1d(tilt),
        int((~inside).sum()),
    )


def _rms(x: Array) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def _round(x: float | None) -> float | None:
    return None if x is None else round(float(x), DECIMALS)


def summarize_errors(errors: ErrorSeries, skipped: int) -> dict[str, Any]:
    """The per-topic measures of DESIGN.md section 8 (None where nothing was scored)."""
    n = int(len(errors.total_deg))
    scored = n > 0
    stats = {
        'rmse_deg': _rms(errors.total_deg) if scored else None,
        'heading_rmse_deg': _rms(errors.heading_deg) if scored else None,
        'tilt_rmse_deg': _rms(errors.tilt_deg) if scored else None,
        'max_deg': float(np.max(errors.total_deg)) if scored else None,
        'mean_deg': float(np.mean(errors.total_deg)) if scored else None,
        'p95_deg': float(np.percentile(errors.total_deg, 95)) if scored else None,
    }
    result: dict[str, Any] = {k: _round(v) for k, v in stats.items()}
    result.update(n=n, skipped=int(skipped), outside=int(errors.outside))
    return result


def topic_key(topic: str) -> str:
    """The JSON key of a topic: its name without the leading slash."""
    return topic.lstrip('/')


#: How an estimate's world frame is matched to the truth's before scoring (``--align-world``).
WORLD_ALIGNMENTS = ('none', 'heading', 'rotation')


def constant_world_rotation(R_true: Array, R_est: Array, mode: str) -> Array:
    """The one rotation A of the world frame that best turns R_est onto R_true (paired
    samples): ``rotation``, the chordal mean of R_true R_est^T; ``heading``, its part about up."""
    A = nearest_rotation(np.einsum('nij,nkj->ik', R_true, R_est))  # sum R_true R_est^T
    if mode == 'heading':
        yaw = math.atan2(A[1, 0] - A[0, 1], A[0, 0] + A[1, 1])
        c, s = math.cos(yaw), math.sin(yaw)
        A = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return A


def align_world(truth: OrientationSeries, estimate: OrientationSeries, mode: str) -> tuple[OrientationSeries, float]:
    """The estimate with its world frame turned onto the truth's by one constant rotation
    (``rotation``: the chordal mean of R_true R_est^T; ``heading``: its part about up only),
    and the angle removed (deg). For truth whose world frame is not north-referenced (optical
    motion capture, a relative reference): such a bag cannot score absolute heading."""
    if mode == 'none' or len(estimate) == 0:
        return estimate, 0.0
    if mode not in WORLD_ALIGNMENTS:
        raise EvaluationError(f'unknown world alignment {mode!r}; use one of {", ".join(WORLD_ALIGNMENTS)}')
    t0 = int(truth.stamps_ns[0])
    R_true, inside = interpolate_rotations((truth.stamps_ns - t0).astype(float), truth.R_enu_cam,
                                           (estimate.stamps_ns - t0).astype(float))
    if not inside.any():
        return estimate, 0.0
    A = constant_world_rotation(R_true, estimate.R_enu_cam[inside], mode)
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(A) - 1.0) / 2.0))))
    return OrientationSeries(estimate.stamps_ns, A @ estimate.R_enu_cam), angle


def score(truth: OrientationSeries, series: OrientationSeries, skipped: int = 0, align: str = 'none') -> dict[str, Any]:
    """summarize_errors of one estimate, after the world alignment (if any)."""
    aligned, angle = align_world(truth, series, align)
    result = summarize_errors(orientation_errors(truth, aligned), skipped)
    if align != 'none':
        result['aligned_by_deg'] = _round(angle)
    return result


def evaluate_orientations(data: BagOrientations, align: str = 'none') -> dict[str, Any]:
    """The metrics dict of already loaded bag data (see the module docstring)."""
    orientation: dict[str, Any] = {}
    for topic, est in data.estimates.items():
        if est.error is not None:
            orientation[topic_key(topic)] = {'error': est.error}
            continue
        orientation[topic_key(topic)] = score(data.truth, est.series, est.skipped, align)
    if not orientation:
        logger.warning('%s: no orientation estimates to evaluate', data.path)
    return {
        'orientation': orientation,
        'bag': {
            'path': str(data.path),
            'duration_s': _round(data.duration_s),
            'topics': data.topic_count,
            # none: every estimate scored in its own world frame (north-referenced truth);
            # heading / rotation: each turned by its constant best fit to the truth first.
            'world_alignment': align,
        },
    }


def evaluate_bag(path: str | Path, align: str = 'none') -> dict[str, Any]:
    """Orientation metrics of every estimate in an output bag against its ground truth.

    Returns the nested JSON-able dict described in the module docstring. Raises
    :class:`EvaluationError` if the bag has no ground truth and lets :class:`BagError`
    propagate for a bag that cannot be read.
    """
    return evaluate_orientations(load_orientations(path), align)
