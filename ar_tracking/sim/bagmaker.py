"""Make simulated bags with ground truth: the entry point behind ``ar-tracking make-bag``.

``make_bag('rotation_sweep', 'out.mcap', seed=3, session='browsing')`` writes a bag of a person
sweeping a phone around at the seed's spot (camera, IMU, magnetometer, GPS, and the ground
truth: orientation, pose, annotation anchors, magnetic disturbance) and a sidecar
``out.params.yaml`` with the device calibration a user would have measured (close to, not
exactly, the truth). The same arguments always give the same bytes: nothing depends on the wall
clock, and every random stream is derived from ``(seed, session)``. The world (textures and
annotation anchors) depends on the seed only, so an authoring and a browsing bag of one seed
show the same spot under a different sun, from standing points less than 2 m apart.

Topics (log time = header stamp, integer ns from a fixed start), as topic: type, rate, frame_id:

* /camera/image_raw: sensor_msgs/Image rgb8, 30 Hz, camera_optical (or, with
  image_format='compressed', /camera/image_raw/compressed: sensor_msgs/CompressedImage jpeg)
* /camera/camera_info: sensor_msgs/CameraInfo, with every image, camera_optical
* /imu/data_raw: sensor_msgs/Imu (no orientation), 100 Hz, imu
* /imu/mag: sensor_msgs/MagneticField (raw, tesla), 100 Hz (IMU stamps), imu
* /gps/fix: sensor_msgs/NavSatFix, 1 Hz, gps
* /tf_static: tf2_msgs/TFMessage, once, imu -> camera_optical (R_imu_cam = diag(1, -1, -1))
* /ground_truth/orientation: geometry_msgs/TransformStamped, 100 Hz, enu -> camera_optical
  (rotation R_enu_cam; translation = the camera position)
* /ground_truth/pose: geometry_msgs/PoseStamped, 100 Hz, enu
* /ground_truth/annotations: visualization_msgs/MarkerArray, once, enu (anchor positions
  relative to the authoring spot)
* /ground_truth/mag_disturbance: geometry_msgs/Vector3Stamped, 100 Hz, enu (x: compass error
  caused by the disturbance in rad, y: extra |B| in tesla)

``profile`` (rotation_sweep): 'hard' (default) simulates a realistic phone, 'kind' the earlier,
easier simulator, whose bags are byte for byte those made before profiles existed (see
:mod:`ar_tracking.sim.rotation_sweep`). In the hard profile the IMU and magnetometer stamps
are the true sample time plus the scenario's camera-IMU time offset (2-8 ms, either sign), so
they no longer equal the ground-truth stamps (true time, on the 100 Hz grid); /tf_static and
/ground_truth/annotations then go first, at the earlier of START_NS and the first IMU stamp.
The profile is named in the sidecar's header comment and, for hard bags, in the MCAP metadata
record ``ar_tracking.simulator`` (scenario, profile, seed, session) for evaluation; kind bags
carry no record, as before. Estimators must not read either.
"""
from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import yaml

from ..core.rotations import matrix_to_quat_xyzw
from ..io.bags import BagError, BagWriter, msg_class, ns_to_stamp
from . import rotation_sweep as rs
from .world import (FrameRenderer, Lighting, Panorama, PinholeCamera, World, build_world,
                    make_lighting, render_panorama, rng_stream)

logger = logging.getLogger(__name__)

SCENARIOS: tuple[str, ...] = ('rotation_sweep', 'robot_arcs', 'handheld_desk')
SESSIONS: tuple[str, ...] = rs.SESSIONS
STORAGES: tuple[str, ...] = ('mcap', 'sqlite3')
IMAGE_FORMATS: tuple[str, ...] = ('raw', 'compressed')
PROFILES: tuple[str, ...] = rs.PROFILES
#: MCAP metadata record naming the simulator profile of a hard rotation_sweep bag (evaluation only).
SIM_METADATA = 'ar_tracking.simulator'

#: Stamp of the first message (2023-11-14T22:13:20Z): fixed, so bags are reproducible.
START_NS = 1_700_000_000 * 1_000_000_000
MAX_DURATION_S = 3600.0
JPEG_QUALITY = 85
#: Auto-exposure only half compensates the scene brightness (a sunnier day stays brighter).
EXPOSURE_TARGET = 0.2
EXPOSURE_COMPENSATION = 0.4

