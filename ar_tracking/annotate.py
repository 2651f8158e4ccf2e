"""Authoring: annotations from an authoring-session bag (Langlotz 2011 sec. 3.2, Fig. 2; sec. 4.3, 5).

:func:`annotate_bag` runs the same cores as the browsing graph over the bag's own sensor data:
the panorama mapper (:class:`~ar_tracking.core.panorama.PanoramaMapper`) over the camera frames,
and the hybrid filter's world alignment with imu_magnetometer's AHRS over ``/imu/data_raw`` +
``/imu/mag`` paired with the mapper's orientations by header stamp
(:class:`~ar_tracking.core.annotations.world_orientation.PanoramaWorldEstimator`, with the
device calibration of ``<bag>.params.yaml`` or ``params_files``). It then cuts a patch of the
finished map at each anchor and stores it with its unit direction in the panorama frame, the
median GPS fix and the panorama's id; the panorama's estimated orientation in ENU (the sensor
prior of sec. 4.2 when browsing) goes with every record and, with its covariance, its up
direction and its source, into the store's panoramas table (:class:`PanoramaInfo`).
``/ground_truth/*`` topics are never read here: a real device has none.

Where an annotation goes (:class:`Position`; a file of rows or the CLI, one form per row):

* ``pixel``: map column u and row v of the authoring panorama (u = W/2 + f atan2(x, z),
  v = H/2 + f y / hypot(x, z) for a direction (x, y, z) in the panorama frame, f = W / 2 pi;
  2048 x 512 pixels, 0.176 deg per pixel, the first frame's optical axis at (1024, 256), pixel
  centres at integers). :func:`write_panorama_png` draws the map with a degree grid to pick them on;
* ``azel``: azimuth (deg, right of the first frame's optical axis, about the panorama's
  vertical axis) and elevation (deg, up) in the panorama frame - the PNG's grid;
* ``bearing``: compass bearing (deg, clockwise from true north) and elevation (deg above the
  horizon) in the world, turned into the panorama frame by the estimated orientation (so the
  anchor is off by that estimate's error, reported as ``heading_sigma_deg``); the record keeps
  the panorama direction of the patch centre.

Re-running on the same bag does not duplicate: the panorama id is derived from the bag and its
first mapped frame, and an anchor within half a map pixel of a stored one of the same panorama
is skipped as already stored (``replace=True`` deletes the panorama's records first).

With the annotations, up to ``landmarks`` (24) distinctive patches of the same panorama are
stored (:mod:`ar_tracking.core.annotations.landmarks`): never shown, they give the re-detector
more matches to align the browsing panorama with; above the estimated horizon.
"""
from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence, Union

import cv2
import numpy as np
import yaml

from .core.annotations.landmarks import LandmarkConfig, select_landmarks
from .core.annotations.patches import cut_patch
from .core.annotations.store import (Annotation, AnnotationStore, AddReport, Landmark, PanoramaInfo,
                                     validate_annotation)
from .core.annotations.world_orientation import DEFAULT_R_IMU_CAM, PanoramaWorld, PanoramaWorldEstimator
from .core.imu_orientation import ImuCalibration
from .core.panorama import MapConfig, MapperConfig, PanoramaMapper
from .core.panorama.cylinder import CylinderGeometry
from .core.rectification import Rectification, RectificationCache, RectificationError
from .core.rotations import matrix_to_quat_xyzw, quat_xyzw_to_matrix
from .core.world_alignment import WorldAlignmentConfig
from .io.bags import BagError, BagReader
from .io.stores import open_store
from .errors import ArTrackingError

logger = logging.getLogger(__name__)

TOPIC_GPS = '/gps/fix'
TOPIC_IMU = '/imu/data_raw'
TOPIC_MAG = '/imu/mag'
TOPIC_INFO = '/camera/camera_info'
FORMS = ('pixel', 'azel', 'bearing')
#: Two anchors of one panorama closer than this (map pixels) are the same anchor.
SAME_POSITION_PX = 0.5


@dataclass(frozen=True)
class Position:
    """Where one annotation goes: ``form`` (:data:`FORMS`) and its two numbers (module doc)."""

    text: str
    a: float
    b: float
    form: str = 'pixel'


#: ``positions`` of :func:`annotate_bag`: the rows, or a function of the panorama's first-frame
#: stamp (ns) that gives them (a simulated user who looks at the panorama before clicking).
Positions = Union[Sequence[Union[Position, tuple]], Callable[[int], Sequence[Position]]]


