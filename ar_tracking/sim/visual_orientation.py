"""A stand-in for the panorama tracker: ``/panorama/orientation`` made from the ground truth.

Until panorama_mapper (issue #3) lands, the hybrid filter (Langlotz 2011 sec. 5) is tested on a
visual orientation synthesised from a bag's ``/ground_truth/orientation``: the true camera
orientation relative to the first camera frame (the panorama frame P = the camera at the first
frame, DESIGN sec. 3), at the camera's stamps, with what a real panorama tracker adds:

* white noise per frame (``noise_deg``, default 0.05 deg: a fraction of a map pixel, 0.176 deg);
* slow drift: a random walk of the panorama frame (``drift_deg_sqrt_s`` per axis) plus a steady
  turn about the panorama's vertical axis (``drift_rate_deg_s``), as mapping errors accumulate;
* lost intervals: a few stretches per minute without any message (fast motion, blur).

The output bag has every topic of the input plus ``/panorama/orientation``
(geometry_msgs/TransformStamped, frame_id ``panorama``, child ``camera_optical``: R_pano_cam),
and the input's sidecar params file is copied next to it. Seeded: same inputs, same bytes.
"""
from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..core.rotations import interpolate_rotations, matrix_to_quat_xyzw, quat_xyzw_to_matrix, rotvec_to_matrix
from ..io.bags import BagError, BagReader, BagWriter, msg_class, ns_to_stamp, stamp_to_ns

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

TOPIC_VISUAL = '/panorama/orientation'
TOPIC_TRUTH = '/ground_truth/orientation'
CAMERA_TOPICS = ('/camera/camera_info', '/camera/image_raw', '/camera/image_raw/compressed')
FRAME_PANORAMA = 'panorama'
FRAME_CAMERA = 'camera_optical'


@dataclass(frozen=True)
class VisualErrorModel:
    """Errors of the synthetic visual tracker (degrees, seconds)."""

    noise_deg: float = 0.05
    drift_deg_sqrt_s: float = 0.02
    drift_rate_deg_s: float = 0.005
    lost_per_min: float = 2.0
    lost_min_s: float = 0.5
    lost_max_s: float = 2.0


def synthesize_visual(
    truth_ns: NDArray[np.int64], R_enu_cam: Array, camera_ns: NDArray[np.int64],
    seed: int = 0, model: VisualErrorModel | None = None,
) -> tuple[NDArray[np.int64], Array]:
    """(stamps, R_pano_cam) of the synthetic tracker at the camera stamps (lost ones left out)."""
    model = model or VisualErrorModel()
    rng = np.random.default_rng(seed)
    truth_ns = np.asarray(truth_ns, dtype=np.int64)
    camera_ns = np.asarray(camera_ns, dtype=np.int64)
    t0 = int(truth_ns[0])
    R_true, inside = interpolate_rotations((truth_ns - t0).astype(float), R_enu_cam,
                                           (camera_ns - t0).astype(float))
    cam = camera_ns[inside]
    if len(cam) == 0:
        return cam, np.zeros((0, 3, 3))
    R_pano_cam = np.swapaxes(R_true[0], -1, -2) @ R_true  # relative to the first frame
    t_s = (cam - cam[0]) * 1e-9
    dt = np.diff(t_s, prepend=t_s[0])
    walk = np.cumsum(rng.normal(0.0, 1.0, (len(cam), 3)) * np.sqrt(dt)[:, None], axis=0)
    drift = np.radians(model.drift_deg_sqrt_s) * walk
    # Steady turn about the panorama's vertical axis (the first frame's image-up, -y).
    up_pano = -R_pano_cam[0][:, 1]
    drift += np.radians(model.drift_rate_deg_s) * t_s[:, None] * up_pano[None, :]
    noise = rng.normal(0.0, np.radians(model.noise_deg), (len(cam), 3))
    R_meas = rotvec_to_matrix(drift) @ R_pano_cam @ rotvec_to_matrix(noise)
    R_meas[0] = np.eye(3)  # the panorama frame is the first frame
    keep = np.ones(len(cam), dtype=bool)
    duration = t_s[-1]
    n_lost = int(rng.poisson(model.lost_per_min * duration / 60.0))
    for _ in range(n_lost):
        start = rng.uniform(min(3.0, duration), duration)
        length = rng.uniform(model.lost_min_s, model.lost_max_s)
        keep &= ~((t_s >= start) & (t_s < start + length))
    return cam[keep], R_meas[keep]