TOPIC_IMAGE = '/camera/image_raw'
TOPIC_IMAGE_COMPRESSED = '/camera/image_raw/compressed'
TOPIC_CAMERA_INFO = '/camera/camera_info'
TOPIC_IMU = '/imu/data_raw'
TOPIC_MAG = '/imu/mag'
TOPIC_GPS = '/gps/fix'
TOPIC_TF_STATIC = '/tf_static'
TOPIC_GT_ORIENTATION = '/ground_truth/orientation'
TOPIC_GT_POSE = '/ground_truth/pose'
TOPIC_GT_ANNOTATIONS = '/ground_truth/annotations'
TOPIC_GT_MAG_DISTURBANCE = '/ground_truth/mag_disturbance'

FRAME_CAMERA = 'camera_optical'
FRAME_IMU = 'imu'
FRAME_GPS = 'gps'
FRAME_WORLD = 'enu'


class SimError(Exception):
    """Bad arguments to the simulator; the message is one line meant for the user."""


# --------------------------------------------------------------------------------------------
# Public entry


def make_bag(scenario: str, out: str | Path, *, seed: int = 0, duration_s: float = 60.0,
             session: str = 'authoring', storage: str = 'mcap', image_format: str = 'raw',
             overwrite: bool = False, progress: Callable[[float], None] | None = None,
             lighting: str | None = None, profile: str = 'hard') -> Path:
    """Writes the bag and a sidecar '<out stem>.params.yaml' next to it; returns the bag path.

    ``storage`` 'mcap' gives one ``.mcap`` file (the suffix is added when missing), 'sqlite3' a
    rosbag2 directory. ``progress`` is called now and then with the fraction done (0..1).
    ``lighting`` (rotation_sweep only): the session whose sun and sky light the spot, default
    ``session``; e.g. a browsing walk under the authoring sun (the 'same lighting' column of
    Langlotz 2011 Fig. 7). ``profile`` (rotation_sweep, robot_arcs): 'hard' (default, a realistic
    phone or camera) or 'kind' (the earlier, easier simulator; byte for byte its bags). Raises
    :class:`SimError` for bad arguments (including an existing output without ``overwrite``).
    """
    _check_args(scenario, seed, duration_s, session, storage, image_format)
    if profile not in PROFILES:
        raise SimError(f'unknown profile {profile!r} (use {" or ".join(PROFILES)})')
    if lighting is not None and lighting not in SESSIONS:
        raise SimError(f'unknown lighting {lighting!r} (use {" or ".join(SESSIONS)})')
    bag_path = _bag_path(Path(out), storage)
    sidecar = sidecar_path(bag_path)
    if not overwrite:
        for p in (bag_path, sidecar):
            if p.exists():
                raise SimError(f'{p}: already exists (choose another name or overwrite)')
    if scenario == 'robot_arcs':  # Caarls 2009 Fig. 9: its own module (session is ignored)
        from . import robot_arcs

        try:
            with BagWriter(bag_path, storage=storage, overwrite=overwrite) as bag:  # type: ignore
                robot_arcs.write_robot_arcs_bag(bag, seed, duration_s, image_format, progress, profile=profile)
        except BagError as exc:
            raise SimError(str(exc)) from exc
        robot_arcs.write_sidecars(sidecar, bag_path, seed, profile=profile)
        return bag_path
    if scenario == 'handheld_desk':  # Klein & Murray 2009: a hand-held phone over a desk (session is ignored)
        from . import handheld_desk

        try:
            with BagWriter(bag_path, storage=storage, overwrite=overwrite) as bag:  # type: ignore
                handheld_desk.write_handheld_desk_bag(bag, seed, duration_s, image_format, progress)
        except BagError as exc:
            raise SimError(str(exc)) from exc
        handheld_desk.write_sidecars(sidecar, bag_path, seed)
        logger.info('wrote %s (handheld_desk, seed %d, %.1f s) and %s', bag_path, seed, duration_s, sidecar.name)
        return bag_path
    scn = rs.make_scenario(seed, session, duration_s, profile=profile)
    world, light, pano = session_view(seed, session, lighting)
    plan = _Plan.make(scn, pano)
    try:
        with BagWriter(bag_path, storage=storage, overwrite=overwrite) as bag:  # type: ignore
            _write_all(bag, scn, world, light, pano, plan, image_format, progress)
    except BagError as exc:
        raise SimError(str(exc)) from exc
    write_sidecar(sidecar, scn, bag_path)
    logger.info('wrote %s (%s, seed %d, %s, %.1f s, profile %s) and %s', bag_path, scenario,
                seed, session, duration_s, profile, sidecar.name)
    return bag_path


