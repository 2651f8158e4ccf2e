"""Report figures of the areas other than orientation, from an output bag.

Each area gets the plots a reader needs to see where its figures come from
(:func:`area_figures`):

* panorama: the tracking error relative to the first frame over time, with the lost frames and
  the camera's angular speed (issue #3 scores tracking below 90 deg/s), and the map built;
* annotations: the browsing panorama with the re-detected labels (annotation_figures.py) and,
  when that module has one, the timeline of which label was shown when;
* slam: top view of the Sim(3)-aligned trajectory and the position error over time
  (slam_figures.py);
* vi: position and orientation error over time of the marker + IMU fusion (``vi/odometry``)
  against the camera alone (the last marker pose that has arrived, held), as in Caarls 2009
  Fig. 10.

Every function returns PNG bytes (or a list of (caption, PNG)) and None / [] when the bag does
not hold the product, so a report shows only what exists. Rendered with matplotlib's Agg backend.
"""
from __future__ import annotations

import io
import logging
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from ..io.bags import BagError, BagReader, stamp_to_ns
from ..ros.conversions import ConversionError, image_to_array

logger = logging.getLogger(__name__)

PANORAMA_IMAGE_TOPIC = '/panorama/image'
#: Lines are thinned to at most this many points: enough for a 1200-pixel-wide figure.
MAX_PLOT_POINTS = 4000

Figures = list[tuple[str, bytes]]


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    return plt


def _png(fig: Any, dpi: int = 90) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format='png', dpi=dpi)
    _pyplot().close(fig)
    return buf.getvalue()


def _thin(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    step = max(1, int(np.ceil(len(arrays[0]) / MAX_PLOT_POINTS)))
    return tuple(a[::step] for a in arrays)


# --- panorama --------------------------------------------------------------------------------

def panorama_png(bag_path: str | Path) -> bytes | None:
    """The last panorama map of the bag (16-bit EDR map shown with a linear tone-mapping)."""
    with BagReader(bag_path) as bag:
        if PANORAMA_IMAGE_TOPIC not in bag.topics:
            return None
        last = None
        for m in bag.messages([PANORAMA_IMAGE_TOPIC]):
            last = m
        if last is None:
            return None
        try:
            msg = bag.deserialize(last)
        except BagError as exc:
            logger.warning('panorama image not shown: %s', exc)
            return None
    try:
        arr = image_to_array(msg)  # honours step, encoding and byte order
    except ConversionError as exc:
        logger.warning('panorama image not shown: %s', exc)
        return None
    img = arr.astype(np.float64)
    mapped = img > 0
    if mapped.any():  # linear tone-mapping of the mapped range to 8 bits
        lo, hi = np.percentile(img[mapped], [0.5, 99.5])
        img = np.clip((img - lo) / max(hi - lo, 1e-9) * 255.0, 0, 255)
    out = img.astype(np.uint8)
    if out.ndim == 3 and msg.encoding.startswith('rgb'):
        out = cv2.cvtColor(out, cv2.COLOR_RGB2BGR)
    ok, png = cv2.imencode('.png', out)
    return png.tobytes() if ok else None


def panorama_tracking_png(bag_path: str | Path, target_deg: float | None = 0.25) -> bytes | None:
    """Tracking error of ``panorama/orientation`` relative to the first frame over time (the
    measure ``panorama.tracking_rmse_deg``), the lost camera frames marked, and the camera's
    angular speed from the truth; None without the estimate or the truth."""
    from .panorama_metrics import (
        _R,
        CAMERA_INFO_TOPIC,
        PANORAMA_TOPIC,
        TRUTH_TOPIC,
        _rates_deg_s,
        tracking_errors,
    )

    est: list[tuple[int, Any]] = []
    truth: list[tuple[int, Any]] = []
    frames: list[int] = []
    with BagReader(bag_path) as bag:
        topics = bag.topics
        if PANORAMA_TOPIC not in topics or TRUTH_TOPIC not in topics:
            return None
        wanted = [t for t in (PANORAMA_TOPIC, TRUTH_TOPIC, CAMERA_INFO_TOPIC) if t in topics]
        for m in bag.messages(wanted):
            try:
                msg = bag.deserialize(m)
            except BagError:
                continue
            stamp = stamp_to_ns(msg.header.stamp)
            if m.topic == CAMERA_INFO_TOPIC:
                frames.append(stamp)
            else:
                (est if m.topic == PANORAMA_TOPIC else truth).append((stamp, _R(msg.transform.rotation)))
    if not est or len(truth) < 2:
        return None
    est.sort(key=lambda e: e[0])
    truth.sort(key=lambda e: e[0])
    ts = np.array([s for s, _ in truth], np.int64)
    Rt = np.array([R for _, R in truth])
    st, err = tracking_errors(np.array([s for s, _ in est], np.int64), np.array([R for _, R in est]), ts, Rt)
    if err.size == 0:
        return None
    t0 = int(ts[0])
    have = {s for s, _ in est}
    lost = np.array(sorted(s for s in set(frames) if s not in have and s > est[0][0]), np.int64)
    rate = _rates_deg_s(ts, Rt)

    plt = _pyplot()
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(11, 5.5), sharex=True, gridspec_kw={'height_ratios': [2, 1]})
    t, e = _thin((st - t0) * 1e-9, err)
    rms = float(np.sqrt(np.mean(err ** 2)))
    ax0.plot(t, e, color='tab:blue', lw=1.0, label=f'panorama tracking error (RMSE {rms:.3f} deg)')
    if target_deg is not None:
        ax0.axhline(target_deg, color='tab:green', lw=1.0, ls='--', label=f'target RMSE {target_deg:g} deg (#3)')
    if lost.size:
        ax0.plot((lost - t0) * 1e-9, np.zeros(lost.size), '|', color='tab:red', ms=10,
                 label=f'lost frames ({lost.size})')
    ax0.set_ylabel('error vs truth [deg]\n(relative to the first frame)')
    ax0.set_ylim(bottom=0.0)
    ax0.legend(loc='upper right', fontsize=8)
    ax0.grid(alpha=0.3)
    tr, r = _thin((ts[1:] - t0) * 1e-9, rate)
    ax1.plot(tr, r, color='0.3', lw=0.8, label='camera angular speed (truth)')
    ax1.axhline(90.0, color='tab:red', lw=0.8, ls=':', label='90 deg/s')
    ax1.set_ylabel('[deg/s]')
    ax1.set_xlabel('time since the first ground-truth stamp [s]')
    ax1.legend(loc='upper right', fontsize=8)
    ax1.grid(alpha=0.3)
    fig.suptitle(f'Panorama tracking (panorama/orientation) against the truth: {Path(bag_path).name}', fontsize=10)
    fig.tight_layout()
    return _png(fig)


