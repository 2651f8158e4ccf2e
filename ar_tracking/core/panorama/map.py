"""The panoramic map: extended-dynamic-range cylinder, tiles and their keypoint queue.

Langlotz 2011 sec. 3.1: camera frames are mapped onto a cylinder on the fly, and only the
pixels not mapped yet are written ("usually < 1000 pixels per frame"). The map is cut into
tiles; a tile whose pixels are all mapped is *finished*, and its FAST keypoints are then
computed off the frame's critical path. Here that background work is a FIFO queue that the
caller drains with a budget after each frame (:meth:`PanoramaMap.process_queue`), so a
lockstep run stays deterministic.

Sec. 4.1 (extended dynamic range, EDR): the map holds 16 bits per channel; the first frame's
intensities are the baseline and each later frame is corrected by a gain and an offset before
it is mapped (fitted on its overlap with the map, :meth:`PanoramaMap.overlap_pairs`, or the
paper's mean difference of its matched keypoint pairs; exposure.py), so the
map can hold values above 255 and below 0 of the 8-bit scale without clipping. Storage:
``stored = round(64 * (value + 256))``: values from -256 to 767.98 in steps of 1/64. It is
shown through a linear tone-mapping (:meth:`PanoramaMap.tone_mapped`). With ``edr=False`` the
map is a plain 8-bit map and no offset is applied (the comparison of the benchmark).

Besides the pixels the map keeps which frame contributed each pixel, for the seam measure of
sec. 4.1 (:func:`seam_error`: the level step between two contributions, per boundary segment,
measured on flat surroundings and freed of the estimation noise; plus the naive pixel-wise
mean absolute difference across boundaries, ``pixelwise``).
"""
from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from .cylinder import CylinderGeometry, image_rows, project_xyz, to_row_cameras

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]

#: EDR storage: stored = EDR_SCALE * (value + EDR_OFFSET) (value in 8-bit units).
EDR_SCALE = 64.0
EDR_OFFSET = 256.0


