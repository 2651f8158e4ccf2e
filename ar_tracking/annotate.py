"""Authoring: annotations from an authoring-session bag (Langlotz 2011 sec. 3.2, Fig. 2; sec. 4.3).

:func:`annotate_bag` runs the panorama mapper (:class:`~ar_tracking.core.panorama.PanoramaMapper`)
over the bag's camera frames, then cuts a patch of the finished map at each anchor and stores it
with its unit direction in the panorama frame, the GPS fix and the panorama's id in the
annotation store. Anchors are either given as map positions (``positions``: text, u, v) or, for
simulated bags, taken from ``/ground_truth/annotations``: an anchor at ENU direction d appears in
the panorama frame at ``R_pano_enu @ d``, with R_enu_pano the ground-truth camera orientation at
the panorama's first frame (the panorama frame is that frame's camera frame).

With the annotations, up to ``landmarks`` (24) distinctive patches of the same panorama are
stored (:mod:`ar_tracking.core.annotations.landmarks`): never shown, they give the re-detector
more matches to align the browsing panorama with. Above the horizon only when the panorama's
orientation is known (the ground is near, its parallax large).

The source panorama's orientation in the world (for the sensor prior of sec. 4.2 when the
annotations are browsed) is stored with each record when known: from the ground truth for
simulated bags (``world_orientation='ground_truth'``), otherwise not (``'none'``).
"""
from __future__ import annotations

import hashlib
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from .core.annotations.landmarks import LandmarkConfig, select_landmarks
from .core.annotations.patches import cut_patch
from .core.annotations.store import (Annotation, AddReport, Landmark, SqliteAnnotationStore,
                                     validate_annotation)
from .core.panorama import MapConfig, MapperConfig, PanoramaMapper
from .core.panorama.cylinder import CylinderGeometry
from .core.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from .io.bags import BagError, BagReader

logger = logging.getLogger(__name__)

TOPIC_GT_ORIENTATION = '/ground_truth/orientation'
TOPIC_GT_ANNOTATIONS = '/ground_truth/annotations'
TOPIC_GPS = '/gps/fix'


@dataclass
class AnnotateReport:
    """What :func:`annotate_bag` did."""

    panorama_id: str
    frames: int = 0
    lost_frames: int = 0
    stored: list[int] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)  # (text, reason)
    latitude_deg: float = float('nan')
    longitude_deg: float = float('nan')
    landmarks: int = 0  # landmarks stored with the annotations


def _interp_rotation(stamps: np.ndarray, rots: np.ndarray, t: int) -> np.ndarray | None:
    from scipy.spatial.transform import Rotation, Slerp

    if len(stamps) == 0 or t < stamps[0] - 50_000_000 or t > stamps[-1] + 50_000_000:
        return None
    if len(stamps) == 1 or t <= stamps[0]:
        return rots[0]
    if t >= stamps[-1]:
        return rots[-1]
    k = int(np.searchsorted(stamps, t))
    s = Slerp([0.0, 1.0], Rotation.from_matrix(rots[k - 1:k + 1]))
    return s([(t - stamps[k - 1]) / max(1, stamps[k] - stamps[k - 1])]).as_matrix()[0]


