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

Dispatch: each scenario is a :class:`.scenario.ScenarioBag` (rotation_sweep in
:mod:`.rotation_sweep_bag`, handheld_desk in :mod:`.handheld_desk`, robot_arcs through the adapter
below); this module checks the arguments, opens the bag and calls it. The scenarios import their
message builders from :mod:`.messages`, never this module, so there is no import cycle.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..io.bags import BagError, BagWriter
from . import handheld_desk, robot_arcs
from . import rotation_sweep as rs
from . import rotation_sweep_bag
from .messages import START_NS
from .messages import Msgs as _Msgs  # noqa: F401  (the old name, for test/eval)
from .rotation_sweep_bag import (EXPOSURE_COMPENSATION, EXPOSURE_TARGET,
                                 SIM_METADATA, session_view)
from .scenario import BagRequest, Progress, ScenarioBag, SimError

logger = logging.getLogger(__name__)

__all__ = ['EXPOSURE_COMPENSATION', 'EXPOSURE_TARGET', 'IMAGE_FORMATS', 'MAX_DURATION_S', 'PROFILES',
           'SCENARIOS', 'SESSIONS', 'SIM_METADATA', 'START_NS', 'STORAGES', 'SimError', 'make_bag',
           'session_view', 'sidecar_path']


class _RobotArcs:
    """The :class:`.scenario.ScenarioBag` of robot_arcs (Caarls et al. 2009, Fig. 9): an adapter
    over :mod:`.robot_arcs`, which keeps its own entry points (the session is ignored)."""

    name = 'robot_arcs'

    def write_bag(self, bag: Any, req: BagRequest, progress: Progress | None) -> None:
        robot_arcs.write_robot_arcs_bag(bag, req.seed, req.duration_s, req.image_format, progress,
                                        profile=req.profile)

    def write_sidecars(self, sidecar: Path, bag_path: Path, req: BagRequest) -> None:
        robot_arcs.write_sidecars(sidecar, bag_path, req.seed, profile=req.profile)

    def summary(self, req: BagRequest) -> str:
        return f'robot_arcs, seed {req.seed}, {req.duration_s:.1f} s, profile {req.profile}'


#: The scenarios by name, in the order the CLI lists them.
REGISTRY: dict[str, ScenarioBag] = {s.name: s for s in (rotation_sweep_bag.SCENARIO, _RobotArcs(),
                                                        handheld_desk.SCENARIO)}
SCENARIOS: tuple[str, ...] = tuple(REGISTRY)
SESSIONS: tuple[str, ...] = rs.SESSIONS
STORAGES: tuple[str, ...] = ('mcap', 'sqlite3')
IMAGE_FORMATS: tuple[str, ...] = ('raw', 'compressed')
PROFILES: tuple[str, ...] = rs.PROFILES
MAX_DURATION_S = 3600.0


