"""The authoring panorama's place in the world, estimated as the browsing graph estimates it
(Langlotz 2011 sec. 5, eq. 1-2), for the sensor prior of sec. 4.2 when its annotations are browsed.

Authoring must not read the simulator's truth: a real device has none. The same cores as the
browsing graph run here on the authoring session's own samples:

* :class:`~ar_tracking.core.world_alignment.WorldAlignment` (the hybrid filter's R_PN): every
  calibrated accelerometer/field sample with the IMU's orientation in the panorama frame at its
  stamp (the visual tracker's R_pano_cam slerped to the sample's header stamp, never across a gap
  of more than ``max_visual_gap_s``; R_pano_imu = R_pano_cam R_imu_cam^T), paired with the newest
  field sample no older than ``max_mag_age_s``, exactly as ``hybrid_orientation_filter`` feeds it;
* :class:`~ar_tracking.core.ahrs.Ahrs` (imu_magnetometer's filter) over the same samples: its
  R_enu_imu(t) R_imu_cam R_pano_cam(t)^T, averaged over the session (chordal mean), is a second,
  independent estimate; its disagreement with the alignment is reported, and it is the fallback
  when the alignment has no field sample (then flagged, with the AHRS covariance).

Result (:class:`PanoramaWorld`): R_enu_pano, its covariance (ENU axes x, y tilt, z heading, rad^2),
the up direction in the panorama frame (gravity, from the alignment's R_PN) and which estimator
gave it. Offline: samples are collected and paired once at :meth:`PanoramaWorldEstimator.estimate`.
"""
from __future__ import annotations

import bisect
import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..ahrs import Ahrs, AhrsConfig, AhrsEstimate
from ..imu_orientation import ImuCalibration
from ..rotations import nearest_rotation, so3_exp, so3_log
from ..world_alignment import WorldAlignment, WorldAlignmentConfig

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: R_imu_cam of the default mount (imu_to_camera_quat_xyzw [1, 0, 0, 0]: 180 deg about x).
DEFAULT_R_IMU_CAM = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class PanoramaWorld:
    """The estimated orientation of a panorama in ENU (R_enu_pano) and its uncertainty."""

    R_enu_pano: Array
    #: Covariance of the error of R_enu_pano about the ENU axes (x, y: tilt; z: heading), rad^2.
    covariance_enu: Array
    #: 'world_alignment' (the hybrid filter's R_PN) or 'ahrs' (fallback: no field sample paired).
    source: str
    #: Angle between the alignment's and the AHRS's estimate, rad (NaN when one is missing).
    ahrs_disagreement_rad: float = float('nan')
    #: IMU samples paired with the visual orientation.
    samples: int = 0

    @property
    def up(self) -> Array:
        """ENU up (gravity's opposite) in the panorama frame."""
        return self.R_enu_pano[2].copy()

    @property
    def heading_sigma_rad(self) -> float:
        return float(math.sqrt(max(self.covariance_enu[2, 2], 0.0)))

    @property
    def tilt_sigma_rad(self) -> float:
        return float(math.sqrt(max(0.5 * (self.covariance_enu[0, 0] + self.covariance_enu[1, 1]), 0.0)))


