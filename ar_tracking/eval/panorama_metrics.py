"""Panorama measures (issue #3, DESIGN sec. 8 area ``panorama``).

``evaluate_panorama(bag)`` reads a runner output bag with ``/panorama/orientation`` and
``/ground_truth/orientation`` and returns::

    {"tracking_rmse_deg", "tracking_max_deg", "tracking_p95_deg", "n", "frames",
     "lost_frames", "lost_frames_below_90dps", "max_rate_deg_s",
     "seam_error": {"edr": .., "8bit": .., "ratio": .., ...}}   # only with camera images

Tracking: the panorama frame is the camera at the panorama's first frame, so both the estimate
(R_pano_cam) and the truth are taken relative to the first frame: the truth R_enu_cam(t0)^T
R_enu_cam(t) is slerp-interpolated at each estimate stamp, t0 = the stamp of the first
published orientation (published as identity); a later identity starts a new panorama (the
mapper's ``restart_lost_s``) and the frames from it are taken relative to it. Frames are counted from ``/camera/camera_info``
(one per image, copied into the output bag by the runner), so ``lost_frames`` is the number of
camera frames without an orientation.

Seam error (sec. 4.1): the output bag has no per-pixel frame contributions, so the core is
run offline on the camera images - from ``source_bag`` (the runner's input bag) or from the
bag itself when it has images - with EDR (the configured correction, by default the overlap
fit), with the plain 8-bit map, with the keypoint-pair offset filtered over frames
(``edr_keypoints``) and with the paper's literal EDR (each frame's own keypoint offset,
unsmoothed: ``edr_paper``), and
:func:`ar_tracking.core.panorama.map.seam_error` is taken on the grey maps (8-bit units
relative to the first frame). Keys of ``seam_error``:

* ``edr``, ``8bit``, ``edr_keypoints``, ``edr_paper``: the seam error proper - the intensity STEP between frame
  contributions: per boundary segment (the pixel pairs shared by one pair of contributions) the
  mean jump across it, on flat surroundings only, freed of the estimation noise, as the RMS
  over the boundary length (map.py explains why). ``ratio`` = edr / 8bit (target <= 0.5),
  ``ratio_keypoints`` = edr_keypoints / 8bit, ``ratio_paper`` = edr_paper / 8bit;
* ``mean_abs_*`` (``ratio_mean_abs``): the length-weighted mean |step| of the same segments;
* ``pixelwise_*`` (``ratio_pixelwise``): the naive figure, the mean |difference| of all
  adjacent pixel pairs across boundaries, texture included;
* ``*_revisit`` (``ratio_revisit``, ``*_revisit_pairs``): the step measure on the boundaries
  between frames >= 1 s apart only (where the map is continued after a revisit); few pairs.
"""
from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path
from typing import Any, Iterator

import cv2
import numpy as np
from numpy.typing import NDArray

from ar_tracking.core.panorama import MapperConfig, PanoramaMapper
from ar_tracking.core.rotations import interpolate_rotations, quat_xyzw_to_matrix, trace_angle
from ar_tracking.io.bags import BagError, BagReader, stamp_to_ns

logger = logging.getLogger(__name__)

PANORAMA_TOPIC = '/panorama/orientation'
TRUTH_TOPIC = '/ground_truth/orientation'
CAMERA_INFO_TOPIC = '/camera/camera_info'
IMAGE_TOPICS = ('/camera/image_raw', '/camera/image_raw/compressed')
#: Boundaries between frames at least this many frames apart (1 s at 30 Hz) are "revisits".
REVISIT_GAP_FRAMES = 30

Array = NDArray[np.float64]


def _R(q: Any) -> Array:
    return quat_xyzw_to_matrix(np.array([q.x, q.y, q.z, q.w], float))


def _decode_image(msg: Any, msgtype: str) -> NDArray[np.uint8] | None:
    """RGB (or grey) uint8 array of a rosbags Image / CompressedImage, None if unusable."""
    if msgtype.endswith('CompressedImage'):
        img = cv2.imdecode(np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR)
        return None if img is None else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    ch = {'rgb8': 3, 'bgr8': 3, 'mono8': 1}.get(msg.encoding)
    if ch is None:
        return None
    buf = np.asarray(msg.data, np.uint8)
    if buf.size < msg.step * msg.height:
        return None
    img = buf[:msg.step * msg.height].reshape(msg.height, msg.step)[:, :msg.width * ch]
    img = img.reshape(msg.height, msg.width, ch) if ch == 3 else img.reshape(msg.height, msg.width)
    return img[:, :, ::-1].copy() if msg.encoding == 'bgr8' else np.ascontiguousarray(img)