def make_bag(scenario: str, out: str | Path, *, seed: int = 0, duration_s: float = 60.0,
             session: str = 'authoring', storage: str = 'mcap', image_format: str = 'raw',
             overwrite: bool = False, progress: Callable[[float], None] | None = None,
             lighting: str | None = None, profile: str = 'hard', imu_time_offset_s: float | None = None,
             readout_s: float | None = None, camera_latency_s: float | None = None,
             world_photos: str | Path | None = None, parallax: bool | None = None) -> Path:
    """Writes the bag and a sidecar '<out stem>.params.yaml' next to it; returns the bag path.

    ``storage`` 'mcap' gives one ``.mcap`` file (the suffix is added when missing), 'sqlite3' a
    rosbag2 directory. ``progress`` is called now and then with the fraction done (0..1).
    ``lighting`` (rotation_sweep only): the session whose sun and sky light the spot, default
    ``session``; e.g. a browsing walk under the authoring sun (the 'same lighting' column of
    Langlotz 2011 Fig. 7). ``imu_time_offset_s`` (rotation_sweep only): the IMU and
    magnetometer stamps minus the true time instead of the profile's offset; ``readout_s``
    (rotation_sweep only): the camera's rolling-shutter readout instead of the profile's (hard:
    8-30 ms per seed, not in the sidecar; kind: 0), written to the sidecar; 0 is a global shutter;
    ``camera_latency_s`` (rotation_sweep only): how long after its stamp each camera frame is
    logged (hard: 30-120 ms per seed; kind: 0). ``world_photos`` (rotation_sweep only): a folder
    of photos of a full turn (with ``pano.txt`` focal lengths, e.g. ../shared/data/pano_grail)
    whose panorama the camera frames are cut from instead of the rendered street (another
    renderer: real textures; the sensors and the truth are unchanged, the bag has no
    annotations). ``parallax`` (rotation_sweep only): the frames are rendered from where the
    camera is (0.2-0.4 m in front of the body's turning axis in the hard profile, plus the hand's
    sway), not from the spot: near objects move against far ones; None (default): the profile's,
    on in 'hard' (a photo world has no depth: no parallax there), off in 'kind'. ``profile`` (rotation_sweep, robot_arcs): 'hard' (default, a realistic
    phone or camera) or 'kind' (the earlier, easier simulator; byte for byte its bags). Raises
    :class:`SimError` for bad arguments (including an existing output without ``overwrite``).
    """
    _check_args(scenario, seed, duration_s, session, storage, image_format)
    if profile not in PROFILES:
        raise SimError(f'unknown profile {profile!r} (use {" or ".join(PROFILES)})')
    if lighting is not None and lighting not in SESSIONS:
        raise SimError(f'unknown lighting {lighting!r} (use {" or ".join(SESSIONS)})')
    if imu_time_offset_s is not None:
        _check_sweep_seconds(scenario, 'IMU time offset', imu_time_offset_s, -1.0, 1.0)
    if readout_s is not None:
        _check_sweep_seconds(scenario, 'readout time', readout_s, 0.0, 0.1)
    if camera_latency_s is not None:
        _check_sweep_seconds(scenario, 'camera latency', camera_latency_s, 0.0, 1.0)
    if world_photos is not None:
        if scenario != 'rotation_sweep':
            raise SimError(f'world photos are a rotation_sweep option, not one of {scenario}')
        from .photo_world import read_sequence
        read_sequence(world_photos)  # here, so that a bad folder fails before the bag is opened
    bag_path = _bag_path(Path(out), storage)
    sidecar = sidecar_path(bag_path)
    if not overwrite:
        for p in (bag_path, sidecar):
            if p.exists():
                raise SimError(f'{p}: already exists (choose another name or overwrite)')
    scn = REGISTRY[scenario]
    req = BagRequest(seed, duration_s, session, image_format, lighting, profile, imu_time_offset_s,
                     None if readout_s is None else float(readout_s),
                     None if camera_latency_s is None else float(camera_latency_s),
                     None if world_photos is None else str(world_photos),
                     None if parallax is None else bool(parallax))
    try:
        with BagWriter(bag_path, storage=storage, overwrite=overwrite) as bag:  # type: ignore
            scn.write_bag(bag, req, progress)
    except BagError as exc:
        raise SimError(str(exc)) from exc
    scn.write_sidecars(sidecar, bag_path, req)
    logger.info('wrote %s (%s) and %s', bag_path, scn.summary(req), sidecar.name)
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


def _check_sweep_seconds(scenario: str, what: str, value: object, lo: float, hi: float) -> None:
    """A rotation_sweep option in seconds: SimError unless the scenario has it and the value
    is a finite number in [lo, hi]."""
    if scenario != 'rotation_sweep':
        raise SimError(f'the {what} is a rotation_sweep option, not one of {scenario}')
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) \
            or not math.isfinite(value) or not lo <= value <= hi:
        raise SimError(f'the {what} must be a finite number of seconds in [{lo:g}, {hi:g}], got {value!r}')


def _bag_path(out: Path, storage: str) -> Path:
    if storage == 'mcap':
        return out if out.suffix == '.mcap' else out.with_name(out.name + '.mcap')
    return out.with_suffix('') if out.suffix in ('.mcap', '.db3') else out