def sidecar_path(bag_path: Path) -> Path:
    """'<bag without suffix>.params.yaml' next to the bag."""
    stem = bag_path.name[:-len(bag_path.suffix)] if bag_path.suffix else bag_path.name
    return bag_path.with_name(stem + '.params.yaml')


def _check_args(scenario: str, seed: int, duration_s: float, session: str, storage: str,
                image_format: str) -> None:
    if scenario not in SCENARIOS:
        raise SimError(f'unknown scenario {scenario!r} (known: {", ".join(SCENARIOS)})')
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**32:
        raise SimError(f'seed must be an integer in [0, 2**32), got {seed!r}')
    if not isinstance(duration_s, (int, float)) or not math.isfinite(duration_s) \
            or not 1.0 <= duration_s <= MAX_DURATION_S:
        raise SimError(f'duration_s must be between 1 and {MAX_DURATION_S:.0f} s, '
                       f'got {duration_s!r}')
    if session not in SESSIONS:
        raise SimError(f'unknown session {session!r} (use {" or ".join(SESSIONS)})')
    if storage not in STORAGES:
        raise SimError(f'unknown storage {storage!r} (use {" or ".join(STORAGES)})')
    if image_format not in IMAGE_FORMATS:
        raise SimError(f'unknown image format {image_format!r} (use {" or ".join(IMAGE_FORMATS)})')


def _bag_path(out: Path, storage: str) -> Path:
    if storage == 'mcap':
        return out if out.suffix == '.mcap' else out.with_name(out.name + '.mcap')
    return out.with_suffix('') if out.suffix in ('.mcap', '.db3') else out


@functools.lru_cache(maxsize=2)
def session_view(seed: int, session: str, lighting: str | None = None
                 ) -> tuple[World, Lighting, Panorama]:
    """World, lighting and the panorama from the session's standing spot (cached: ~3 s each).

    ``lighting``: the session whose sun lights the spot (default ``session``)."""
    world = _world(seed)
    light = make_lighting(seed, lighting or session, world)
    pano = render_panorama(world, light, rs.session_offset(seed, session))
    return world, light, pano


@functools.lru_cache(maxsize=2)
def _world(seed: int) -> World:
    return build_world(seed)


# --------------------------------------------------------------------------------------------
# Timing and camera settings