def _camera_stamps(bag: BagReader) -> NDArray[np.int64]:
    topics = bag.topics
    for topic in CAMERA_TOPICS:
        if topic in topics:
            stamps = [stamp_to_ns(bag.deserialize(m).header.stamp) for m in bag.messages([topic])]
            return np.unique(np.asarray(stamps, dtype=np.int64))
    raise BagError(f'{bag.path}: no camera topic ({", ".join(CAMERA_TOPICS)}) for the stamps')


def add_visual_orientation(bag_in: str | Path, bag_out: str | Path, seed: int = 0,
                           model: VisualErrorModel | None = None) -> Path:
    """Copy ``bag_in`` to ``bag_out`` (mcap) adding ``/panorama/orientation``; returns bag_out.

    The sidecar ``<bag_in>.params.yaml`` is copied to ``<bag_out>.params.yaml`` when present.
    Raises :class:`BagError` when the bag has no ground truth or no camera stamps.
    """
    bag_in, bag_out = Path(bag_in), Path(bag_out)
    with BagReader(bag_in) as bag:
        if TOPIC_TRUTH not in bag.topics:
            raise BagError(f'{bag_in}: no {TOPIC_TRUTH} to synthesise a visual orientation from')
        truth_t, truth_R = [], []
        for m in bag.messages([TOPIC_TRUTH]):
            msg = bag.deserialize(m)
            q = msg.transform.rotation
            truth_t.append(stamp_to_ns(msg.header.stamp))
            truth_R.append(quat_xyzw_to_matrix(np.array([q.x, q.y, q.z, q.w])))
        order = np.argsort(truth_t, kind='stable')
        stamps, R = synthesize_visual(np.asarray(truth_t, np.int64)[order], np.asarray(truth_R)[order],
                                      _camera_stamps(bag), seed, model)
        TS = msg_class('geometry_msgs/msg/TransformStamped')
        Header = msg_class('std_msgs/msg/Header')
        Tf = msg_class('geometry_msgs/msg/Transform')
        V3 = msg_class('geometry_msgs/msg/Vector3')
        Q = msg_class('geometry_msgs/msg/Quaternion')
        visual = []
        for t, Rk in zip(stamps, R, strict=True):
            q = matrix_to_quat_xyzw(Rk)
            visual.append((int(t), TS(header=Header(stamp=ns_to_stamp(int(t)), frame_id=FRAME_PANORAMA),
                                      child_frame_id=FRAME_CAMERA,
                                      transform=Tf(translation=V3(x=0.0, y=0.0, z=0.0),
                                                   rotation=Q(x=q[0], y=q[1], z=q[2], w=q[3])))))
        i = 0
        with BagWriter(bag_out, overwrite=True) as out:
            for m in bag.messages():
                while i < len(visual) and visual[i][0] <= m.log_time_ns:
                    out.write(TOPIC_VISUAL, visual[i][0], visual[i][1])
                    i += 1
                out.write(m.topic, m.log_time_ns, m.rawdata, msgtype=m.msgtype)
            for t, msg in visual[i:]:
                out.write(TOPIC_VISUAL, t, msg)
    sidecar = bag_in.with_name(bag_in.name[: -len(bag_in.suffix)] + '.params.yaml') if bag_in.suffix \
        else bag_in.with_name(bag_in.name + '.params.yaml')
    if sidecar.exists():
        target = bag_out.with_name(bag_out.name[: -len(bag_out.suffix)] + '.params.yaml')
        shutil.copyfile(sidecar, target)
    logger.info('wrote %s with %d visual orientations (%d lost frames)', bag_out, len(visual),
                0 if len(stamps) == 0 else int(round((stamps[-1] - stamps[0]) * 30e-9)) + 1 - len(visual))
    return bag_out


def visual_bag(workdir: Path, seed: int = 1, duration_s: float = 60.0) -> Path:
    """A rotation_sweep bag with /panorama/orientation (made once in ``workdir``, then reused)."""
    from .bagmaker import make_bag

    workdir.mkdir(parents=True, exist_ok=True)
    out = workdir / f'rotation_sweep_seed{seed}_{duration_s:g}s_visual.mcap'
    if not out.exists():
        src = workdir / f'rotation_sweep_seed{seed}_{duration_s:g}s.mcap'
        if not src.exists():
            make_bag('rotation_sweep', src, seed=seed, duration_s=duration_s, overwrite=True)
        add_visual_orientation(src, out, seed=seed)
    return out