class PositionError(ArTrackingError, ValueError):
    """A bad position row (one line)."""


def parse_position(text: str, numbers: str, form: str) -> Position:
    """A :class:`Position` from a label and ``"a,b"``; PositionError (one line) when bad."""
    if form not in FORMS:
        raise PositionError(f'unknown position form {form!r} (one of {", ".join(FORMS)})')
    if not text.strip():
        raise PositionError('empty annotation text')
    parts = numbers.split(',')
    if len(parts) != 2:
        raise PositionError(f'{text.strip()!r}: expected two numbers "a,b", got {numbers.strip()!r}')
    try:
        a, b = (float(p) for p in parts)
    except ValueError:
        raise PositionError(f'{text.strip()!r}: not numbers: {numbers.strip()!r}') from None
    if not (math.isfinite(a) and math.isfinite(b)):
        raise PositionError(f'{text.strip()!r}: numbers must be finite, got {numbers.strip()!r}')
    if form != 'pixel' and not -90.0 < b < 90.0:
        raise PositionError(f'{text.strip()!r}: elevation {b:g} deg is not within (-90, 90)')
    return Position(text.strip(), a, b, form)


def read_positions(path: str | Path, form: str = 'pixel') -> tuple[list[Position], list[str]]:
    """Rows ``text,a,b`` of a positions file (``#`` comments; a line ``# form: azel`` sets the
    form of the rows after it, default ``form``); bad rows are returned as one line each."""
    rows: list[Position] = []
    bad: list[str] = []
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise PositionError(f'{path}: cannot read the positions file ({exc})') from None
    for n, line in enumerate(lines, 1):
        s = line.strip()
        if s.startswith('#'):
            key, _, value = s.lstrip('#').partition(':')
            if key.strip().lower() == 'form':
                if value.strip() not in FORMS:
                    raise PositionError(f'{path}:{n}: unknown form {value.strip()!r} (one of {", ".join(FORMS)})')
                form = value.strip()
            continue
        if not s:
            continue
        try:
            if s.count(',') < 2:
                raise PositionError(f'expected "text,a,b", got {s!r}')
            text, a, b = s.rsplit(',', 2)
            rows.append(parse_position(text, f'{a},{b}', form))
        except PositionError as exc:
            bad.append(f'{path}:{n}: {exc}; row skipped')
    return rows, bad


def position_direction(p: Position, geo: CylinderGeometry, R_enu_pano: np.ndarray | None) -> np.ndarray | None:
    """Unit direction of a position in the panorama frame (None: a bearing without orientation)."""
    if p.form == 'pixel':
        return np.asarray(geo.unproject(np.array(p.a), np.array(p.b)), float).reshape(3)
    az, el = math.radians(p.a), math.radians(p.b)
    if p.form == 'azel':
        return np.array([math.sin(az) * math.cos(el), -math.sin(el), math.cos(az) * math.cos(el)])
    if R_enu_pano is None:
        return None
    d_enu = np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])
    return R_enu_pano.T @ d_enu


@dataclass
class AnnotateReport:
    """What :func:`annotate_bag` did."""

    panorama_id: str
    frames: int = 0
    lost_frames: int = 0
    stored: list[int] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)  # (text, reason)
    duplicates: int = 0  # anchors already stored for this panorama
    replaced: int = 0  # records deleted first (replace=True)
    latitude_deg: float = float('nan')
    longitude_deg: float = float('nan')
    landmarks: int = 0  # landmarks stored with the annotations
    first_stamp_ns: int = 0  # the panorama's first frame (its frame is that camera's)
    orientation_source: str = 'none'  # 'world_alignment', 'ahrs' or 'none'
    heading_sigma_deg: float = float('nan')
    tilt_sigma_deg: float = float('nan')
    ahrs_disagreement_deg: float = float('nan')
    calibration: str = ''  # where the device calibration came from
    png: str = ''


def _sidecar(bag: Path) -> Path | None:
    stem = bag.name[: -len(bag.suffix)] if bag.suffix else bag.name
    p = bag.with_name(stem + '.params.yaml')
    return p if p.is_file() else None