class PanoramaWorldEstimator:
    """Collects one authoring session's visual orientations and raw IMU/field samples (stamped
    with their header stamps, ns) and estimates the panorama's orientation in ENU (module doc)."""

    def __init__(self, calibration: ImuCalibration | None = None, R_imu_cam: Array | None = None,
                 alignment: WorldAlignmentConfig | None = None, ahrs: AhrsConfig | None = None,
                 max_visual_gap_s: float = 0.2, max_mag_age_s: float = 0.1) -> None:
        self.calibration = calibration or ImuCalibration()
        self.R_imu_cam = DEFAULT_R_IMU_CAM.copy() if R_imu_cam is None else np.asarray(R_imu_cam, float)
        self.alignment_config = alignment or WorldAlignmentConfig()
        self.ahrs_config = ahrs or AhrsConfig(declination_rad=self.alignment_config.declination_rad)
        self.max_gap_ns = int(max_visual_gap_s * 1e9)
        self.max_mag_age_ns = int(max_mag_age_s * 1e9)
        self.visual: list[tuple[int, Array]] = []
        self.imu: list[tuple[int, Array, Array]] = []
        self.mag: list[tuple[int, Array]] = []

    def add_visual(self, t_ns: int, R_pano_cam: Array) -> None:
        """The visual tracker's camera orientation in the panorama frame at a frame's stamp."""
        self.visual.append((int(t_ns), np.asarray(R_pano_cam, float)))

    def add_imu(self, t_ns: int, gyro_rad_s: Array, accel_m_s2: Array) -> None:
        """One raw gyro/accelerometer sample (calibrated here)."""
        g, a = np.asarray(gyro_rad_s, float), np.asarray(accel_m_s2, float)
        if g.shape == (3,) and a.shape == (3,) and np.all(np.isfinite(g)) and np.all(np.isfinite(a)) \
                and float(a @ a) > 0:
            self.imu.append((int(t_ns), g, a))

    def add_mag(self, t_ns: int, field_t: Array) -> None:
        """One raw magnetometer sample, tesla (calibrated here)."""
        m = np.asarray(field_t, float)
        if m.shape == (3,) and np.all(np.isfinite(m)) and float(m @ m) > 0:
            self.mag.append((int(t_ns), m))

    def _visual_at(self, ts: list[int], t: int) -> Array | None:
        k = bisect.bisect_left(ts, t)
        if k < len(ts) and ts[k] == t:
            return self.visual[k][1]
        if k == 0 or k == len(ts):
            return None
        t0, R0 = self.visual[k - 1]
        t1, R1 = self.visual[k]
        if t1 - t0 > self.max_gap_ns:
            return None
        return R0 @ so3_exp((t - t0) / (t1 - t0) * so3_log(R0.T @ R1))

    def estimate(self) -> PanoramaWorld | None:
        """The estimate over every sample given so far (None without paired IMU samples)."""
        self.visual.sort(key=lambda x: x[0])
        self.imu.sort(key=lambda x: x[0])
        self.mag.sort(key=lambda x: x[0])
        vts = [t for t, _ in self.visual]
        mts = [t for t, _ in self.mag]
        align = WorldAlignment(self.alignment_config)
        ahrs = Ahrs(self.ahrs_config, self.calibration)
        ahrs_sum = np.zeros((3, 3))
        n = n_ahrs = 0
        cal = self.calibration
        next_field = 0  # each field sample joins the alignment once, at its own stamp
        for t, gyro, accel in self.imu:
            k = bisect.bisect_right(mts, t) - 1
            raw_mag = self.mag[k][1] if k >= 0 and t - mts[k] <= self.max_mag_age_ns else None
            est = ahrs.update(t, gyro, accel, raw_mag, mts[k] if raw_mag is not None else None)
            R_pano_cam = self._visual_at(vts, t)
            if R_pano_cam is not None:
                R_pano_imu = R_pano_cam @ self.R_imu_cam.T
                align.add(t, R_pano_imu, cal.accel(accel), None, cal.gyro(gyro))
                n += 1
            while next_field <= k:
                t_m, raw = self.mag[next_field]
                next_field += 1
                R_field = self._visual_at(vts, t_m)
                if R_field is not None:
                    align.add_field(t_m, R_field @ self.R_imu_cam.T, cal.mag(raw))
            if R_pano_cam is None:
                continue
            if isinstance(est, AhrsEstimate) and est.mag_used:
                ahrs_sum += est.R_enu_body @ R_pano_imu.T
                n_ahrs += 1
        if n == 0:
            return None
        R_ahrs = nearest_rotation(ahrs_sum) if n_ahrs else None
        world = align.estimate()
        if world is not None:
            R = world.R_pano_enu.T
            diff = float(np.linalg.norm(so3_log(R_ahrs.T @ R))) if R_ahrs is not None else float('nan')
            return PanoramaWorld(R, np.asarray(world.covariance_enu, float), 'world_alignment', diff, n)
        if R_ahrs is None:
            return None
        logger.warning('world alignment has no field sample: the AHRS places the panorama in the world')
        c = self.ahrs_config  # the AHRS's own floors (its per-sample covariance is not averaged down)
        cov = np.diag([c.tilt_sigma_floor_rad ** 2, c.tilt_sigma_floor_rad ** 2, c.heading_sigma_floor_rad ** 2])
        return PanoramaWorld(R_ahrs, cov, 'ahrs', float('nan'), n)
