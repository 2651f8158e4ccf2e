"""Scenario ``rotation_sweep`` as a bag: a person sweeping a phone around at the seed's spot.

The motion, sensors and their errors are :mod:`.rotation_sweep`'s; the street scene is built
(:mod:`.layout`), lit (:mod:`.lighting`) and rendered to a panorama (:mod:`.render`) once per
seed and session, and camera frames are cut from it (:class:`.camera.FrameRenderer`). The topics
are listed in :mod:`.bagmaker`. In the hard profile the IMU and magnetometer stamps are the true
sample time plus the scenario's camera-IMU time offset; /tf_static and /ground_truth/annotations
then go first, at the earlier of START_NS and the first IMU stamp. Hard bags carry the MCAP
metadata record :data:`SIM_METADATA` (scenario, profile, seed, session) for evaluation; kind bags
carry none, as before profiles existed.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from ..core.rotations import matrix_to_quat_xyzw
from ..io.bags import BagWriter, msg_class
from . import rotation_sweep as rs
from .camera import FrameRenderer, PinholeCamera
from .layout import build_world
from .lighting import make_lighting
from .messages import (FRAME_CAMERA, FRAME_IMU, FRAME_WORLD, START_NS, TOPIC_CAMERA_INFO, TOPIC_GPS,
                       TOPIC_GT_ANNOTATIONS, TOPIC_GT_MAG_DISTURBANCE, TOPIC_GT_ORIENTATION,
                       TOPIC_GT_POSE, TOPIC_IMAGE, TOPIC_IMAGE_COMPRESSED, TOPIC_IMU, TOPIC_MAG,
                       TOPIC_TF_STATIC, Msgs)
from .model import Anchor, Lighting, Panorama, World
from .photo_world import photo_panorama
from .render import render_panorama
from .rng import rng_stream
from .scenario import BagRequest, Progress

#: MCAP metadata record naming the simulator profile of a hard rotation_sweep bag (evaluation only).
SIM_METADATA = 'ar_tracking.simulator'
#: The hard profile's revision, in that record: raised whenever the same seed gives another bag
#: (18: camera frames logged after their stamps; 19: parallax on, gyro scale errors), so that a
#: bench does not reuse a stale bag.
SIM_REVISION = '19'
#: Auto-exposure only half compensates the scene brightness (a sunnier day stays brighter).
EXPOSURE_TARGET = 0.2
EXPOSURE_COMPENSATION = 0.4


class RotationSweep:
    """The :class:`.scenario.ScenarioBag` of rotation_sweep (Langlotz et al. 2011, section 6)."""

    name = 'rotation_sweep'

    def write_bag(self, bag: BagWriter, req: BagRequest, progress: Progress | None) -> None:
        scn = rs.make_scenario(req.seed, req.session, req.duration_s, profile=req.profile,
                              imu_time_offset_s=req.imu_time_offset_s, readout_s=req.readout_s,
                              camera_latency_s=req.camera_latency_s)
        if req.world_photos is None:
            world, light, pano = session_view(req.seed, req.session, req.lighting)
            anchors = world.anchors
        else:  # another renderer: a real scene's photos; the street only lights it (no sun in view)
            light = make_lighting(req.seed, req.lighting or req.session, _world(req.seed))
            pano = photo_panorama(req.world_photos, photo_azimuth_deg(req.seed))
            anchors = []
        _write_all(bag, scn, anchors, light, pano, Plan.make(scn, pano), req.image_format, progress,
                   req.world_photos, with_parallax(req))

    def write_sidecars(self, sidecar: Path, bag_path: Path, req: BagRequest) -> None:
        write_sidecar(sidecar, rs.make_scenario(req.seed, req.session, req.duration_s, profile=req.profile,
                                                imu_time_offset_s=req.imu_time_offset_s, readout_s=req.readout_s,
                                                camera_latency_s=req.camera_latency_s),
                      bag_path)

    def summary(self, req: BagRequest) -> str:
        return (f'rotation_sweep, seed {req.seed}, {req.session}, {req.duration_s:.1f} s, '
                f'profile {req.profile}'
                + ('' if req.imu_time_offset_s is None else f', IMU stamps {req.imu_time_offset_s * 1e3:+.1f} ms')
                + ('' if req.readout_s is None else
                   f', rolling shutter {req.readout_s * 1e3:.0f} ms' if req.readout_s else ', global shutter')
                + ('' if req.camera_latency_s is None else f', camera latency {req.camera_latency_s * 1e3:.0f} ms')
                + ('' if req.world_photos is None else f', world from the photos in {req.world_photos}')
                + (', with parallax' if with_parallax(req) else ', without parallax'))


SCENARIO = RotationSweep()


def with_parallax(req: BagRequest) -> bool:
    """Whether the frames show the camera's offset from the spot: as asked, else the profile's
    (the hard profile's phone turns about the user's body, 0.2-0.4 m in front of it; the kind
    profile's about its own centre). A photo world has no depth: no parallax there."""
    if req.world_photos is not None:
        return False
    return req.profile == 'hard' if req.parallax is None else bool(req.parallax)


def session_view(seed: int, session: str, lighting: str | None = None
                 ) -> tuple[World, Lighting, Panorama]:
    """World, lighting and the panorama from the session's standing spot (cached: ~3 s each).

    ``lighting``: the session whose sun lights the spot (default ``session``). Cached by
    (seed, session, lighting or session): ``session_view(1, 'browsing')``,
    ``session_view(1, 'browsing', None)`` and ``session_view(1, 'browsing', 'browsing')`` are
    one view, built once (``functools.lru_cache`` keys them apart)."""
    return _session_view(seed, session, lighting or session)


@functools.lru_cache(maxsize=2)
def _session_view(seed: int, session: str, lighting: str) -> tuple[World, Lighting, Panorama]:
    world = _world(seed)
    light = make_lighting(seed, lighting, world)
    pano = render_panorama(world, light, rs.session_offset(seed, session))
    return world, light, pano


@functools.lru_cache(maxsize=2)
def _world(seed: int) -> World:
    return build_world(seed)


def photo_azimuth_deg(seed: int) -> float:
    """Compass azimuth of the first photo of a photo world: drawn per seed (stream 'photo-world'),
    so that north falls elsewhere in the scene on every seed."""
    return float(rng_stream(seed, 'photo-world', 'authoring').uniform(0.0, 360.0))


# --------------------------------------------------------------------------------------------
# Timing and camera settings


@dataclass(frozen=True)
class Plan:
    """Stamps of every stream and the camera's exposure settings."""

    imu_ns: np.ndarray
    cam_ns: np.ndarray
    gps_ns: np.ndarray
    gain: np.ndarray  # per frame, multiplies linear radiance
    wb: np.ndarray  # (n_frames, 3)

    @staticmethod
    def make(scn: rs.Scenario, pano: Panorama) -> 'Plan':
        dur_ns = int(round(scn.duration_s * 1e9))
        imu = np.arange(0, dur_ns, 1_000_000_000 // rs.IMU_RATE_HZ, dtype=np.int64)
        n_cam = int(math.ceil(dur_ns * rs.CAMERA_RATE_HZ / 1e9))
        cam = (np.arange(n_cam, dtype=np.int64) * 1_000_000_000) // rs.CAMERA_RATE_HZ
        gps = np.arange(0, dur_ns, 1_000_000_000 // rs.GPS_RATE_HZ, dtype=np.int64)
        factor, wb = rs.make_exposure(scn.seed, scn.session, scn.duration_s,
                                      scn.profile).at(cam * 1e-9)
        base = (EXPOSURE_TARGET / max(pano.mean_radiance, 1e-3)) ** EXPOSURE_COMPENSATION
        return Plan(imu, cam, gps, base * factor, wb)


# --------------------------------------------------------------------------------------------
# Writing


def _write_all(bag: BagWriter, scn: rs.Scenario, anchors: list[Anchor], light: Lighting, pano: Panorama,
               plan: Plan, image_format: str, progress: Callable[[float], None] | None,
               world_photos: str | None = None, parallax: bool = False) -> None:
    """All messages in stamp order; images are rendered when their turn comes."""
    m = Msgs()
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
                                        'seed': str(scn.seed), 'session': scn.session,
                                        'revision': SIM_REVISION,
                                        **({} if world_photos is None else
                                           {'world': f'photos:{Path(world_photos).name}'}),
                                        **({'parallax': 'true'} if parallax else {})})

    bag.write(TOPIC_TF_STATIC, first_ns, msg_class('tf2_msgs/msg/TFMessage')(transforms=[
        m.transform_stamped(first_ns, FRAME_IMU, FRAME_CAMERA, np.zeros(3),
                            matrix_to_quat_xyzw(rs.R_IMU_CAM))]))
    bag.write(TOPIC_GT_ANNOTATIONS, first_ns, m.markers(
        first_ns, [a.label for a in anchors], [a.position_enu for a in anchors]))

    # (log time, stream, part, k): IMU + magnetometer (0, 0), ground truth (0, 1), GPS, camera;
    # with no offset and no latency this is the order of the earlier simulator (IMU, truth,
    # GPS, camera). A camera frame is logged camera_latency_ns after its stamp (it arrives
    # behind the IMU samples of its time); every message keeps its stamp in its header.
    lat = int(scn.camera_latency_ns)
    events = sorted([(int(s) + off, 0, 0, k) for k, s in enumerate(plan.imu_ns)]
                    + [(int(s), 0, 1, k) for k, s in enumerate(plan.imu_ns)]
                    + [(int(s), 1, 0, k) for k, s in enumerate(plan.gps_ns)]
                    + [(int(s) + lat, 2, 0, k) for k, s in enumerate(plan.cam_ns)])
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
            t_ns = int(plan.cam_ns[k])  # the frame's stamp; ns is when it arrives
            R = rs.frame_orientations(scn.trajectory, t_ns * 1e-9, cam.fx, scn.readout_s, cam.height)
            offset = scn.trajectory.position(np.array([t_ns * 1e-9]))[0] - pano.viewpoint_enu if parallax else None
            rgb = renderer.render(R, float(plan.gain[k]), plan.wb[k], offset)
            stamp_ns = START_NS + t_ns
            bag.write(TOPIC_CAMERA_INFO, ns, m.camera_info(stamp_ns, cam))
            bag.write(image_topic, ns, m.image(stamp_ns, rgb) if image_format == 'raw'
                      else m.compressed(stamp_ns, rgb))
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
    ``hybrid_orientation_filter``; a rolling shutter's readout under ``panorama_mapper`` when it
    was asked for (the hard profile's own readout is left for the mapper to estimate)."""
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
    camera = '' if not scn.readout_declared else (
        '# The camera has a rolling shutter: its rows are read out over this time after the stamp.\n'
        + dump({'panorama_mapper': {'ros__parameters': {'readout_s': float(scn.readout_s)}}}))
    path.write_text(head + dump(doc) + '# The same calibration for the hybrid filter, which '
                    'reads raw accelerometer and field samples too.\n' + dump(hybrid) + camera)