def camera_frames(bag_path: str | Path, max_frames: int | None = None
                  ) -> Iterator[tuple[int, NDArray[np.uint8], Array]]:
    """(stamp ns, RGB/grey frame, K) of a bag's camera, image paired with camera_info by stamp."""
    with BagReader(bag_path) as bag:
        topics = bag.topics
        img_topic = next((t for t in IMAGE_TOPICS if t in topics), None)
        if img_topic is None or CAMERA_INFO_TOPIC not in topics:
            return
        infos: dict[int, Array] = {}
        n = 0
        for m in bag.messages([img_topic, CAMERA_INFO_TOPIC]):
            msg = bag.deserialize(m)
            stamp = stamp_to_ns(msg.header.stamp)
            if m.topic == CAMERA_INFO_TOPIC:
                infos[stamp] = np.asarray(msg.k, float).reshape(3, 3)
                continue
            K = infos.pop(stamp, None)
            img = _decode_image(msg, m.msgtype)
            if K is None or img is None:
                continue
            yield stamp, img, K
            n += 1
            if max_frames is not None and n >= max_frames:
                return


def run_core(frames: Any, config: MapperConfig | None = None) -> tuple[PanoramaMapper, list[tuple[int, Array | None]]]:
    """Run the mapper on (stamp, frame, K) items; returns it and (stamp, R or None) per frame."""
    mapper = PanoramaMapper(config)
    out: list[tuple[int, Array | None]] = []
    for stamp, img, K in frames:
        res = mapper.process(img, K, stamp)
        mapper.background()
        out.append((stamp, res.R_pano_cam))
    return mapper, out


#: The maps compared by :func:`seam_errors`: name -> (edr, EDR correction, smoothed keypoint offset).
SEAM_VARIANTS = {'edr': (True, None, True), '8bit': (False, None, True),
                 'edr_keypoints': (True, 'offset', True), 'edr_paper': (True, 'offset', False)}


def seam_errors(bag_path: str | Path, max_frames: int | None = None,
                config: MapperConfig | None = None) -> dict[str, float] | None:
    """Seam error of the map built with EDR and with the plain 8-bit map on the same frames
    (module docstring), and of the keypoint-pair EDR versions (filtered, and the paper's literal
    unsmoothed per-frame offset)."""
    base = config or MapperConfig()
    frames = list(camera_frames(bag_path, max_frames))
    if not frames:
        return None
    result: dict[str, float] = {}
    for name, (edr, correction, smooth) in SEAM_VARIANTS.items():
        cfg = replace(base, map=replace(base.map, edr=edr), edr_correction=correction or base.edr_correction,
                      offset_exposure=replace(base.offset_exposure, smooth=smooth and base.offset_exposure.smooth))
        mapper, _ = run_core(frames, cfg)
        s = mapper.seam_error()
        result[name] = round(s['step'], 4)
        result[f'mean_abs_{name}'] = round(s['mean_step'], 4)
        result[f'pixelwise_{name}'] = round(s['pixelwise'], 4)
        r = mapper.seam_error(min_gap=REVISIT_GAP_FRAMES)
        result[f'{name}_revisit'] = round(r['step'], 4)
        result[f'{name}_revisit_pairs'] = r['pairs']
    for num, den, key in (('edr', '8bit', 'ratio'), ('edr_paper', '8bit', 'ratio_paper'),
                          ('edr_keypoints', '8bit', 'ratio_keypoints'),
                          ('mean_abs_edr', 'mean_abs_8bit', 'ratio_mean_abs'),
                          ('pixelwise_edr', 'pixelwise_8bit', 'ratio_pixelwise'),
                          ('edr_revisit', '8bit_revisit', 'ratio_revisit')):
        if result[den] > 0:
            result[key] = round(result[num] / result[den], 4)
    return result