def _nonzero_2d(mask: NDArray[np.bool_]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """``np.nonzero`` of a 2-D mask (rows, columns, in row-major order), from the flat indices:
    the same arrays at a fraction of the time (numpy's 2-D nonzero took ~120 us on a frame's
    footprint of ~95,000 map pixels, even with none set; this ~6 us)."""
    rows, cols = np.divmod(np.flatnonzero(mask), mask.shape[1])
    return rows, cols


@dataclass(frozen=True)
class MapConfig:
    """Map layout and the mapping / keypoint parameters."""

    width: int = 2048
    height: int = 512
    tile_size: int = 64
    #: Extended dynamic range (sec. 4.1); False: plain 8-bit map, no exposure correction.
    edr: bool = True
    #: 1: grey map; 3: colour map (RGB, one offset for all channels, as sec. 4.1).
    channels: int = 1
    #: Frame pixels this close to the frame border are not mapped (vignetting, blur at edges).
    frame_border_px: int = 2
    #: FAST threshold (8-bit units) for the keypoints of finished tiles.
    fast_threshold: int = 12
    #: Strongest FAST keypoints kept per finished tile.
    keypoints_per_tile: int = 12
    #: A keypoint needs all map pixels within this radius mapped (its patch is warped from there).
    keypoint_margin_px: int = 7

    def __post_init__(self) -> None:
        if self.width % self.tile_size or self.height % self.tile_size:
            raise ValueError(f'map {self.width}x{self.height} is not a multiple of tile_size {self.tile_size}')
        if self.channels not in (1, 3):
            raise ValueError('channels must be 1 or 3')


def sample_points(img: NDArray, x: NDArray, y: NDArray) -> NDArray:
    """Bilinear samples of ``img`` at float pixel coordinates (N,) -> (N,) or (N, C).
    cv2.remap limits each side of its output to 32767, so the points go in as rows of 1024."""
    n = x.size
    cols = 1024
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(img, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR)
    return out.reshape(rows * cols, -1)[:n] if out.ndim == 3 else out.reshape(-1)[:n]


@dataclass(frozen=True)
class NewPixels:
    """Map pixels (uu, vv) and where they fall in a frame (x, y): the pixels a frame will write
    (:meth:`PanoramaMap.new_pixels`), or the mapped ones it overlaps."""

    uu: NDArray[np.int64]
    vv: NDArray[np.int64]
    x: NDArray[np.float32]
    y: NDArray[np.float32]


class PanoramaMap:
    """State of the map (see the module docstring). Not thread-safe; one caller."""

    #: How far outside the frame its outline in the map is drawn, frame pixels.
    OUTLINE_MARGIN_PX = 3.0

    def __init__(self, config: MapConfig | None = None) -> None:
        self.config = cfg = config or MapConfig()
        self.geometry = CylinderGeometry(cfg.width, cfg.height)
        H, W, C = cfg.height, cfg.width, cfg.channels
        self.stored = np.zeros((H, W, C), np.uint16 if cfg.edr else np.uint8)
        #: Grey map in 8-bit units relative to the baseline (what the tracker matches against).
        self.gray = np.zeros((H, W), np.float32)
        self.mapped = np.zeros((H, W), bool)
        #: Index of the frame that contributed each pixel (-1: unmapped).
        self.contribution = np.full((H, W), -1, np.int32)
        ts = cfg.tile_size
        self.tiles_shape = (H // ts, W // ts)
        self.tile_count = np.zeros(self.tiles_shape[0] * self.tiles_shape[1], np.int64)
        #: 0 unfinished, 1 finished (queued for keypoints), 2 finished with keypoints.
        self.tile_state = np.zeros(self.tiles_shape[0] * self.tiles_shape[1], np.uint8)
        self.queue: deque[int] = deque()
        self._kp_dirs: list[Array] = []
        self._kp_uv: list[Array] = []
        self._kp_score: list[Array] = []
        self._kp_cache: tuple[Array, Array, Array] | None = None
        self.version = 0  # bumped whenever pixels are written
        #: How many times the panorama's map was painted again from scratch (:mod:`.repaint`):
        #: its finished tiles are then new, and :meth:`tiles_image` says so.
        self.generation = 0
        #: (omega rad/s camera axes, readout s) of the frame being mapped when its camera has a
        #: rolling shutter (set by the mapper per frame), else None: see cylinder.row_rotations.
        self.row_motion: tuple[Array, float] | None = None
        self.frames_mapped = 0
        self._col_sin, self._col_cos = self.geometry.column_terms(np.arange(W, dtype=float))
        self._row_h = self.geometry.row_terms(np.arange(H, dtype=float))
        self._fast = cv2.FastFeatureDetector.create(cfg.fast_threshold, True)  # = FastFeatureDetector_create
        self._footprint: tuple[tuple[bytes, bytes, tuple[int, ...]],
                               tuple[tuple[int, int, int, int], NDArray[np.int32] | None]] | None = None
        self._mask: tuple[object, NDArray[np.bool_]] | None = None
        #: (K bytes, size) -> the outline's rays in camera_optical (the same for every frame of
        #: one camera: only their rotation into the panorama changes)
        self._outline_rays: tuple[tuple[bytes, tuple[int, ...]], Array] | None = None

    # -- queries -----------------------------------------------------------------------------

    @property
    def empty(self) -> bool:
        return self.frames_mapped == 0

    def keypoints(self) -> tuple[Array, Array, Array]:
        """(directions (N, 3), map uv (N, 2), FAST score (N,)) of the finished tiles' keypoints."""
        if self._kp_cache is None:
            if self._kp_dirs:
                self._kp_cache = (np.concatenate(self._kp_dirs), np.concatenate(self._kp_uv),
                                  np.concatenate(self._kp_score))
            else:
                self._kp_cache = (np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0))
        return self._kp_cache

    def tiles_image(self) -> NDArray[np.uint8]:
        """One pixel per tile (the ``panorama/tiles`` product): 0 unfinished, nonzero finished -
        255 in the map as first painted, one less for each time it was painted again
        (:attr:`generation`; never below 1), so that a consumer of the finished tiles sees that
        they changed."""
        value = max(255 - self.generation, 1)
        return np.where(self.tile_state > 0, value, 0).astype(np.uint8).reshape(self.tiles_shape)

    def finished_tiles(self) -> NDArray[np.int64]:
        return np.flatnonzero(self.tile_state > 0)

    def values(self) -> NDArray[np.float32]:
        """The map in 8-bit units relative to the baseline, (H, W, C) float32 (NaN unmapped)."""
        if self.config.edr:
            out = self.stored.astype(np.float32) / EDR_SCALE - EDR_OFFSET
        else:
            out = self.stored.astype(np.float32)
        out[~self.mapped] = np.nan
        return out

    def tone_mapped(self, bits: int = 16) -> NDArray[np.integer]:
        """The map through a linear tone-mapping (sec. 4.1): the range of mapped values is
        stretched onto [0, 2^bits - 1]; unmapped pixels are 0. Channels as stored (RGB)."""
        top = (1 << bits) - 1
        dtype = np.uint16 if bits > 8 else np.uint8
        mapped = self.mapped
        if not mapped.any():
            return np.zeros(self.stored.shape, dtype)
        # Whole-array passes with the mask as a factor (boolean indexing of the 2048x512x3 map
        # cost ~22 ms per call): unmapped pixels are multiplied to 0 before the rounding, so
        # they come out 0. The grey map's range from OpenCV's masked minMaxLoc (one pass).
        if not self.config.edr:  # plain 8-bit map: shown as it is
            vals = self.stored.astype(np.float32) * np.float32(top / 255.0)
        else:
            if self.stored.shape[2] == 1:
                lo, hi, _, _ = cv2.minMaxLoc(self.stored[..., 0], mapped.view(np.uint8))
            else:
                mask = mapped[..., None]
                lo = float(np.min(self.stored, where=mask, initial=np.iinfo(self.stored.dtype).max))
                hi = float(np.max(self.stored, where=mask, initial=0))
            vals = self.stored.astype(np.float32)
            vals -= np.float32(lo)
            vals *= np.float32(top / max(hi - lo, 1.0))
        np.clip(vals, 0, top, out=vals)
        vals *= mapped[..., None]
        vals += np.float32(0.5)
        return vals.astype(dtype)

    # -- mapping -----------------------------------------------------------------------------

    def footprint(self, K: Array, R_pano_cam: Array, size: tuple[int, int]) -> tuple[int, int, int, int]:
        """Bounding box (u0, u1, v0, v1) of the frame in the map, u unwrapped around the optical
        axis (u1 - u0 <= W; u may be negative or >= W), v clipped to the map."""
        return self._footprint_of(K, R_pano_cam, size)[0]

    def footprint_mask(self, K: Array, R_pano_cam: Array, size: tuple[int, int]
                       ) -> tuple[tuple[int, int, int, int], NDArray[np.bool_]]:
        """The bounding box and a (v1 - v0, u1 - u0) mask of the pixels in it that the frame may
        see: the frame's outline (32 points, a few pixels outside the frame) projected into the
        map and filled. A frame seen at a slant covers a small part of its
        box; mapping tests only the pixels in the mask. All True when the outline spans the
        whole turn (a pole in view)."""
        outline = self._footprint_of(K, R_pano_cam, size)
        box, ring = outline
        if self._mask is not None and self._mask[0] is outline:  # the same frame as last time
            return box, self._mask[1]
        u0, u1, v0, v1 = box
        if ring is None or v1 <= v0:
            mask = np.ones((max(v1 - v0, 0), u1 - u0), bool)
        else:
            filled = np.zeros((v1 - v0, u1 - u0), np.uint8)
            cv2.fillPoly(filled, [ring], 1)
            mask = filled.view(bool)
        mask.flags.writeable = False
        self._mask = (outline, mask)
        return box, mask

    def _footprint_of(self, K: Array, R_pano_cam: Array, size: tuple[int, int]
                      ) -> tuple[tuple[int, int, int, int], NDArray[np.int32] | None]:
        """Box and outline (int32 (N, 1, 2) u - u0, v - v0; None across a pole) of the frame.
        The last one is kept: a frame's correction and its mapping ask for the same."""
        key = (K.tobytes(), np.asarray(R_pano_cam, float).tobytes(), tuple(size))
        if self._footprint is not None and self._footprint[0] == key:
            return self._footprint[1]
        # the outline's directions and, last, the optical axis's: one projection
        d = np.concatenate([self._outline(K, size) @ R_pano_cam.T, R_pano_cam[None, :, 2]])
        u, v = self.geometry.project(d)
        u, v, uc = u[:-1], v[:-1], u[-1]
        W = self.config.width
        du = np.mod(u - uc + W / 2, W) - W / 2
        u0 = int(np.floor(uc + du.min())) - 1
        u1 = int(np.ceil(uc + du.max())) + 2
        ring: NDArray[np.int32] | None = None
        if u1 - u0 > W:
            u0, u1 = int(uc) - W // 2, int(uc) - W // 2 + W
        else:
            ring = np.rint(np.stack([uc + du - u0, v], -1)).astype(np.int32).reshape(-1, 1, 2)
        v0 = max(0, int(np.floor(v.min())) - 1)
        v1 = min(self.config.height, int(np.ceil(v.max())) + 2)
        if ring is not None:
            ring[:, 0, 1] -= v0
        out = ((u0, u1, v0, v1), ring)
        self._footprint = (key, out)
        return out

    def _outline(self, K: Array, size: tuple[int, int]) -> Array:
        """Rays (32, 3) in camera_optical through the frame's outline, kept for the camera."""
        key = (K.tobytes(), tuple(size))
        if self._outline_rays is not None and self._outline_rays[0] == key:
            return self._outline_rays[1]
        h, w = size
        # The outline runs MARGIN pixels outside the frame: its chords cut the curved edges
        # by well under a pixel, so no pixel of the frame falls outside the mask.
        m = self.OUTLINE_MARGIN_PX
        xs = np.linspace(-m, w - 1 + m, 9)
        ys = np.linspace(-m, h - 1 + m, 7)[1:-1]
        # The border as a ring: top left to right, right side down, bottom back, left side up.
        bx = np.concatenate([xs, np.full_like(ys, w - 1 + m), xs[::-1], np.full_like(ys, -m)])
        by = np.concatenate([np.full_like(xs, -m), ys, np.full_like(xs, h - 1 + m), ys[::-1]])
        Kinv = np.linalg.inv(K)
        rays: Array = np.stack([bx, by, np.ones_like(bx)], -1) @ Kinv.T
        rays.flags.writeable = False
        self._outline_rays = (key, rays)
        return rays

    def _columns(self, a: NDArray, u0: int, u1: int, v0: int, v1: int) -> NDArray:
        """Rows v0:v1, columns u0:u1 of a map-sized array, columns wrapped (0 < u1 - u0 <= W):
        a view, or two slices joined when the range crosses u = 0 (no fancy indexing)."""
        W = self.config.width
        start, n = u0 % W, u1 - u0
        rows = a[v0:v1]
        if start + n <= W:
            return rows[:, start:start + n]
        return np.concatenate([rows[:, start:], rows[:, :start + n - W]], axis=1)

    def _in_frame(self, K: Array, R_pano_cam: Array, size: tuple[int, int], uu: NDArray[np.int64],
                  vv: NDArray[np.int64]) -> NewPixels | None:
        """The map pixels (uu, vv) that a frame of ``size`` (h, w) at R_pano_cam sees outside its
        ``frame_border_px``, with their frame coordinates; None when it sees none of them."""
        h, w = size
        # Separable direction (sin t, h, cos t): camera coordinates are R^T d.
        Rt = R_pano_cam.T
        s, c, hh = self._col_sin[uu], self._col_cos[uu], self._row_h[vv]
        # The three coordinates as separate contiguous arrays (the (N, 3) array's strided
        # columns cost a third more in project_to_image).
        px, py, pz = (Rt[k, 0] * s + Rt[k, 1] * hh + Rt[k, 2] * c for k in range(3))
        if self.row_motion is None:
            x, y, front = project_xyz(K, px, py, pz)
        else:  # a rolling shutter: where the row that saw it put it
            x, y, front = project_xyz(K, *to_row_cameras(self.row_motion, image_rows(K, py, pz), h, px, py, pz))
        b = self.config.frame_border_px
        ok = front & (x >= b) & (x <= w - 1 - b) & (y >= b) & (y <= h - 1 - b)
        if not ok.any():
            return None
        return NewPixels(uu[ok], vv[ok], x[ok].astype(np.float32), y[ok].astype(np.float32))

    def overlap_pairs(self, gray: NDArray[np.uint8], K: Array, R_pano_cam: Array, step: int = 6
                      ) -> tuple[NDArray[np.float32], NDArray[np.float32]] | None:
        """(map values, frame values) at the already-mapped pixels the frame sees, on a grid of
        ``step`` map pixels: what the frame's photometric correction is fitted on
        (:func:`.exposure.fit_overlap_exposure`). None when the frame sees no mapped pixel;
        border pixels as in :meth:`map_frame`."""
        (u0, u1, v0, v1), seen = self.footprint_mask(K, R_pano_cam, gray.shape[:2])
        if v1 <= v0:
            return None
        ri, ci = _nonzero_2d(self._columns(self.mapped, u0, u1, v0, v1)[::step, ::step] & seen[::step, ::step])
        if ri.size == 0:
            return None
        old = self._in_frame(K, R_pano_cam, gray.shape[:2], (u0 + ci * step) % self.config.width, v0 + ri * step)
        if old is None:
            return None
        return (np.take(self.gray.reshape(-1), old.vv * self.config.width + old.uu),
                sample_points(gray, old.x, old.y).astype(np.float32))

    def new_pixels(self, K: Array, R_pano_cam: Array, size: tuple[int, int]) -> NewPixels | None:
        """The not-yet-mapped map pixels a frame of ``size`` (h, w) at R_pano_cam sees (frame
        border excluded), None when there are none: what :meth:`map_frame` writes."""
        (u0, u1, v0, v1), seen = self.footprint_mask(K, R_pano_cam, size)
        if v1 <= v0:
            return None
        # seen and not mapped: one comparison of the booleans instead of a negation and an 'and'
        vv, ii = _nonzero_2d(seen > self._columns(self.mapped, u0, u1, v0, v1))
        if vv.size == 0:
            return None
        return self._in_frame(K, R_pano_cam, size, (ii + u0) % self.config.width, vv + v0)

    def map_frame(self, frame: NDArray[np.uint8], K: Array, R_pano_cam: Array, frame_index: int,
                  offset: float = 0.0, frame_gray: NDArray[np.uint8] | None = None,
                  gain: float = 1.0, pixels: NewPixels | None = None) -> int:
        """Write the not-yet-mapped map pixels that the frame sees; returns how many.

        ``frame`` is grey (H, W) or RGB (H, W, 3) uint8 (channels as configured); the EDR
        correction maps a frame value I to ``gain * I + offset`` (8-bit units; both ignored
        when EDR is off); ``frame_gray`` the grey version of an RGB frame (computed when not
        given); ``pixels`` the frame's :meth:`new_pixels` when the caller has them already.
        """
        cfg = self.config
        if frame.ndim == 2:
            gray_src = frame
        elif frame_gray is None:
            gray_src = np.asarray(cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), dtype=np.uint8)  # uint8: no copy
        else:
            gray_src = frame_gray
        if pixels is None:
            pixels = self.new_pixels(K, R_pano_cam, frame.shape[:2])
        if pixels is None:
            return 0
        uu, vv, x, y = pixels.uu, pixels.vv, pixels.x, pixels.y
        g = sample_points(gray_src, x, y).astype(np.float32)
        if cfg.channels == 3:
            src = frame if frame.ndim == 3 else cv2.cvtColor(frame, cv2.COLOR_GRAY2RGB)
            col = sample_points(src, x, y).astype(np.float32)
        else:
            col = g.reshape(-1, 1)
        # the pixels' flat indices: one gather-scatter per array instead of two index arrays each
        flat = vv * cfg.width + uu
        if cfg.edr:
            off, gn = np.float32(offset), np.float32(gain)
            gray_val = g * gn + off
            stored = np.clip(np.rint((col * gn + off + np.float32(EDR_OFFSET)) * np.float32(EDR_SCALE)), 0, 65535)
            self.stored.reshape(-1, cfg.channels)[flat] = stored.astype(np.uint16)
        else:
            gray_val = g
            self.stored.reshape(-1, cfg.channels)[flat] = col.astype(np.uint8)
        self.gray.reshape(-1)[flat] = gray_val
        self.mapped.reshape(-1)[flat] = True
        self.contribution.reshape(-1)[flat] = frame_index
        self._count_tiles(uu, vv)
        self.version += 1
        self.frames_mapped += 1
        return int(uu.size)

    def _count_tiles(self, uu: NDArray[np.int64], vv: NDArray[np.int64]) -> None:
        ts = self.config.tile_size
        tw = self.tiles_shape[1]
        idx = (vv // ts) * tw + (uu // ts)
        self.tile_count += np.bincount(idx, minlength=self.tile_count.size)
        done = np.flatnonzero((self.tile_count == ts * ts) & (self.tile_state == 0))
        for t in done.tolist():
            self.tile_state[t] = 1
            self.queue.append(t)

    # -- background keypoints ---------------------------------------------------------------

    def process_queue(self, budget_tiles: int, min_keypoints: int = 0) -> int:
        """FAST keypoints of up to ``budget_tiles`` finished tiles from the queue (more while
        the map has fewer than ``min_keypoints``: at start-up tracking needs some at once).
        Deterministic: the order is the order in which tiles were finished. Returns tiles done."""
        done = 0
        while self.queue and (done < budget_tiles or self.keypoints()[0].shape[0] < min_keypoints):
            self._tile_keypoints(self.queue.popleft())
            done += 1
        return done

    def _tile_keypoints(self, t: int) -> None:
        cfg = self.config
        ts, m = cfg.tile_size, cfg.keypoint_margin_px
        tw = self.tiles_shape[1]
        r0, c0 = (t // tw) * ts, (t % tw) * ts
        pad = 3  # FAST's circle radius: keypoints right at the tile edge need the neighbours
        rows = np.clip(np.arange(r0 - pad, r0 + ts + pad), 0, cfg.height - 1)
        cols = np.arange(c0 - pad, c0 + ts + pad) % cfg.width
        img = np.clip(self.gray[rows][:, cols] + 0.5, 0, 255).astype(np.uint8)
        kps = self._fast.detect(img, None)
        self.tile_state[t] = 2
        if not kps:
            return
        pts = np.array([k.pt for k in kps]) - pad
        resp = np.array([k.response for k in kps])
        inside = (pts[:, 0] >= 0) & (pts[:, 0] < ts) & (pts[:, 1] >= 0) & (pts[:, 1] < ts)
        pts, resp = pts[inside], resp[inside]
        order = np.argsort(-resp, kind='stable')
        keep_uv, keep_s = [], []
        for i in order:
            u, v = c0 + pts[i, 0], r0 + pts[i, 1]
            if v - m < 0 or v + m >= cfg.height:
                continue
            cu = np.arange(int(u) - m, int(u) + m + 1) % cfg.width
            if not self.mapped[int(v) - m:int(v) + m + 1][:, cu].all():
                continue
            keep_uv.append((u, v))
            keep_s.append(resp[i])
            if len(keep_uv) >= cfg.keypoints_per_tile:
                break
        if not keep_uv:
            return
        uv = np.array(keep_uv, float)
        self._kp_uv.append(uv)
        self._kp_dirs.append(self.geometry.unproject(uv[:, 0], uv[:, 1]))
        self._kp_score.append(np.array(keep_s, float))
        self._kp_cache = None


#: Default of :func:`seam_error`'s ``flat_max``: about twice the noise of the difference of
#: two neighbouring map pixels (sensor noise ~2 DN, slightly smoothed by the bilinear mapping).
SEAM_FLAT_MAX = 4.0


def _seam_windows(v: NDArray[np.float64], c: NDArray[np.integer], axis: int
                  ) -> tuple[list[NDArray], list[NDArray], list[NDArray]]:
    """Four pixels a', a, b, b' in a row along ``axis`` (1: across the map, which wraps; 0: down)
    for every start pixel, their contributions, and the gradients along the boundary at a, b."""
    if axis == 1:
        sh = [np.roll(v, -k, axis=1) for k in range(4)]
        sc = [np.roll(c, -k, axis=1) for k in range(4)]
        along = [0.5 * np.abs(np.roll(x, -1, axis=0) - np.roll(x, 1, axis=0)) for x in sh[1:3]]
        for g in along:  # the map does not wrap vertically
            g[0] = np.nan
            g[-1] = np.nan
    else:
        n = v.shape[0] - 3
        sh = [v[k:k + n] for k in range(4)]
        sc = [c[k:k + n] for k in range(4)]
        along = [0.5 * np.abs(np.roll(x, -1, axis=1) - np.roll(x, 1, axis=1)) for x in sh[1:3]]
    return sh, sc, along


def seam_error(values: NDArray[np.floating], contribution: NDArray[np.integer], min_pairs: int = 8,
               min_gap: int = 1, flat_max: float = SEAM_FLAT_MAX, block_px: int = 16) -> dict[str, float]:
    """Intensity steps between frame contributions of a map (sec. 4.1, Fig. 3).

    ``values`` (H, W) grey map in 8-bit units (NaN or contribution -1: unmapped). A seam is a
    *level* difference between two contributions A | B that persists along their common
    boundary; texture, blur and sub-pixel misregistration also make pixels differ across a
    boundary, but with a sign that changes along it. So the step is measured per boundary
    *segment* (the adjacent pixel pairs owned by one pair of contributions, both axes; the map
    wraps in u):

    * at each pair, with a', a from A and b, b' from B in a row across the boundary, the jump
      that the local gradient does not explain: (b - a) - ((a - a') + (b' - b)) / 2, signed
      from the earlier frame to the later one (contribution ids are frame indices);
    * only pairs in flat surroundings count (|a - a'|, |b' - b| and the gradients along the
      boundary at a and b all <= ``flat_max``): a step is what the eye sees as a seam on a
      smooth surface, while on edges the differences are structure (blur, misregistration),
      which no exposure correction can or should change;
    * segment step = mean of its pairs; its noise variance = kappa * var / n, with kappa >= 1
      the inflation of the variance of a mean by the correlation of neighbouring pairs, from
      the batch means of ``block_px`` blocks (the mean over segments of batch-means variance /
      naive variance).

    Limits: an edge of the scene lying exactly on a boundary (between a and b) along the
    segment looks like a step and counts as one; pairs are not trimmed, because a true exposure
    step varies along a boundary with the brightness (a gain) and trimming would cut it.

    Returned (8-bit units; weights = segment lengths in pairs, segments of >= ``min_pairs``):

    * ``step``: the root of the length-weighted mean of (step^2 - noise variance) - the RMS step
      over the boundary length, unbiased in the square (a mean of |step| cannot be made
      unbiased: noise alone gives |mean| > 0), and it weights the large, visible steps most.
      This is the seam error;
    * ``mean_step``: length-weighted mean of sqrt(max(step^2 - noise variance, 0)) (mean absolute
      step; the per-segment clipping leaves a small positive floor from noise);
    * ``pixelwise``: the plain mean |I_b - I_a| over all adjacent pixel pairs of different
      contributions (no gradient compensation, texture included; the naive seam figure);
    * ``pairs``, ``boundaries``: flat pairs and segments used; ``kappa``.

    ``min_gap`` > 1 keeps only boundaries between frames at least that many frames apart
    (exposure seams between revisited parts: the closing of the 360-degree turn, pitch passes).
    """
    v = np.asarray(values, np.float64)
    c = np.asarray(contribution)
    d_all, lo_all, hi_all, pos_all, pix = [], [], [], [], []
    H, W = v.shape
    rows, cols = np.mgrid[0:H, 0:W]
    for axis in (0, 1):
        sh, sc, along = _seam_windows(v, c, axis)
        a2, a, b, b2 = sh
        ca2, ca, cb, cb2 = sc
        edge = (ca >= 0) & (cb >= 0) & (np.abs(ca - cb) >= min_gap) & np.isfinite(a) & np.isfinite(b)
        pix.append(np.abs(b - a)[edge])
        with np.errstate(invalid='ignore'):
            flat = (np.abs(a - a2) <= flat_max) & (np.abs(b2 - b) <= flat_max) \
                & (along[0] <= flat_max) & (along[1] <= flat_max)
        sel = edge & (ca2 == ca) & (cb2 == cb) & flat
        jump = ((b - a) - 0.5 * ((a - a2) + (b2 - b)))[sel]
        ca_s, cb_s = ca[sel], cb[sel]
        d_all.append(np.where(cb_s > ca_s, jump, -jump))
        lo_all.append(np.minimum(ca_s, cb_s).astype(np.int64))
        hi_all.append(np.maximum(ca_s, cb_s).astype(np.int64))
        r, q = (rows[:H - 3], cols[:H - 3]) if axis == 0 else (rows, cols)
        pos_all.append((r[sel] // block_px) * (W // block_px + 1) + q[sel] // block_px)
    pixels = np.concatenate(pix)
    out: dict[str, float] = {'step': float('nan'), 'mean_step': float('nan'),
                             'pixelwise': float(pixels.mean()) if pixels.size else float('nan'),
                             'pairs': 0, 'boundaries': 0, 'kappa': float('nan')}
    d = np.concatenate(d_all)
    if d.size == 0:
        return out
    lo, hi, pos = np.concatenate(lo_all), np.concatenate(hi_all), np.concatenate(pos_all)
    _, seg, n = np.unique(lo * (int(hi.max()) + 1) + hi, return_inverse=True, return_counts=True)
    seg = seg.reshape(-1)
    mean = np.bincount(seg, weights=d) / n
    var = np.maximum(np.bincount(seg, weights=d * d) / n - mean ** 2, 0.0) * n / np.maximum(n - 1, 1)
    use = n >= min_pairs
    if not use.any():
        return out
    # Correlation along the boundary: batch means over blocks of each segment.
    _, blk, bn = np.unique(seg.astype(np.int64) * (int(pos.max()) + 1) + pos, return_inverse=True,
                           return_counts=True)
    blk = blk.reshape(-1)
    bseg = np.zeros(bn.size, np.int64)
    bseg[blk] = seg
    bmean = np.bincount(blk, weights=d) / bn
    nb = np.bincount(bseg, minlength=n.size)
    bvar = np.bincount(bseg, weights=bn ** 2 * (bmean - mean[bseg]) ** 2, minlength=n.size) / n ** 2 \
        * nb / np.maximum(nb - 1, 1)
    ok = use & (nb >= 3) & (var > 0)
    # The mean of the segments' ratios: every segment counts once, whatever its texture.
    kappa = max(float(np.mean(bvar[ok] / (var[ok] / n[ok]))), 1.0) if ok.any() else 1.0
    noise = kappa * var / n
    w = n[use].astype(np.float64)
    ms = float(np.sum(w * (mean[use] ** 2 - noise[use])) / w.sum())
    out.update(step=math.sqrt(max(ms, 0.0)),
               mean_step=float(np.sum(w * np.sqrt(np.maximum(mean[use] ** 2 - noise[use], 0.0))) / w.sum()),
               pairs=int(n[use].sum()), boundaries=int(np.count_nonzero(use)), kappa=kappa)
    return out
