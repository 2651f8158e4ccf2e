"""Scenario ``robot_arcs``: a SCARA robot moves a camera + IMU in half circles in front of a
wall of markers (Caarls et al. 2009, sec. 2.6, Fig. 9a and Fig. 10).

The robot's tool moves in the horizontal plane on a half circle of radius 0.55 m around the
robot base, back and forth, one half circle per speed of :data:`ARC_SPEEDS_M_S` (32-224 cm/s,
as in Fig. 9a: "7 half-circles back and forth, radius 55 cm, 32-224 cm/s, accel. time 0.5 s"),
with a pause at each end; the schedule repeats for the length of the bag. The camera looks at
the marker wall 3.2 m away (the pattern "at x = 0.2 m, y = 3.2 m"); the tool turns the camera
by a few degrees with the arc, so that the gyroscopes see a signal. The motion is closed-form
(smooth velocity ramps), so the IMU and the ground truth are exact.

Sensors, as the seed's set-up:

* camera 15 Hz, 640x480 mono8, ideal pinhole (hfov 60 deg, no distortion); the image is
  *published 80 ms after capture* (image processing delay): message log time = capture + 80 ms,
  header stamp = capture time;
* IMU 100 Hz with Xsens MTx-like noise (gyro 0.3 deg/s, accelerometer 0.013 m/s^2 per sample)
  and biases (gyro 0.2-0.6 deg/s with a slow random walk, accelerometer 0.01-0.03 m/s^2).

Markers (OpenCV's AprilTag 36h11 dictionary, one module of white quiet zone) are rendered with
their exact projected corners: each marker's plate is warped into an 8x supersampled patch with
nearest-neighbour lookup (sharp edges exactly where the homography puts them) and box-averaged
down, then the frame is blurred (Gaussian, sigma 0.6 px) and noise is added (sigma 2 grey
levels). One extra marker that is not in the map hangs at the side (an unknown ID).

Topics (log time = header stamp except for the camera):
/camera/image_raw (sensor_msgs/Image mono8, or /camera/image_raw/compressed png), /camera/camera_info,
/imu/data_raw (Imu, frame imu), /tf_static (imu -> camera_optical, R_IMU_CAM = diag(1, -1, -1)),
/ground_truth/pose (PoseStamped enu, the camera), /ground_truth/orientation
(TransformStamped enu -> camera_optical), both at the IMU stamps.

The sidecar ``<bag stem>.params.yaml`` holds the marker_tracker parameters (the marker map
inline, the dictionary) and the visual_inertial_filter parameters (the IMU -> camera rotation
and the sensor noise); ``<bag stem>.markers.yaml`` is the same map as a marker-map file.

The model (schedule, motion, IMU, markers, rendering, parameters) lives in
:mod:`.robot_arcs_model`, shared with the ``hard`` profile (:mod:`.robot_arcs_real`), and every
name of it is importable from here; this module writes the bags and the sidecars.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable

import cv2
import numpy as np
import yaml

from ..core.rotations import matrix_to_quat_xyzw
from . import robot_arcs_real
from .robot_arcs_model import (  # noqa: F401 - the model is part of this module's interface
    ACCEL_TIME_S, ARC_SPEEDS_M_S, ArcSchedule, Array, BLACK, BLUR_SIGMA_PX, CAMERA_HEIGHT_M, CAMERA_RATE_HZ,
    Camera, DICTIONARY, FRAME_CAMERA, FRAME_IMU, FRAME_WORLD, GRAVITY_M_S2, HFOV_RAD, IMAGE_SIZE,
    IMU_RATE_HZ, ImuErrors, MarkerSpec, PAUSE_S, PIXEL_NOISE, PROCESSING_DELAY_NS, R0_ENU_CAM, RADIUS_M,
    R_ENU_WALL_MARKER, R_IMU_CAM, SUPERSAMPLING, Truth, WALL, WHITE, YAW_AMPLITUDE_RAD, arc_motion,
    make_imu_errors, marker_map_doc, marker_plate, project, render_frame, render_markers, sidecar_params,
    simulate_imu, truth_at, wall_markers,
)
from .world import rng_stream


def write_robot_arcs_bag(bag: Any, seed: int, duration_s: float, image_format: str,
                         progress: Callable[[float], None] | None = None,
                         speeds: tuple[float, ...] = ARC_SPEEDS_M_S, profile: str = 'hard') -> None:
    """Write all messages of the scenario into an open BagWriter, in log-time order.
    ``profile`` 'hard' (default): the real-camera effects of :mod:`.robot_arcs_real`; 'kind':
    this module's ideal pinhole camera (its bags byte for byte)."""
    if profile == 'hard':
        robot_arcs_real.write_bag(bag, seed, duration_s, image_format, progress, speeds)
        return
    from ..io.bags import msg_class
    from .messages import START_NS
    from .messages import Msgs as _Msgs

    m = _Msgs()
    cam = Camera()
    sched = ArcSchedule.make(duration_s, speeds)
    mapped, unknown = wall_markers()
    dur_ns = int(round(duration_s * 1e9))
    imu_ns = np.arange(0, dur_ns, 1_000_000_000 // IMU_RATE_HZ, dtype=np.int64)
    n_cam = int(math.ceil(dur_ns * CAMERA_RATE_HZ / 1e9))
    cam_ns = (np.arange(n_cam, dtype=np.int64) * 1_000_000_000) // CAMERA_RATE_HZ
    truth = truth_at(sched, imu_ns * 1e-9)
    err = make_imu_errors(seed)
    gyro, accel = simulate_imu(truth, err, seed)
    q_gt = matrix_to_quat_xyzw(truth.R_enu_cam)
    cam_truth = truth_at(sched, cam_ns * 1e-9)
    pixel_rng = rng_stream(seed, 'robot-arcs-pixels')
    gv, av = err.gyro_noise_rad_s ** 2, err.accel_noise_m_s2 ** 2

    bag.write('/tf_static', START_NS, msg_class('tf2_msgs/msg/TFMessage')(transforms=[
        m.transform_stamped(START_NS, FRAME_IMU, FRAME_CAMERA, np.zeros(3), matrix_to_quat_xyzw(R_IMU_CAM))]))
    events = sorted([(int(s), 0, k) for k, s in enumerate(imu_ns)]
                    + [(int(s) + PROCESSING_DELAY_NS, 1, k) for k, s in enumerate(cam_ns)])
    K = cam.K
    P = np.hstack([K, np.zeros((3, 1))])
    Image = msg_class('sensor_msgs/msg/Image')
    report_every = max(1, n_cam // 50)
    for log_ns, kind, k in events:
        if kind == 0:
            ns = START_NS + log_ns
            bag.write('/imu/data_raw', ns, m.imu(ns, gyro[k], accel[k], gv, av))
            bag.write('/ground_truth/orientation', ns, m.transform_stamped(
                ns, FRAME_WORLD, FRAME_CAMERA, truth.position[k], q_gt[k]))
            bag.write('/ground_truth/pose', ns, m.pose_stamped(ns, FRAME_WORLD, truth.position[k], q_gt[k]))
            continue
        stamp = START_NS + int(cam_ns[k])
        log = START_NS + log_ns
        img, _ = render_frame(cam, cam_truth.R_enu_cam[k], cam_truth.position[k], mapped + unknown, pixel_rng)
        info = msg_class('sensor_msgs/msg/CameraInfo')(
            header=m.header(stamp, FRAME_CAMERA), height=cam.height, width=cam.width,
            distortion_model='plumb_bob', d=np.zeros(5), k=K.ravel(), r=np.eye(3).ravel(),
            p=P.ravel(), binning_x=0, binning_y=0,
            roi=msg_class('sensor_msgs/msg/RegionOfInterest')(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        bag.write('/camera/camera_info', log, info)
        if image_format == 'raw':
            bag.write('/camera/image_raw', log, Image(
                header=m.header(stamp, FRAME_CAMERA), height=cam.height, width=cam.width,
                encoding='mono8', is_bigendian=0, step=cam.width, data=img.reshape(-1)))
        else:
            ok, buf = cv2.imencode('.png', img)
            bag.write('/camera/image_raw/compressed', log, msg_class('sensor_msgs/msg/CompressedImage')(
                header=m.header(stamp, FRAME_CAMERA), format='png', data=buf.reshape(-1)))
        if progress is not None and (k % report_every == 0 or k == n_cam - 1):
            progress((k + 1) / n_cam)


def write_sidecars(params_path: Path, bag_path: Path, seed: int, profile: str = 'hard') -> None:
    """<stem>.params.yaml (both nodes' parameters) and <stem>.markers.yaml (the marker map)."""
    if profile == 'hard':
        head = (f'# Parameters for {bag_path.name} (scenario robot_arcs, profile hard, seed {seed}): the marker\n'
                '# map inline for marker_tracker, the IMU noise for visual_inertial_filter. The IMU mount\n'
                '# (rotation and lever arm) is only on the bag\'s /tf_static, as in a recorded bag.\n')
        params = robot_arcs_real.sidecar_params(seed)
    else:
        head = (f'# Parameters for {bag_path.name} (scenario robot_arcs, seed {seed}): the marker map\n'
                '# inline for marker_tracker, the IMU -> camera rotation and IMU noise for visual_inertial_filter.\n')
        params = sidecar_params(seed)
    params_path.write_text(head + yaml.safe_dump(params, sort_keys=False, default_flow_style=None))
    map_path = params_path.with_name(params_path.name.replace('.params.yaml', '.markers.yaml'))
    map_path.write_text(yaml.safe_dump(marker_map_doc(wall_markers()[0]), sort_keys=False, default_flow_style=None))