def tracking_errors(est_stamps: NDArray[np.int64], R_est: Array, truth_stamps: NDArray[np.int64],
                    R_truth: Array) -> tuple[NDArray[np.int64], Array]:
    """Angle (deg) between each estimate and the truth, both relative to the stamp of the first
    estimate of its panorama; returns (stamps inside the truth's span, errors). A panorama starts
    at its first frame, published as the identity: a later identity is a new panorama
    (panorama_mapper's ``restart_lost_s``), and the frames from it are taken relative to it."""
    inside = (est_stamps >= truth_stamps[0]) & (est_stamps <= truth_stamps[-1])
    st, Re = est_stamps[inside], R_est[inside]
    if st.size == 0:
        return st, np.zeros(0)
    t = (truth_stamps - truth_stamps[0]) * 1e-9
    q = (st - truth_stamps[0]) * 1e-9
    Rt, _ = interpolate_rotations(t, R_truth, q)
    # Each frame's panorama start: the index of the last identity at or before it (frame 0 if none).
    index = np.arange(len(st))
    is_start = np.all(np.abs(Re - np.eye(3)) < 1e-12, axis=(1, 2))
    first = np.maximum.accumulate(np.where(is_start, index, 0))
    rel_true = np.einsum('nji,njk->nik', Rt[first], Rt)
    rel_est = np.einsum('nji,njk->nik', Re[first], Re)
    E = np.einsum('nji,njk->nik', rel_est, rel_true)
    return st, np.degrees(trace_angle(E))


def evaluate_panorama(bag_path: str | Path, source_bag: str | Path | None = None,
                      seam: bool = True) -> dict[str, Any] | None:
    """The panorama measures of a runner output bag (module docstring); None without
    ``/panorama/orientation``."""
    bag_path = Path(bag_path)
    with BagReader(bag_path) as bag:
        topics = bag.topics
        if PANORAMA_TOPIC not in topics:
            return None
        est = []
        for m in bag.messages([PANORAMA_TOPIC]):
            try:
                msg = bag.deserialize(m)
            except BagError:
                continue
            est.append((stamp_to_ns(msg.header.stamp), _R(msg.transform.rotation)))
        frames = [stamp_to_ns(bag.deserialize(m).header.stamp) for m in bag.messages([CAMERA_INFO_TOPIC])] \
            if CAMERA_INFO_TOPIC in topics else []
        truth = []
        if TRUTH_TOPIC in topics:
            for m in bag.messages([TRUTH_TOPIC]):
                msg = bag.deserialize(m)
                truth.append((stamp_to_ns(msg.header.stamp), _R(msg.transform.rotation)))
    out: dict[str, Any] = {'n': len(est)}
    est.sort(key=lambda e: e[0])
    if frames:
        have = {s for s, _ in est}
        frame_set = sorted(set(frames))
        lost = [s for s in frame_set if s not in have and (not est or s > est[0][0])]
        out['frames'] = len(frame_set)
        out['lost_frames'] = len(lost)
    if est and len(truth) > 1:
        ts = np.array([s for s, _ in truth], np.int64)
        Rt = np.array([R for _, R in truth])
        order = np.argsort(ts, kind='stable')
        ts, Rt = ts[order], Rt[order]
        st, err = tracking_errors(np.array([s for s, _ in est], np.int64),
                                  np.array([R for _, R in est]), ts, Rt)
        if err.size:
            out['tracking_rmse_deg'] = round(float(np.sqrt(np.mean(err ** 2))), 4)
            out['tracking_max_deg'] = round(float(err.max()), 4)
            out['tracking_p95_deg'] = round(float(np.percentile(err, 95)), 4)
        if frames and 'lost_frames' in out:
            rate = _rates_deg_s(ts, Rt)
            lost_arr = np.array([s for s in sorted(set(frames)) if s not in {x for x, _ in est}
                                 and s > est[0][0]], np.int64)
            r_lost = np.interp(lost_arr, ts[1:], rate) if lost_arr.size else np.zeros(0)
            out['lost_frames_below_90dps'] = int(np.count_nonzero(r_lost < 90.0))
            out['max_rate_deg_s'] = round(float(rate.max()), 2) if rate.size else 0.0
    if seam:
        src = Path(source_bag) if source_bag is not None else bag_path
        try:
            s = seam_errors(src)
        except BagError as exc:
            logger.warning('seam error not computed: %s', exc)
            s = None
        if s is not None:
            out['seam_error'] = s
    return out


def _rates_deg_s(ts: NDArray[np.int64], R: Array) -> Array:
    """Angular speed (deg/s) between consecutive truth samples (stamped at the later one)."""
    if ts.size < 2:
        return np.zeros(0)
    E = np.einsum('nji,njk->nik', R[:-1], R[1:])
    ang = trace_angle(E)
    dt = np.maximum(np.diff(ts) * 1e-9, 1e-9)
    return np.degrees(ang) / dt
