"""Speed of the panorama core (no ROS) and a comparison with cv2.Stitcher (issue #3).

``bench_panorama(workdir)`` returns (DESIGN sec. 8, area ``panorama``)::

    {"fps_320x240", "fps_640x480", "frames", "stitcher_time_ratio", "stitcher_ok",
     "stitcher_s", "core_s_same_span", "stitcher_frames", "photos": {name: {...}}}

* fps: frames per second of PanoramaMapper.process + background (mapping, tracking and the
  finished tiles' FAST), one thread, on the committed sample bag's 320x240 frames, and on the
  same frames upscaled to 640x480 (the simulator renders 320x240 only; K scaled with them).
* Stitcher: cv2.Stitcher PANORAMA on every ``STITCH_STEP``-th frame of the first
  ``STITCH_SPAN`` frames, against the core on all frames of that span (the core needs the video;
  both produce the panorama of the same span). ratio = stitcher time / core time.
* photos: the real rotating-camera sequences in ../shared/data (when present): the core's
  statuses, the estimated pan steps and loop closure, the Stitcher on the same photos, and the
  panorama PNG written into ``workdir``.
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ar_tracking.core.panorama import PanoramaMapper
from ar_tracking.eval.panorama_metrics import camera_frames

logger = logging.getLogger(__name__)

SAMPLE_BAG = Path(__file__).resolve().parents[2] / 'bags' / 'rotation_sweep_authoring.mcap'
SHARED_DATA = Path(__file__).resolve().parents[3] / 'shared' / 'data'
PHOTO_SETS = {'parrington': 'prtn', 'grail': 'grail'}
STITCH_SPAN = 120
STITCH_STEP = 10


def _time_core(frames: list[tuple[int, np.ndarray, np.ndarray]]) -> tuple[float, PanoramaMapper]:
    mapper = PanoramaMapper()
    start = time.perf_counter()
    for stamp, img, K in frames:
        mapper.process(img, K, stamp)
        mapper.background()
    return time.perf_counter() - start, mapper


def _stitch(images: list[np.ndarray]) -> tuple[float, bool, np.ndarray | None]:
    stitcher = cv2.Stitcher_create(cv2.Stitcher_PANORAMA)
    start = time.perf_counter()
    try:
        status, pano = stitcher.stitch(images)
    except cv2.error:
        status, pano = -1, None
    return time.perf_counter() - start, status == cv2.Stitcher_OK, pano


def photo_panorama(folder: Path, prefix: str, workdir: Path) -> dict[str, Any] | None:
    """Run the core on one photo sequence (rotation about the vertical); PNG into workdir."""
    files = sorted(folder.glob(f'{prefix}*.jpg'))
    if not files:
        return None
    focal = [float(line.split()[-1]) for line in (folder / 'pano.txt').read_text().splitlines() if line.strip()] \
        if (folder / 'pano.txt').exists() else []
    mapper = PanoramaMapper()
    statuses, Rs = [], []
    images = []
    for i, f in enumerate(files):
        bgr = cv2.imread(str(f))
        images.append(bgr)
        h, w = bgr.shape[:2]
        fl = focal[i] if i < len(focal) else focal[0] if focal else w
        K = np.array([[fl, 0, (w - 1) / 2], [0, fl, (h - 1) / 2], [0, 0, 1.0]])
        g = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
        res = mapper.process(g, K, (i + 1) * 1_000_000_000)
        if res.status == 'lost' and i == 1:
            # Photos 20 deg apart (a third of the view) are no video: the first step gets the
            # capture design (20 deg about the vertical, either way) as a prior.
            for sign in (1.0, -1.0):
                a = math.radians(20.0 * sign)
                prior = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])
                res = mapper.process(g, K, (i + 1) * 1_000_000_000 + 1, prior=prior)
                if res.status != 'lost':
                    break
        mapper.background()
        statuses.append(res.status)
        Rs.append(res.R_pano_cam)
    yaw = [math.degrees(math.atan2(R[0, 2], R[2, 2])) if R is not None else None for R in Rs]
    steps = [((b - a + 180) % 360) - 180 for a, b in zip(yaw, yaw[1:]) if a is not None and b is not None]
    png = workdir / f'panorama_{folder.name}.png'
    cv2.imwrite(str(png), mapper.map.tone_mapped(8)[:, :, 0])
    st_s, st_ok, st_pano = _stitch(images)
    if st_ok and st_pano is not None:
        cv2.imwrite(str(workdir / f'stitcher_{folder.name}.png'), st_pano)
    return {
        'photos': len(files),
        'tracked': sum(s != 'lost' for s in statuses),
        'statuses': statuses,
        'yaw_steps_deg': [round(s, 2) for s in steps],
        'yaw_step_mean_deg': round(float(np.mean(steps)), 3) if steps else None,
        'png': str(png),
        'mapped_fraction': round(float(mapper.map.mapped.mean()), 4),
        'stitcher_s': round(st_s, 3),
        'stitcher_ok': st_ok,
    }


def bench_panorama(workdir: Path, bag: Path | None = None) -> dict[str, Any]:
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    frames = list(camera_frames(bag or SAMPLE_BAG))
    out: dict[str, Any] = {'frames': len(frames)}
    if not frames:
        return out
    gray = [(s, cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img, K) for s, img, K in frames]
    t, mapper = _time_core(gray)
    out['fps_320x240'] = round(len(gray) / t, 1)
    out['lost_320x240'] = mapper.lost_frames
    S = np.diag([2.0, 2.0, 1.0])
    big = []
    for s, img, K in gray:
        K2 = S @ K
        K2[0, 2] += 0.5
        K2[1, 2] += 0.5
        big.append((s, cv2.resize(img, (img.shape[1] * 2, img.shape[0] * 2), interpolation=cv2.INTER_LINEAR), K2))
    t2, mapper2 = _time_core(big)
    out['fps_640x480'] = round(len(big) / t2, 1)
    out['lost_640x480'] = mapper2.lost_frames
    span = gray[:STITCH_SPAN]
    core_s, _ = _time_core(span)
    sub = [cv2.cvtColor(frames[i][1], cv2.COLOR_RGB2BGR) for i in range(0, len(span), STITCH_STEP)]
    st_s, st_ok, _ = _stitch(sub)
    out.update({'stitcher_frames': len(sub), 'stitcher_s': round(st_s, 3), 'stitcher_ok': st_ok,
                'core_s_same_span': round(core_s, 4), 'stitcher_time_ratio': round(st_s / core_s, 1)})
    photos = {}
    for name, prefix in PHOTO_SETS.items():
        folder = SHARED_DATA / f'pano_{name}'
        if folder.is_dir():
            r = photo_panorama(folder, prefix, workdir)
            if r is not None:
                photos[name] = r
    if photos:
        out['photos'] = photos
    return out


if __name__ == '__main__':  # pragma: no cover
    import json
    import sys

    print(json.dumps(bench_panorama(Path(sys.argv[1] if len(sys.argv) > 1 else 'out/bench_panorama')), indent=1))