def _node_params(files: Sequence[str | Path], nodes: Sequence[str]) -> dict[str, Any]:
    """The parameters of ``nodes`` (later ones and later files win) in ROS 2 params files, with
    or without ``ros__parameters``. BagError (one line) for an unreadable or invalid file."""
    values: dict[str, Any] = {}
    for f in files:
        try:
            doc = yaml.safe_load(Path(f).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise BagError(f'{f}: cannot read the params file ({str(exc).splitlines()[0]})') from None
        if not isinstance(doc, dict):
            raise BagError(f'{f}: a params file is a mapping of node names')
        for node in nodes:
            sec = doc.get(node) or doc.get('/' + node) or {}
            sec = sec.get('ros__parameters', sec) if isinstance(sec, dict) else {}
            values.update(sec)
    return values


def load_camera_params(files: Sequence[str | Path]) -> dict[str, Any]:
    """The camera's rolling shutter as the graph's mapper gets it, from the ``panorama_mapper``
    section of ROS 2 params files: :class:`MapperConfig` fields ``readout_s`` (default 0),
    ``estimate_readout`` (True) and ``repaint_max_mb`` (the config's default)."""
    values = _node_params(files, ('panorama_mapper',))
    try:
        readout = float(values.get('readout_s', 0.0))
        estimate = values.get('estimate_readout', True)
        repaint = float(values.get('repaint_max_mb', MapperConfig.repaint_max_mb))
        if not math.isfinite(readout) or not 0.0 <= readout <= 0.1 or not isinstance(estimate, bool):
            raise ValueError('readout_s must be in [0, 0.1] s and estimate_readout true or false')
        if not math.isfinite(repaint) or repaint < 0.0:
            raise ValueError('repaint_max_mb must be 0 or more')
    except (TypeError, ValueError) as exc:
        raise BagError(f'camera parameters in {", ".join(map(str, files))}: {exc}') from None
    return {'readout_s': readout, 'estimate_readout': estimate, 'repaint_max_mb': repaint}


def load_device_params(files: Sequence[str | Path]) -> tuple[ImuCalibration, np.ndarray, float]:
    """(calibration, R_imu_cam, declination_rad) from ROS 2 params files: the
    ``hybrid_orientation_filter`` section (else ``imu_magnetometer``), later files win; with or
    without ``ros__parameters``. BagError (one line) for an unreadable or invalid file."""
    values = _node_params(files, ('imu_magnetometer', 'hybrid_orientation_filter'))
    try:
        cal = ImuCalibration(gyro_bias=values.get('gyro_bias', [0.0] * 3),
                             accel_bias=values.get('accel_bias', [0.0] * 3),
                             hard_iron_offset=values.get('hard_iron_offset', [0.0] * 3),
                             soft_iron_matrix=values.get('soft_iron_matrix', np.eye(3).ravel().tolist()))
        q = values.get('imu_to_camera_quat_xyzw')
        R_imu_cam = DEFAULT_R_IMU_CAM if q is None else quat_xyzw_to_matrix(np.asarray(q, float))
        decl = float(values.get('declination_rad', 0.0))
    except (TypeError, ValueError) as exc:
        raise BagError(f'device calibration in {", ".join(map(str, files))}: {exc}') from None
    return cal, R_imu_cam, decl


def annotate_bag(bag: str | Path, store_path: str | Path, *, positions: Positions,
                 patch_px: int = 16, author: str = '', panorama_id: str | None = None,
                 edr: bool = True, create: bool = True, replace: bool = False,
                 params_files: Sequence[str | Path] | None = None,
                 landmarks: int = LandmarkConfig.count,
                 support_landmarks: int = LandmarkConfig.support_count,
                 png: str | Path | None = None,
                 progress: Callable[[float], None] | None = None) -> AnnotateReport:
    """Author annotations from an authoring bag into the store at ``store_path`` (see module
    docstring), and up to ``landmarks`` landmarks of the panorama (0: none) plus up to
    ``support_landmarks`` next to each annotation (:mod:`.core.annotations.landmarks`).
    ``params_files``: the device calibration (default: ``<bag>.params.yaml`` when present).
    ``png``: also write the authoring panorama with a degree grid there. Raises BagError /
    StoreError (one line) for unusable bags / stores.

    The steps: read the bag and map it (:func:`_map_bag`), estimate the panorama's orientation in
    the world, turn the positions into patches and records (:func:`_anchor_records`), store them
    with the panorama and its landmarks (:func:`_store_all`)."""
    bag = Path(bag)
    # Open the store first: a missing/locked/corrupt store fails before minutes of mapping.
    store = open_store(store_path, create=create)  # a path, sqlite:///path or postgresql:// (PostGIS)
    try:
        if params_files is None:
            side = _sidecar(bag)
            params_files = [side] if side is not None else []
        cal, R_imu_cam, decl = load_device_params(params_files)
        geo = CylinderGeometry()
        # One authoring session is one panorama: a restart after a loss would leave the
        # annotations placed before it in a map that is gone.
        mapper = PanoramaMapper(MapperConfig(map=MapConfig(edr=edr), restart_lost_s=0.0,
                                             **load_camera_params(params_files)))
        world_est = PanoramaWorldEstimator(cal, R_imu_cam, WorldAlignmentConfig(declination_rad=decl))
        fixes, init_ns = _map_bag(bag, mapper, world_est, progress)
        if init_ns is None:
            raise BagError(f'{bag}: the panorama could not be started (no usable camera frames with camera_info)')
        pid = panorama_id or f'{bag.stem}-{hashlib.sha1(f"{bag.name}:{init_ns}".encode()).hexdigest()[:10]}'
        report = AnnotateReport(panorama_id=pid, frames=mapper.frame_index, lost_frames=mapper.lost_frames,
                                first_stamp_ns=init_ns, calibration=', '.join(map(str, params_files)) or 'none')
        if not fixes:
            raise BagError(f'{bag}: no valid GPS fix ({TOPIC_GPS}) to tag the annotations with')
        lat, lon, alt = (float(np.median([f[i] for f in fixes])) for i in range(3))
        report.latitude_deg, report.longitude_deg = lat, lon
        world: PanoramaWorld | None = world_est.estimate()
        if world is None:
            logger.warning('%s: no IMU samples paired with the panorama: stored without its orientation '
                           '(no sensor prior when browsing)', bag)
        else:
            report.orientation_source = world.source
            report.heading_sigma_deg = math.degrees(world.heading_sigma_rad)
            report.tilt_sigma_deg = math.degrees(world.tilt_sigma_rad)
            report.ahrs_disagreement_deg = math.degrees(world.ahrs_disagreement_rad)
        R_enu_pano = world.R_enu_pano if world is not None else None
        if png is not None:
            report.png = str(write_panorama_png(mapper.map.tone_mapped(8), mapper.map.mapped, png, R_enu_pano))
        rows = positions(init_ns) if callable(positions) else positions
        todo: list[Position] = [r if isinstance(r, Position) else Position(str(r[0]), float(r[1]), float(r[2]))
                                for r in rows]
        q = matrix_to_quat_xyzw(R_enu_pano) if R_enu_pano is not None else np.full(4, np.nan)
        if replace:
            report.replaced = store.delete_panorama(pid)
        template = Annotation(text='', patch=np.zeros((patch_px, patch_px), np.uint8), direction=np.zeros(3),
                              latitude_deg=lat, longitude_deg=lon, altitude_m=alt, panorama_id=pid,
                              author=author, created_ns=init_ns, panorama_in_world_quat_xyzw=q)
        records, texts = _anchor_records(todo, store, template, mapper, geo, R_enu_pano, patch_px, report)
        _store_all(store, records, texts, template, world, mapper, geo, landmarks, support_landmarks, report)
        return report
    finally:
        store.close()


def _map_bag(bag: Path, mapper: PanoramaMapper, world_est: PanoramaWorldEstimator,
             progress: Callable[[float], None] | None) -> tuple[list[tuple[float, float, float]], int | None]:
    """Read the bag once: camera frames into the panorama mapper (from the first camera_info on),
    the mapper's orientations, ``/imu/data_raw`` and ``/imu/mag`` into the world estimator, the
    valid GPS fixes collected. A lens distortion in camera_info is undone before mapping, as
    panorama_mapper does. Returns (fixes, stamp of the frame that started the panorama or None)."""
    rectify: Rectification | None = None
    rectifications = RectificationCache()  # camera_info comes with every frame: built once
    fixes: list[tuple[float, float, float]] = []
    init_ns: int | None = None
    with BagReader(bag) as reader:
        topics = reader.topics
        image_topics = [t for t in topics if t.endswith('image_raw') or t.endswith('image_raw/compressed')]
        if not image_topics:
            raise BagError(f'{bag}: no camera image topic in the bag')
        n_img = reader.message_count(image_topics)
        wanted = image_topics + [TOPIC_INFO, TOPIC_GPS, TOPIC_IMU, TOPIC_MAG]
        done = 0
        for m in reader.messages([t for t in wanted if t in topics]):
            if m.topic == TOPIC_INFO:
                info = reader.deserialize(m)
                k = np.asarray(info.k, float).reshape(3, 3)
                if np.all(np.isfinite(k)) and k[0, 0] > 0 and info.width > 0 and info.height > 0:
                    try:
                        rectify = rectifications.get(k, info.d, info.width, info.height,
                                                     str(info.distortion_model))[0]
                    except RectificationError:
                        pass  # coefficients OpenCV cannot use: the camera_info before stays
            elif m.topic == TOPIC_IMU:
                s = reader.deserialize(m)
                w, a = s.angular_velocity, s.linear_acceleration
                world_est.add_imu(_ns(s.header), np.array([w.x, w.y, w.z]), np.array([a.x, a.y, a.z]))
            elif m.topic == TOPIC_MAG:
                s = reader.deserialize(m)
                f = s.magnetic_field
                world_est.add_mag(_ns(s.header), np.array([f.x, f.y, f.z]))
            elif m.topic == TOPIC_GPS:
                f = reader.deserialize(m)
                if f.status.status >= 0 and all(math.isfinite(x) for x in (f.latitude, f.longitude, f.altitude)):
                    fixes.append((f.latitude, f.longitude, f.altitude))
            else:
                done += 1
                if rectify is None:
                    continue
                frame = _gray_frame(bag, m.topic, reader.deserialize(m))
                if frame is None:
                    continue
                gray, stamp = frame
                res = mapper.process(rectify(gray), rectify.K, stamp)
                if res.status == 'initialised':
                    init_ns = stamp
                if res.R_pano_cam is not None and init_ns is not None:
                    world_est.add_visual(stamp, res.R_pano_cam)
                mapper.background()
                if progress is not None and n_img:
                    progress(done / n_img)
    return fixes, init_ns


def _gray_frame(bag: Path, topic: str, msg: Any) -> tuple[np.ndarray, int] | None:
    """(8-bit grey image, header stamp) of one camera message for the mapper, None for a frame
    that cannot be converted (logged) or is not 8-bit."""
    from .ros.conversions import ConversionError, compressed_to_array, image_to_array

    try:
        arr = compressed_to_array(msg) if topic.endswith('compressed') else image_to_array(msg)
    except ConversionError as exc:
        logger.warning('%s: frame skipped: %s', bag, exc)
        return None
    if arr.dtype != np.uint8:
        return None
    bgr = topic.endswith('compressed') or getattr(msg, 'encoding', '').startswith('bgr')
    gray = arr if arr.ndim == 2 else cv2.cvtColor(arr, cv2.COLOR_BGR2GRAY if bgr else cv2.COLOR_RGB2GRAY)
    return gray, _ns(msg.header)


def _anchor_records(todo: Sequence[Position], store: AnnotationStore, template: Annotation, mapper: PanoramaMapper,
                    geo: CylinderGeometry, R_enu_pano: np.ndarray | None, patch_px: int,
                    report: AnnotateReport) -> tuple[list[Annotation], list[str]]:
    """The records of the positions: each one's patch cut from the finished map at its direction;
    a position without a direction, patch or valid record is skipped (reason in ``report``), one
    within ``SAME_POSITION_PX`` of a stored or earlier one of the panorama counted a duplicate.
    ``template`` carries the fields every record shares (fix, panorama, author, orientation)."""
    gray = mapper.map.gray
    existing = np.array([a.direction for a in store.annotations_of(template.panorama_id)]).reshape(-1, 3)
    same = math.cos(SAME_POSITION_PX / geo.f)
    records, texts = [], []
    for p in todo:
        d = position_direction(p, geo, R_enu_pano)
        if d is None:
            report.skipped.append((p.text, 'a compass bearing needs the panorama orientation, which could not be estimated'))
            continue
        u, v = geo.project(d)
        patch, d, reason = cut_patch(gray, mapper.map.mapped, float(u), float(v), patch_px, geo)
        if patch is None or d is None:
            report.skipped.append((p.text, reason))
            logger.warning('annotation %r skipped: %s', p.text, reason)
            continue
        if len(existing) and float(np.max(existing @ d)) >= same:
            report.duplicates += 1
            continue
        a = dataclasses.replace(template, text=p.text, patch=patch, direction=d)
        bad = validate_annotation(a)
        if bad:
            report.skipped.append((p.text, bad))
            continue
        records.append(a)
        texts.append(p.text)
        existing = np.vstack([existing, d])
    return records, texts


def _store_all(store: AnnotationStore, records: list[Annotation], texts: list[str], template: Annotation,
               world: PanoramaWorld | None, mapper: PanoramaMapper, geo: CylinderGeometry,
               landmarks: int, support_landmarks: int, report: AnnotateReport) -> None:
    """Store the records, the panorama (its orientation in the world, covariance, up direction and
    source) and, when records were stored and the panorama has none yet, its landmarks."""
    pid, init_ns = template.panorama_id, template.created_ns
    added: AddReport = store.add(records)
    report.stored = added.ids
    report.skipped += [(texts[i], r) for i, r in added.skipped]
    store.put_panorama(PanoramaInfo(
        pid, template.panorama_in_world_quat_xyzw,
        world.covariance_enu if world is not None else np.full((3, 3), np.nan),
        world.up if world is not None else np.full(3, np.nan),
        'estimated' if world is not None else 'none', init_ns))
    if report.stored and landmarks > 0 and not store.landmarks([pid]):
        cfg = LandmarkConfig(count=landmarks, support_count=support_landmarks)
        found = select_landmarks(mapper.map.gray, mapper.map.mapped, geo, world.up if world is not None else None,
                                 cfg, avoid=np.array([a.direction for a in store.annotations_of(pid)]))
        report.landmarks = len(store.add_landmarks(
            Landmark(pid, lm.patch, lm.direction) for lm in found).ids)


def _ns(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def write_panorama_png(tone_mapped: np.ndarray, mapped: np.ndarray, path: str | Path,
                       R_enu_pano: np.ndarray | None = None, step_deg: int = 10) -> Path:
    """The authoring panorama (8-bit) with a degree grid to pick positions on: a line every
    ``step_deg`` of azimuth and elevation in the panorama frame (labels every 30 deg, at the top
    and the left edge), unmapped parts dark blue; with the estimated orientation, the compass
    bearing of every 30 deg of azimuth along the bottom (at the panorama's horizon). Map pixels are
    the PNG's pixels (u = column, v = row)."""
    geo = CylinderGeometry()
    img = np.asarray(tone_mapped)
    img = img[..., 0] if img.ndim == 3 and img.shape[2] == 1 else img
    gray = img if img.ndim == 2 else cv2.cvtColor(img.astype(np.uint8), cv2.COLOR_RGB2GRAY)
    out = cv2.cvtColor(gray.astype(np.uint8), cv2.COLOR_GRAY2BGR)
    out[~np.asarray(mapped, bool)] = (60, 20, 0)
    H, W = gray.shape
    font = cv2.FONT_HERSHEY_SIMPLEX
    for az in range(-180, 180, step_deg):
        u = int(round(W / 2 + math.radians(az) * geo.f)) % W
        major = az % 30 == 0
        cv2.line(out, (u, 0), (u, H - 1), (0, 200, 255) if major else (0, 120, 160), 1)
        if major:
            cv2.putText(out, f'{az:+d}', (u + 2, 12), font, 0.35, (0, 255, 255), 1, cv2.LINE_AA)
            if R_enu_pano is not None:
                d = np.array([math.sin(math.radians(az)), 0.0, math.cos(math.radians(az))])
                e = R_enu_pano @ d
                bearing = math.degrees(math.atan2(e[0], e[1])) % 360.0
                cv2.putText(out, f'N{bearing:.0f}', (u + 2, H - 4), font, 0.35, (255, 255, 0), 1, cv2.LINE_AA)
    for el in range(-60, 61, step_deg):
        v = int(round(H / 2 - math.tan(math.radians(el)) * geo.f))
        if 0 <= v < H:
            cv2.line(out, (0, v), (W - 1, v), (0, 200, 255) if el % 30 == 0 else (0, 120, 160), 1)
            cv2.putText(out, f'{el:+d}', (2, v - 2), font, 0.35, (0, 255, 255), 1, cv2.LINE_AA)
    path = Path(path)
    if not cv2.imwrite(str(path), out):
        raise BagError(f'{path}: cannot write the panorama PNG')
    return path