def panorama_figures(bag_path: str | Path) -> Figures:
    figures: Figures = []
    track = panorama_tracking_png(bag_path)
    if track is not None:
        figures.append(('Panorama tracking error over time (lost frames in red) and the angular speed', track))
    pano = panorama_png(bag_path)
    if pano is not None:
        figures.append(('Panorama map built during the run (panorama/image, last message)', pano))
    return figures


# --- annotations -----------------------------------------------------------------------------

def annotation_figures_of(bag_path: str | Path) -> Figures:
    """The annotation figures annotation_figures.py provides (whatever of them exists)."""
    from . import annotation_figures as af

    figures: Figures = []
    with tempfile.TemporaryDirectory() as tmp:
        written = af.annotation_figure(bag_path, Path(tmp) / 'annotations.png')
        if written is not None:
            figures.append(('Annotations placed in the panorama (matched green, inferred by alignment '
                            'another colour) and AR overlay frames', written.read_bytes()))
        # the timeline (which label was shown when, and whether it was right) is annotation_figures'
        # own: drawn when that module has a public ``*timeline*(bag, png)`` function
        timeline: Callable[..., Any] | None = next(
            (getattr(af, n) for n in sorted(dir(af)) if 'timeline' in n and not n.startswith('_')
             and callable(getattr(af, n))), None)
        if timeline is not None:
            try:
                out = timeline(bag_path, Path(tmp) / 'timeline.png')
            except Exception as exc:  # a figure of another module must not cost the report
                logger.warning('annotation timeline not drawn: %s: %s', type(exc).__name__, exc)
                out = None
            if out is not None:
                data = out if isinstance(out, bytes) else Path(out).read_bytes()
                figures.append(('Annotation timeline: which label was shown when, and whether it was right', data))
    return figures


# --- slam ------------------------------------------------------------------------------------

def slam_figures_of(bag_path: str | Path) -> Figures:
    if not _has_topic(bag_path, '/slam/pose'):
        return []
    from .slam_figures import slam_figure

    with tempfile.TemporaryDirectory() as tmp:
        written = slam_figure(bag_path, Path(tmp) / 'slam.png')
        if written is None:
            return []
        return [('Keyframe SLAM (slam/pose) against the ground truth after a Sim(3) '
                 'alignment: top view and position error over time', written.read_bytes())]


# --- vi --------------------------------------------------------------------------------------

def _pose_errors(truth: Any, t_ns: NDArray[np.int64], p: np.ndarray, R: np.ndarray
                 ) -> tuple[NDArray[np.int64], np.ndarray, np.ndarray]:
    """(stamps inside the truth, position error m, orientation error deg)."""
    from ..core.rotations import angle_of
    from .vi_metrics import truth_at

    if len(t_ns) == 0:
        return t_ns, np.zeros(0), np.zeros(0)
    pt, Rt, inside = truth_at(truth, t_ns)
    perr = np.linalg.norm(p[inside] - pt, axis=1)
    oerr = np.degrees(angle_of(R[inside] @ np.swapaxes(Rt, 1, 2)))
    return t_ns[inside], perr, oerr