def annotate_bag(bag: str | Path, store_path: str | Path, *, positions: Sequence[tuple[str, float, float]] | None = None,
                 patch_px: int = 16, author: str = '', panorama_id: str | None = None,
                 edr: bool = True, world_orientation: str = 'ground_truth', create: bool = True,
                 landmarks: int = LandmarkConfig.count,
                 support_landmarks: int = LandmarkConfig.support_count,
                 progress: Callable[[float], None] | None = None) -> AnnotateReport:
    """Author annotations from an authoring bag into the store at ``store_path`` (see module
    docstring), and up to ``landmarks`` landmarks of the panorama (0: none) plus up to
    ``support_landmarks`` next to each annotation (:mod:`.core.annotations.landmarks`). Raises
    BagError / StoreError (one line) for unusable bags / stores."""
    from .ros.conversions import ConversionError, compressed_to_array, image_to_array

    bag = Path(bag)
    if world_orientation not in ('ground_truth', 'none'):
        raise ValueError("world_orientation must be 'ground_truth' or 'none'")
    # Open the store first: a missing/locked/corrupt store fails before minutes of mapping.
    store = SqliteAnnotationStore(store_path, create=create)
    try:
        geo = CylinderGeometry()
        mapper = PanoramaMapper(MapperConfig(map=MapConfig(edr=edr)))
        K = None
        gt_t: list[int] = []
        gt_R: list[np.ndarray] = []
        anchors_enu: list[tuple[str, np.ndarray]] = []
        fixes: list[tuple[float, float, float]] = []
        init_ns: int | None = None
        first_ns: int | None = None
        with BagReader(bag) as reader:
            topics = reader.topics
            image_topics = [t for t in topics if t.endswith('image_raw') or t.endswith('image_raw/compressed')]
            if not image_topics:
                raise BagError(f'{bag}: no camera image topic in the bag')
            n_img = reader.message_count(image_topics)
            wanted = image_topics + ['/camera/camera_info', TOPIC_GT_ORIENTATION, TOPIC_GT_ANNOTATIONS, TOPIC_GPS]
            done = 0
            for m in reader.messages([t for t in wanted if t in topics]):
                if m.topic == '/camera/camera_info':
                    info = reader.deserialize(m)
                    k = np.asarray(info.k, float).reshape(3, 3)
                    if np.all(np.isfinite(k)) and k[0, 0] > 0:
                        K = k
                elif m.topic == TOPIC_GT_ORIENTATION:
                    q = reader.deserialize(m).transform.rotation
                    gt_t.append(m.log_time_ns)
                    gt_R.append(quat_xyzw_to_matrix(np.array([q.x, q.y, q.z, q.w])))
                elif m.topic == TOPIC_GT_ANNOTATIONS:
                    for mk in reader.deserialize(m).markers:
                        p = np.array([mk.pose.position.x, mk.pose.position.y, mk.pose.position.z])
                        if np.all(np.isfinite(p)) and np.linalg.norm(p) > 0:
                            anchors_enu.append((mk.text, p / np.linalg.norm(p)))
                elif m.topic == TOPIC_GPS:
                    f = reader.deserialize(m)
                    if f.status.status >= 0 and all(math.isfinite(x) for x in (f.latitude, f.longitude, f.altitude)):
                        fixes.append((f.latitude, f.longitude, f.altitude))
                else:
                    done += 1
                    if K is None:
                        continue
                    msg = reader.deserialize(m)
                    try:
                        arr = compressed_to_array(msg) if m.topic.endswith('compressed') else image_to_array(msg)
                    except ConversionError as exc:
                        logger.warning('%s: frame skipped: %s', bag, exc)
                        continue
                    if arr.dtype != np.uint8:
                        continue
                    bgr = m.topic.endswith('compressed') or getattr(msg, 'encoding', '').startswith('bgr')
                    gray = arr if arr.ndim == 2 else cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY if bgr else cv2.COLOR_RGB2GRAY)
                    stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
                    first_ns = stamp if first_ns is None else first_ns
                    res = mapper.process(gray, K, stamp)
                    if res.status == 'initialised':
                        init_ns = stamp
                    mapper.background()
                    if progress is not None and n_img:
                        progress(done / n_img)
        if init_ns is None:
            raise BagError(f'{bag}: the panorama could not be started (no usable camera frames with camera_info)')
        pid = panorama_id or f'{bag.stem}-{hashlib.sha1(f"{bag.name}:{init_ns}".encode()).hexdigest()[:10]}'
        report = AnnotateReport(panorama_id=pid, frames=mapper.frame_index, lost_frames=mapper.lost_frames)
        if not fixes:
            raise BagError(f'{bag}: no valid GPS fix ({TOPIC_GPS}) to tag the annotations with')
        lat, lon, alt = (float(np.median([f[i] for f in fixes])) for i in range(3))
        report.latitude_deg, report.longitude_deg = lat, lon
        R_enu_pano = None
        if gt_t:
            order = np.argsort(gt_t)
            R_enu_pano = _interp_rotation(np.asarray(gt_t)[order], np.asarray(gt_R)[order], init_ns)
        # Anchors as map positions.
        todo: list[tuple[str, float, float]] = []
        if positions is not None:
            todo = [(t, float(u), float(v)) for t, u, v in positions]
        else:
            if not anchors_enu:
                raise BagError(f'{bag}: no anchor positions given and no {TOPIC_GT_ANNOTATIONS} in the bag')
            if R_enu_pano is None:
                raise BagError(f'{bag}: {TOPIC_GT_ANNOTATIONS} needs {TOPIC_GT_ORIENTATION} at the first frame')
            for text, d in anchors_enu:
                u, v = geo.project(R_enu_pano.T @ d)
                todo.append((text, float(u), float(v)))
        q = (matrix_to_quat_xyzw(R_enu_pano) if (R_enu_pano is not None and world_orientation == 'ground_truth')
             else np.full(4, np.nan))
        gray = mapper.map.gray
        records, texts = [], []
        for text, u, v in todo:
            patch, d, reason = cut_patch(gray, mapper.map.mapped, u, v, patch_px, geo)
            if patch is None:
                report.skipped.append((text, reason))
                logger.warning('annotation %r skipped: %s', text, reason)
                continue
            a = Annotation(text=text, patch=patch, direction=d, latitude_deg=lat, longitude_deg=lon,
                           altitude_m=alt, panorama_id=pid, author=author, created_ns=init_ns,
                           panorama_in_world_quat_xyzw=q)
            bad = validate_annotation(a)
            if bad:
                report.skipped.append((text, bad))
                continue
            records.append(a)
            texts.append(text)
        added: AddReport = store.add(records)
        report.stored = added.ids
        report.skipped += [(texts[i], r) for i, r in added.skipped]
        if report.stored and landmarks > 0:
            up = R_enu_pano[2] if R_enu_pano is not None else None
            cfg = LandmarkConfig(count=landmarks, support_count=support_landmarks)
            found = select_landmarks(gray, mapper.map.mapped, geo, up, cfg,
                                     avoid=np.array([a.direction for a in records]))
            report.landmarks = len(store.add_landmarks(
                Landmark(pid, lm.patch, lm.direction) for lm in found).ids)
        return report
    finally:
        store.close()