@dataclass(frozen=True)
class _Plan:
    """Stamps of every stream and the camera's exposure settings."""

    imu_ns: np.ndarray
    cam_ns: np.ndarray
    gps_ns: np.ndarray
    gain: np.ndarray  # per frame, multiplies linear radiance
    wb: np.ndarray  # (n_frames, 3)

    @staticmethod
    def make(scn: rs.Scenario, pano: Panorama) -> '_Plan':
        dur_ns = int(round(scn.duration_s * 1e9))
        imu = np.arange(0, dur_ns, 1_000_000_000 // rs.IMU_RATE_HZ, dtype=np.int64)
        n_cam = int(math.ceil(dur_ns * rs.CAMERA_RATE_HZ / 1e9))
        cam = (np.arange(n_cam, dtype=np.int64) * 1_000_000_000) // rs.CAMERA_RATE_HZ
        gps = np.arange(0, dur_ns, 1_000_000_000 // rs.GPS_RATE_HZ, dtype=np.int64)
        factor, wb = rs.make_exposure(scn.seed, scn.session, scn.duration_s,
                                      scn.profile).at(cam * 1e-9)
        base = (EXPOSURE_TARGET / max(pano.mean_radiance, 1e-3)) ** EXPOSURE_COMPENSATION
        return _Plan(imu, cam, gps, base * factor, wb)


# --------------------------------------------------------------------------------------------
# Messages


class _Msgs:
    """Builders of the rosbags message objects used here."""

    def __init__(self) -> None:
        self.Header = msg_class('std_msgs/msg/Header')
        self.Vector3 = msg_class('geometry_msgs/msg/Vector3')
        self.Quaternion = msg_class('geometry_msgs/msg/Quaternion')
        self.Point = msg_class('geometry_msgs/msg/Point')
        self.Pose = msg_class('geometry_msgs/msg/Pose')
        self.Transform = msg_class('geometry_msgs/msg/Transform')

    def header(self, ns: int, frame_id: str) -> Any:
        return self.Header(stamp=ns_to_stamp(ns), frame_id=frame_id)

    def vec(self, v: np.ndarray) -> Any:
        return self.Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quat(self, q_xyzw: np.ndarray) -> Any:
        return self.Quaternion(x=float(q_xyzw[0]), y=float(q_xyzw[1]), z=float(q_xyzw[2]),
                               w=float(q_xyzw[3]))

    def transform_stamped(self, ns: int, parent: str, child: str, t: np.ndarray,
                          q_xyzw: np.ndarray) -> Any:
        return msg_class('geometry_msgs/msg/TransformStamped')(
            header=self.header(ns, parent), child_frame_id=child,
            transform=self.Transform(translation=self.vec(t), rotation=self.quat(q_xyzw)))

    def pose_stamped(self, ns: int, frame: str, p: np.ndarray, q_xyzw: np.ndarray) -> Any:
        return msg_class('geometry_msgs/msg/PoseStamped')(
            header=self.header(ns, frame),
            pose=self.Pose(position=self.Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                           orientation=self.quat(q_xyzw)))

    def imu(self, ns: int, gyro: np.ndarray, accel: np.ndarray, gyro_var: float,
            accel_var: float) -> Any:
        return msg_class('sensor_msgs/msg/Imu')(
            header=self.header(ns, FRAME_IMU),
            orientation=self.Quaternion(x=0.0, y=0.0, z=0.0, w=0.0),
            orientation_covariance=np.array([-1.0] + [0.0] * 8),
            angular_velocity=self.vec(gyro),
            angular_velocity_covariance=np.diag([gyro_var] * 3).ravel(),
            linear_acceleration=self.vec(accel),
            linear_acceleration_covariance=np.diag([accel_var] * 3).ravel())

    def mag(self, ns: int, field_t: np.ndarray, var: float) -> Any:
        return msg_class('sensor_msgs/msg/MagneticField')(
            header=self.header(ns, FRAME_IMU), magnetic_field=self.vec(field_t),
            magnetic_field_covariance=np.diag([var] * 3).ravel())

    def vector3_stamped(self, ns: int, frame: str, v: np.ndarray) -> Any:
        return msg_class('geometry_msgs/msg/Vector3Stamped')(header=self.header(ns, frame),
                                                             vector=self.vec(v))

    def navsat(self, ns: int, lat: float, lon: float, alt: float, sig_h: float,
               sig_v: float) -> Any:
        NavSatFix = msg_class('sensor_msgs/msg/NavSatFix')
        Status = msg_class('sensor_msgs/msg/NavSatStatus')
        return NavSatFix(
            header=self.header(ns, FRAME_GPS),
            status=Status(status=Status.STATUS_FIX, service=Status.SERVICE_GPS),
            latitude=float(lat), longitude=float(lon), altitude=float(alt),
            position_covariance=np.diag([sig_h ** 2, sig_h ** 2, sig_v ** 2]).ravel(),
            position_covariance_type=NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN)

    def camera_info(self, ns: int, cam: PinholeCamera) -> Any:
        K = cam.K
        P = np.hstack([K, np.zeros((3, 1))])
        return msg_class('sensor_msgs/msg/CameraInfo')(
            header=self.header(ns, FRAME_CAMERA), height=cam.height, width=cam.width,
            distortion_model='plumb_bob', d=np.zeros(5), k=K.ravel(), r=np.eye(3).ravel(),
            p=P.ravel(), binning_x=0, binning_y=0,
            roi=msg_class('sensor_msgs/msg/RegionOfInterest')(
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))

    def image(self, ns: int, rgb: np.ndarray) -> Any:
        h, w = rgb.shape[:2]
        return msg_class('sensor_msgs/msg/Image')(
            header=self.header(ns, FRAME_CAMERA), height=h, width=w, encoding='rgb8',
            is_bigendian=0, step=3 * w, data=np.ascontiguousarray(rgb).reshape(-1))

    def compressed(self, ns: int, rgb: np.ndarray) -> Any:
        ok, buf = cv2.imencode('.jpg', cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                               [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
        if not ok:  # pragma: no cover - OpenCV always encodes a valid uint8 image
            raise SimError('JPEG encoding failed')
        return msg_class('sensor_msgs/msg/CompressedImage')(
            header=self.header(ns, FRAME_CAMERA), format='jpeg', data=buf.reshape(-1))

    def markers(self, ns: int, labels: list[str], positions: list[np.ndarray]) -> Any:
        Marker = msg_class('visualization_msgs/msg/Marker')
        out = []
        for i, (label, p) in enumerate(zip(labels, positions)):
            out.append(Marker(
                header=self.header(ns, FRAME_WORLD), ns='ground_truth', id=i,
                type=Marker.TEXT_VIEW_FACING, action=Marker.ADD,
                pose=self.Pose(position=self.Point(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                               orientation=self.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                scale=self.Vector3(x=0.0, y=0.0, z=1.0),
                color=msg_class('std_msgs/msg/ColorRGBA')(r=1.0, g=0.85, b=0.1, a=1.0),
                lifetime=msg_class('builtin_interfaces/msg/Duration')(sec=0, nanosec=0),
                frame_locked=False, points=[], colors=[], texture_resource='',
                texture=msg_class('sensor_msgs/msg/CompressedImage')(
                    header=self.header(0, ''), format='', data=np.zeros(0, np.uint8)),
                uv_coordinates=[], text=label, mesh_resource='',
                mesh_file=msg_class('visualization_msgs/msg/MeshFile')(
                    filename='', data=np.zeros(0, np.uint8)),
                mesh_use_embedded_materials=False))
        return msg_class('visualization_msgs/msg/MarkerArray')(markers=out)


# --------------------------------------------------------------------------------------------
# Writing


def _write_all(bag: BagWriter, scn: rs.Scenario, world: World, light: Lighting, pano: Panorama,
               plan: _Plan, image_format: str, progress: Callable[[float], None] | None) -> None:
    """All messages in stamp order; images are rendered when their turn comes."""
    m = _Msgs()
    cam = PinholeCamera()
    renderer = FrameRenderer(pano, light, cam, rng_stream(scn.seed, 'pixel-noise', scn.session))
    imu = rs.simulate_imu(scn, plan.imu_ns * 1e-9)
    gps = rs.simulate_gps(scn, plan.gps_ns * 1e-9)
    q_gt = matrix_to_quat_xyzw(imu.R_enu_cam)
    err = scn.errors
    gyro_var, accel_var, mag_var = (err.gyro_noise_rad_s ** 2, err.accel_noise_m_s2 ** 2,
                                    err.mag_noise_t ** 2)
    image_topic = TOPIC_IMAGE if image_format == 'raw' else TOPIC_IMAGE_COMPRESSED
    # IMU/magnetometer stamps = true sample time + offset; ground truth at the true time.
    off = int(scn.imu_time_offset_ns)
    first_ns = START_NS + min(0, off)
    if scn.profile != 'kind':  # kind bags stay byte for byte those of the earlier simulator
        bag.add_metadata(SIM_METADATA, {'scenario': 'rotation_sweep', 'profile': scn.profile,
                                        'seed': str(scn.seed), 'session': scn.session})

    bag.write(TOPIC_TF_STATIC, first_ns, msg_class('tf2_msgs/msg/TFMessage')(transforms=[
        m.transform_stamped(first_ns, FRAME_IMU, FRAME_CAMERA, np.zeros(3),
                            matrix_to_quat_xyzw(rs.R_IMU_CAM))]))
    bag.write(TOPIC_GT_ANNOTATIONS, first_ns, m.markers(
        first_ns, [a.label for a in world.anchors], [a.position_enu for a in world.anchors]))

    # (stamp, stream, part, k): IMU + magnetometer (0, 0), ground truth (0, 1), GPS, camera;
    # with no offset this is the order of the earlier simulator (IMU, truth, GPS, camera).
    events = sorted([(int(s) + off, 0, 0, k) for k, s in enumerate(plan.imu_ns)]
                    + [(int(s), 0, 1, k) for k, s in enumerate(plan.imu_ns)]
                    + [(int(s), 1, 0, k) for k, s in enumerate(plan.gps_ns)]
                    + [(int(s), 2, 0, k) for k, s in enumerate(plan.cam_ns)])
    n_cam = len(plan.cam_ns)
    report_every = max(1, n_cam // 50)
    for stamp, kind, part, k in events:
        ns = START_NS + stamp
        if kind == 0 and part == 0:
            bag.write(TOPIC_IMU, ns, m.imu(ns, imu.gyro_rad_s[k], imu.accel_m_s2[k], gyro_var,
                                           accel_var))
            bag.write(TOPIC_MAG, ns, m.mag(ns, imu.mag_t[k], mag_var))
        elif kind == 0:
            bag.write(TOPIC_GT_ORIENTATION, ns, m.transform_stamped(
                ns, FRAME_WORLD, FRAME_CAMERA, imu.position_enu[k], q_gt[k]))
            bag.write(TOPIC_GT_POSE, ns, m.pose_stamped(ns, FRAME_WORLD, imu.position_enu[k],
                                                        q_gt[k]))
            bag.write(TOPIC_GT_MAG_DISTURBANCE, ns, m.vector3_stamped(
                ns, FRAME_WORLD, np.array([imu.deflection_rad[k], imu.extra_field_t[k], 0.0])))
        elif kind == 1:
            bag.write(TOPIC_GPS, ns, m.navsat(ns, gps.latitude_deg[k], gps.longitude_deg[k],
                                              gps.altitude_m[k], gps.sigma_horizontal_m,
                                              gps.sigma_vertical_m))
        else:
            R = rs.blur_samples(scn.trajectory, stamp * 1e-9, cam.fx)
            rgb = renderer.render(R, float(plan.gain[k]), plan.wb[k])
            bag.write(TOPIC_CAMERA_INFO, ns, m.camera_info(ns, cam))
            bag.write(image_topic, ns, m.image(ns, rgb) if image_format == 'raw'
                      else m.compressed(ns, rgb))
            if progress is not None and (k % report_every == 0 or k == n_cam - 1):
                progress((k + 1) / n_cam)


#: The calibration keys the hybrid filter reads too (it uses raw accelerometer and field samples).
HYBRID_CALIBRATION_KEYS = ('gyro_bias', 'accel_bias', 'hard_iron_offset', 'soft_iron_matrix',
                           'declination_rad')
_PROFILE_NOTES = {
    'hard': 'a realistic phone: hand acceleration, field turns that keep |B| and dip, '
            'residual iron after a rough calibration, gyro bias drift, camera-IMU time offset',
    'kind': 'the earlier, easier simulator',
}


def write_sidecar(path: Path, scn: rs.Scenario, bag_path: Path) -> None:
    """The ROS 2 params file for this device (plain floats): the calibration under
    ``imu_magnetometer`` and the same values (:data:`HYBRID_CALIBRATION_KEYS`) under
    ``hybrid_orientation_filter``."""
    cal = rs.calibration_params(scn)
    doc = {'imu_magnetometer': {'ros__parameters': cal}}
    hybrid = {'hybrid_orientation_filter': {'ros__parameters': {
        k: cal[k] for k in HYBRID_CALIBRATION_KEYS}}}
    quality = ('with 1-3 % error' if scn.profile == 'kind' else
               'from a rough calibration (biases 1-3 % off, hard iron 0.4-1.2 uT off per axis, '
               'soft iron 20-50 % off)')
    head = (f'# Calibration of the simulated device of {bag_path.name} '
            f'(scenario rotation_sweep, seed {scn.seed}, session {scn.session}).\n'
            f'# Measured values {quality}, as a user would have them; '
            'calibrated mag = soft_iron_matrix @ (raw - hard_iron_offset).\n'
            f'# Simulator profile: {scn.profile} ({_PROFILE_NOTES[scn.profile]}).\n')
    dump = functools.partial(yaml.safe_dump, sort_keys=False, default_flow_style=None)
    path.write_text(head + dump(doc) + '# The same calibration for the hybrid filter, which '
                    'reads raw accelerometer and field samples too.\n' + dump(hybrid))