def vi_png(bag_path: str | Path) -> bytes | None:
    """Position and orientation error over time of ``vi/odometry`` and of the camera alone
    (``markers/pose`` held from its arrival, and at its capture stamps); None without
    ``vi/odometry`` or ``ground_truth/pose``."""
    from .vi_metrics import WARMUP_S, hold_camera, load_vi

    data = load_vi(bag_path)
    if data is None:
        return None
    t0 = int(data.truth.t_ns[0])
    warm = int(data.odom.t_ns[0] + WARMUP_S * 1e9)
    series: list[tuple[str, str, float, tuple[NDArray[np.int64], np.ndarray, np.ndarray]]] = []
    keep = data.odom.t_ns >= warm
    series.append(('marker + IMU fusion (vi/odometry)', 'tab:blue', 1.0,
                   _pose_errors(data.truth, data.odom.t_ns[keep], data.odom.p[keep], data.odom.R[keep])))
    if len(data.camera) and data.camera.log_ns is not None:
        grid = data.odom.t_ns[keep]
        p, R, ok = hold_camera(data.camera, grid)
        series.append(('camera only, last pose that arrived held', 'tab:orange', 0.8,
                       _pose_errors(data.truth, grid[ok], p, R)))
        cam_keep = data.camera.t_ns >= warm
        series.append(('camera only, at its capture time (markers/pose)', 'tab:gray', 0.0,
                       _pose_errors(data.truth, data.camera.t_ns[cam_keep], data.camera.p[cam_keep],
                                    data.camera.R[cam_keep])))
    plt = _pyplot()
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(11, 6), sharex=True)
    for label, colour, lw, (t, perr, oerr) in series:
        if len(t) == 0:
            continue
        tt, pe, oe = _thin((t - t0) * 1e-9, perr * 100.0, oerr)
        rms_p = float(np.sqrt(np.mean(perr ** 2))) * 100.0
        rms_o = float(np.sqrt(np.mean(oerr ** 2)))
        style: dict[str, Any] = ({'ls': 'none', 'marker': '.', 'ms': 3} if lw == 0.0 else {'lw': lw})
        ax0.plot(tt, pe, color=colour, label=f'{label}: RMSE {rms_p:.2f} cm', **style)
        ax1.plot(tt, oe, color=colour, label=f'{label}: RMSE {rms_o:.3f} deg', **style)
    ax0.set_ylabel('position error [cm]')
    ax1.set_ylabel('orientation error [deg]')
    ax1.set_xlabel('time since the first ground-truth stamp [s]')
    for ax in (ax0, ax1):
        ax.set_yscale('log')
        ax.grid(alpha=0.3, which='both')
        ax.legend(loc='upper right', fontsize=8)
    fig.suptitle(f'Marker + IMU tracking against ground_truth/pose: {Path(bag_path).name}', fontsize=10)
    fig.tight_layout()
    return _png(fig)


def vi_figures(bag_path: str | Path) -> Figures:
    png = vi_png(bag_path)
    return [('Marker + IMU fusion against the camera alone: position and orientation error over time '
             '(log scale)', png)] if png is not None else []


# --- all -------------------------------------------------------------------------------------

#: area -> the function that draws its figures.
AREA_FIGURES: dict[str, Callable[[str | Path], Figures]] = {
    'panorama': panorama_figures, 'annotations': annotation_figures_of, 'slam': slam_figures_of,
    'vi': vi_figures,
}


def area_figures(bag_path: str | Path, areas: list[str] | None = None) -> dict[str, Figures]:
    """area -> [(caption, PNG)] for every area (or the ones named) that has a figure in the
    bag. A figure that fails is logged and left out: it never costs the rest of the report."""
    out: dict[str, Figures] = {}
    for area, draw in AREA_FIGURES.items():
        if areas is not None and area not in areas:
            continue
        try:
            figures = draw(bag_path)
        except (BagError, ValueError, KeyError, IndexError) as exc:
            logger.warning('%s figure not drawn: %s: %s', area, type(exc).__name__, exc)
            figures = []
        if figures:
            out[area] = figures
    return out


def extra_figures(bag_path: str | Path) -> Figures:
    """(caption, PNG) of every extra product the bag holds, areas in order."""
    return [fig for figures in area_figures(bag_path).values() for fig in figures]


def _has_topic(bag_path: str | Path, topic: str) -> bool:
    try:
        with BagReader(bag_path) as reader:
            return topic in reader.topics
    except BagError:
        return False
