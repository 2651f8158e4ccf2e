"""Panoramic mapping and tracking, one frame at a time (Langlotz 2011 sec. 3.1 and 4.1).

:class:`PanoramaMapper` ties the pieces together. Per frame (:meth:`PanoramaMapper.process`):

1. the first frame defines the ``panorama`` frame (R = I) and is mapped as the EDR baseline;
2. later frames: constant-motion prediction (the last inter-frame rotation, scaled by the
   stamp ratio), active-search tracking against the map keypoints; if that fails, a wider
   search, then re-localisation against the finished tiles;
3. a tracked frame is mapped (only its not-yet-mapped pixels), corrected for exposure (EDR,
   ``edr_correction``): by default with a gain and offset fitted on its whole overlap with the
   map (exposure.fit_overlap_exposure), or by the paper's intensity offset of its matched
   keypoints, filtered over frames (``offset_exposure``; unfiltered with
   ``offset_exposure.smooth=False``, the paper's literal version), or by the filtered log-domain
   gain of the same pairs (exposure.py); a frame that is not tracked is neither mapped nor
   reported (lost).

The keypoints of newly finished tiles are computed by :meth:`PanoramaMapper.background`, which
the caller runs after it has used the frame's result (off the critical path, deterministic).
No ROS here; the node is a thin wrapper.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .exposure import (OFFSET_EXPOSURE, ExposureConfig, ExposureFilter, OverlapExposureConfig,
                       fit_overlap_exposure)
from .map import MapConfig, NewPixels, PanoramaMap, seam_error
from .cylinder import project_to_image
from .readout import Painting, ReadoutConfig, ReadoutEstimator, RowFit
from .relocalise import Relocaliser, RelocaliserConfig
from .repaint import EarlyFrame, EarlyFrames, repaint, stamp_orientation
from .tracker import ActiveSearchTracker, TrackerConfig, TrackResult
from ...errors import ArTrackingError

logger = logging.getLogger(__name__)

Array = NDArray[np.float64]


class PanoramaError(ArTrackingError, ValueError):
    """A frame or calibration the mapper cannot use (one line)."""


#: The EDR correction models of :class:`MapperConfig` (``edr_correction``).
EDR_CORRECTIONS = ('overlap', 'offset', 'gain')


@dataclass(frozen=True)
class MapperConfig:
    map: MapConfig = field(default_factory=MapConfig)
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    relocaliser: RelocaliserConfig = field(default_factory=RelocaliserConfig)
    #: Search radius of the second attempt when the prediction fails, pixels.
    wide_radius_px: int = 10
    #: Rolling-shutter readout of the camera, s (row y read ``readout_s (y + 0.5) / height``
    #: after the stamp); 0 is a global shutter. With it the tracker and the map turn each row
    #: by the camera's rate (the constant-motion velocity) and the estimate is the stamp's.
    readout_s: float = 0.0
    #: Estimate the readout from the tracked frames (:mod:`.readout`) and use the estimate in
    #: place of ``readout_s`` once it is known (a bag seldom says what its camera's readout is).
    estimate_readout: bool = True
    readout_estimate: ReadoutConfig = field(default_factory=ReadoutConfig)
    #: With ``readout_s`` 0 and the estimate on, the frames mapped before the estimate is
    #: applied are kept, up to this many MB, and the map is painted again from them with the
    #: estimated readout when it is (:mod:`.repaint`); 0 never repaints.
    repaint_max_mb: float = 96.0
    #: Finished tiles whose keypoints are computed per background step.
    background_tiles: int = 4
    #: While the map has fewer keypoints, the background step does all queued tiles.
    min_keypoints: int = 150
    #: Largest rotation between consecutive tracked frames accepted, degrees.
    max_step_deg: float = 30.0
    #: Lost this long (stamps) with nothing in the map to relocalise against, a new panorama is
    #: started from the current frame, s; 0 (the default) waits for the map. A user who turns on
    #: into azimuths the map never saw (the tracker lost among near objects) otherwise stays
    #: lost until they turn back; the readout estimate is kept (it is the camera's). Off by
    #: default: on 14 simulated seeds a restart 3 s into a loss helped one (lost 11.6 s) and
    #: cost three (docs/panorama.md): the new panorama's placement from the gyro is worse
    #: than waiting for a tracker that comes back within seconds.
    restart_lost_s: float = 0.0
    #: Frames with a grey-level standard deviation below this are textureless (lost).
    min_texture_std: float = 3.0
    #: A lost frame whose place the relocaliser found but whose verification failed only its
    #: consistency ratios (parallax: 30-40 inliers of ~55 matched) leaves that place for the next
    #: one: the tracker tries it first, and when the view is again found but inconsistent the
    #: frame is lost without a new relocalisation (:meth:`PanoramaMapper._held_view`), at most
    #: this many frames in a row (then one relocalises in full); 0: every lost frame relocalises.
    hold_parallax_frames: int = 30
    #: EDR correction model (sec. 4.1): 'overlap' - gain and offset fitted on every mapped
    #: pixel the frame overlaps (exposure.fit_overlap_exposure; an extension: on the 60 s
    #: rotation_sweep bags it leaves about half the seams of the keypoint versions,
    #: docs/panorama.md); 'offset' - the mean difference of intensities of
    #: the matched keypoint pairs added to every pixel (the paper's reading), filtered over
    #: frames (``offset_exposure``); 'gain' - the mean difference of log intensities of the
    #: pairs, filtered (``exposure``). 'overlap' falls back to 'offset' for a frame whose overlap
    #: is too small or too saturated to fit.
    edr_correction: str = 'overlap'
    #: Filter of the log gain ('gain' mode).
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    #: Filter of the offset ('offset' mode, 8-bit units). ``smooth=False``: each frame's own
    #: offset, as sec. 4.1 literally says; the default smooths the per-frame noise, which
    #: otherwise becomes a small step at nearly every contribution boundary (exposure.py).
    offset_exposure: ExposureConfig = field(default_factory=lambda: OFFSET_EXPOSURE)
    #: The overlap fit ('overlap' mode).
    overlap_exposure: OverlapExposureConfig = field(default_factory=OverlapExposureConfig)

    def __post_init__(self) -> None:
        if self.edr_correction not in EDR_CORRECTIONS:
            raise ValueError(f"edr_correction must be one of {', '.join(EDR_CORRECTIONS)}")


@dataclass
class FrameResult:
    """Outcome of one frame: R_pano_cam or None when lost."""

    R_pano_cam: Array | None
    status: str  # 'initialised', 'tracked', 'relocalised', 'lost'
    track: TrackResult | None = None
    mapped_pixels: int = 0
    #: EDR additive correction of the frame, 8-bit units (its pixels were mapped as
    #: ``intensity_gain * I + intensity_offset``; 0 without EDR).
    intensity_offset: float = 0.0
    reason: str = ''
    #: EDR multiplicative correction of the frame (1 without EDR, in 'offset' mode, and for a
    #: frame the overlap fit left to the keypoint offset).
    intensity_gain: float = 1.0


class PaintedFrames(dict[int, tuple[Array, Array | None, float]]):
    """The frames that painted the map: index -> (R_pano_cam, rate rad/s camera axes or None
    while unknown, readout its rows were turned by); a dict, whose items (set one at a time) are
    also kept as arrays by row ``index + 1`` (row 0: no such frame - identity, no rate, 0 s), so
    that the rays of a fit look their painting frames up in one gather per array
    (:meth:`PanoramaMapper._painting`; a unique / stack of the frames per tracked frame cost
    more than the arithmetic)."""

    def __init__(self) -> None:
        super().__init__()
        self.R = np.tile(np.eye(3), (64, 1, 1))
        self.rate = np.zeros((64, 3))
        self.known = np.zeros(64, bool)
        self.readout = np.zeros(64)

    def __setitem__(self, index: int, value: tuple[Array, Array | None, float]) -> None:
        super().__setitem__(index, value)
        row = index + 1
        if row >= self.known.size:
            grow = max(row + 1, 2 * self.known.size) - self.known.size
            self.R = np.concatenate([self.R, np.tile(np.eye(3), (grow, 1, 1))])
            self.rate = np.concatenate([self.rate, np.zeros((grow, 3))])
            self.known = np.concatenate([self.known, np.zeros(grow, bool)])
            self.readout = np.concatenate([self.readout, np.zeros(grow)])
        R, rate, readout = value
        self.R[row] = R
        self.rate[row] = 0.0 if rate is None else rate
        self.known[row] = rate is not None
        self.readout[row] = readout

    def _not_mirrored(self, *args: object, **kwargs: object) -> None:
        raise TypeError('PaintedFrames: items are set one at a time (the arrays mirror __setitem__ only)')

    __delitem__ = pop = popitem = clear = update = setdefault = _not_mirrored  # type: ignore[assignment]

    def rows(self, index: NDArray[np.integer]) -> NDArray[np.intp]:
        """The array rows of frame indices (0 for one that painted nothing)."""
        index = np.asarray(index, np.intp)
        return np.where((index >= 0) & (index < self.known.size - 1), index + 1, 0)


def _grey_std(gray: NDArray[np.uint8]) -> float:
    """Standard deviation of the grey levels (cv2: a tenth of numpy's time at 320 x 240)."""
    return float(cv2.meanStdDev(gray)[1][0, 0])


def _log_rotation(R: Array) -> Array:
    rvec, _ = cv2.Rodrigues(R)
    return np.asarray(rvec, dtype=np.float64).reshape(3)  # float64 in, float64 out: no copy


def _exp_rotation(w: Array) -> Array:
    R, _ = cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))
    return np.asarray(R, dtype=np.float64)  # float64 in, float64 out: no copy


class PanoramaMapper:
    """See the module docstring."""

    def __init__(self, config: MapperConfig | None = None) -> None:
        self.config = config or MapperConfig()
        self.reset()

    def reset(self) -> None:
        cfg = self.config
        self.map = PanoramaMap(cfg.map)
        # The tracker's log gain is read by the 'gain' EDR correction only.
        wants_log_gain = cfg.map.edr and cfg.edr_correction == 'gain'
        self.tracker = ActiveSearchTracker(cfg.tracker if wants_log_gain else replace(cfg.tracker, log_gain=False))
        self.relocaliser = Relocaliser(cfg.relocaliser)
        self.exposure = ExposureFilter(cfg.exposure)
        self.offset_filter = ExposureFilter(cfg.offset_exposure)
        #: The last frame's overlap fit (gain, offset): where the next fit starts trimming.
        self._overlap_fit: tuple[float, float] | None = None
        self.frame_index = 0
        self.lost_frames = 0
        #: Stamp of the first frame of the current loss (None while tracking).
        self._lost_since_ns: int | None = None
        #: New panoramas started after a loss (restart_lost_s), since the reset.
        self.restarts = 0
        self.frame_size: tuple[int, int] | None = None
        self._last_R: Array | None = None
        self._last_stamp: int | None = None
        # The last tracked frame at its rows' mean read time (R, stamp ns, s after the stamp;
        # the stamp itself with a global shutter): what the rate is differenced from
        # (see _row_centre).
        self._last_centre: tuple[Array, int, float] | None = None
        self._last_row_centre = 0.5  # its inliers' mean row position, (row + 0.5) / height
        self._velocity: Array | None = None  # rotation vector per second, camera frame
        self._recent_rate: Array | None = None  # the last velocity known (kept while lost)
        self._tracking = False
        #: Where the last lost frame's view was found when only its ratios failed
        #: (``hold_parallax_frames``); None otherwise; and the frames lost on it in a row.
        self._held: Array | None = None
        self._held_frames = 0
        self.readout_estimator = ReadoutEstimator(cfg.readout_estimate)
        #: Frames that painted the map: index -> (R_pano_cam, rate rad/s camera axes or None
        #: while unknown, readout its rows were turned by) - what the readout's estimate needs.
        self._painted = PaintedFrames()
        #: The readout in use, s (``readout_s``, then the estimate).
        self.readout_s = cfg.readout_s
        #: The frames mapped as a global shutter until the estimate replaces readout 0 (then
        #: None: the map was repainted, or there is nothing to repaint).
        self._early: EarlyFrames | None = None
        if cfg.estimate_readout and cfg.readout_s == 0.0 and cfg.repaint_max_mb > 0:
            self._early = EarlyFrames(int(cfg.repaint_max_mb * 2 ** 20))

    @property
    def initialised(self) -> bool:
        return self._last_R is not None

    @property
    def tracking(self) -> bool:
        return self._tracking

    def predict(self, stamp_ns: int | None) -> Array:
        """Constant-motion prediction of R_pano_cam at ``stamp_ns`` from the last tracked frame."""
        assert self._last_R is not None
        if self._velocity is None or stamp_ns is None or self._last_stamp is None:
            return self._last_R
        dt = (stamp_ns - self._last_stamp) * 1e-9
        if not 0 < dt < 0.5:
            return self._last_R
        return self._last_R @ _exp_rotation(self._velocity * dt)

    def process(self, frame: NDArray[np.uint8], K: Array, stamp_ns: int | None = None,
                gray: NDArray[np.uint8] | None = None, prior: Array | None = None) -> FrameResult:
        """Track and map one frame (grey (H, W) or RGB (H, W, 3) uint8) with intrinsics K.

        ``prior``: an optional R_pano_cam from elsewhere (a gyro, or the capture design of a
        photo sequence) used instead of the constant-motion prediction and as the
        re-localisation hint; the estimate still comes from the map alone."""
        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or frame.ndim not in (2, 3) or (frame.ndim == 3 and frame.shape[2] != 3):
            raise PanoramaError(f'frame must be uint8 grey or RGB, got {frame.dtype} {frame.shape}')
        K = np.asarray(K, float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise PanoramaError('camera matrix K is not a valid 3x3 intrinsic matrix')
        # OpenCV's colour conversions keep uint8; np.asarray only narrows their MatLike type.
        if gray is None:
            gray = frame if frame.ndim == 2 else np.asarray(cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY), dtype=np.uint8)
        to_map = frame if self.config.map.channels == 3 else gray
        if to_map.ndim == 2 and self.config.map.channels == 3:
            to_map = np.asarray(cv2.cvtColor(gray, cv2.COLOR_GRAY2RGB), dtype=np.uint8)
        gray_of_rgb = gray if to_map.ndim == 3 else None  # what map_frame samples a colour frame's grey from
        self.frame_index += 1
        idx = self.frame_index
        was_tracking = self._tracking
        if not self.initialised:
            if _grey_std(gray) < self.config.min_texture_std:
                self.lost_frames += 1
                return FrameResult(None, 'lost', reason='first frame has no texture')
            R = np.eye(3)
            n = self.map.map_frame(to_map, K, R, idx, 0.0, gray_of_rgb)
            self._painted[idx] = (R, None, 0.0)
            if self._early is not None:
                self._early.add(EarlyFrame(idx, to_map, gray_of_rgb, K, 0.5, 0.0, 1.0))
            self._accept(R, stamp_ns, self._row_centre(R, stamp_ns, 0.5, None))
            self.frame_size = gray.shape
            return FrameResult(R, 'initialised', mapped_pixels=n)
        last_R = self._last_R
        assert last_R is not None  # initialised (above) means a last pose
        texture = _grey_std(gray)
        if texture < self.config.min_texture_std:
            return self._lose(f'frame has no texture (std {texture:.1f})')
        status = 'tracked'
        res: TrackResult | None = None
        # a rolling shutter's rows turn at the last rate known (the velocity, or the last one while lost)
        motion = self._row_motion(self._recent_rate)
        if self._tracking or prior is not None:
            R_pred = self.predict(stamp_ns) if prior is None else np.asarray(prior, float)
            res = self.tracker.track(gray, K, R_pred, self.map, row_motion=motion)
            if not res.ok:
                res = self.tracker.track(gray, K, R_pred, self.map, self.config.wide_radius_px, row_motion=motion)
        if res is None or not res.ok:
            held = self._held_view(gray, K, motion) if prior is None else None
            if held is not None and not self._restart_due(stamp_ns):
                self._held_frames += 1
                return self._lose(held.reason, held, hold=held.R_fit)
            status = 'relocalised'
            res = self._recover(gray, K, last_R if prior is None else np.asarray(prior, float), motion) or res
        if res is None or not res.ok:
            if self._restart_due(stamp_ns):
                self._restart()
                return self.process(frame, K, stamp_ns, gray, prior)
            hold = res.R_fit if res is not None and self._only_ratios_failed(res) else None
            self._held_frames = 0
            return self._lose(res.reason if res is not None else 'no relocalisation hypothesis', res, hold=hold)
        R = res.R_pano_cam
        if status == 'tracked':
            step = np.degrees(np.linalg.norm(_log_rotation(last_R.T @ R)))
            if step > self.config.max_step_deg:
                return self._lose(f'rotation step of {step:.0f} deg between frames', res)
        # the inliers' mean row position (row + 0.5) / height; a tracked frame has its fit
        row_centre = float(np.mean(res.row_fit.rows)) if res.row_fit is not None else 0.5
        centre = self._row_centre(R, stamp_ns, row_centre, motion)
        rate = self._rate_to(centre) if status == 'tracked' else None
        if rate is not None:
            previous = self._painted.get(idx - 1)
            if previous is not None and previous[1] is None:  # painted before its rate was known
                self._painted[idx - 1] = (previous[0], rate, previous[2])
            if self.config.estimate_readout and res.row_fit is not None:
                self.readout_estimator.add(self.readout_s, rate, R, *self._painting(res.row_fit, K, gray.shape[0]))
            if motion is not None and centre is not None:
                # The fit turned the rows by the previous pair's rate, and its error times the
                # rows' mean read time went into its stamp orientation; the rate of the pair this
                # frame closes is 1.5 frame intervals more recent. (With the previous one the
                # frame-to-frame rotations lagged the truth by 4-7 ms at 28-30 ms readouts - the
                # hand changes its rate from frame to frame - and biased the camera-IMU offset.)
                R = stamp_orientation(centre[0], rate, centre[2])
        # the rate over the last frame interval turns the rows of this frame as it is mapped
        paint_motion = self.map.row_motion = self._row_motion(rate)
        try:
            pixels = self.map.new_pixels(K, R, gray.shape)
            offset, gain = self._correction(res, stamp_ns, gray, K, pixels)
            n = 0 if pixels is None else self.map.map_frame(to_map, K, R, idx, offset, gray_of_rgb, gain, pixels)
        finally:
            self.map.row_motion = None
        if n:
            self._painted[idx] = (R, rate, 0.0 if paint_motion is None else paint_motion[1])
            if self._early is not None:
                self._early.add(EarlyFrame(idx, to_map, gray_of_rgb, K, row_centre, offset, gain))
        self._accept(R, stamp_ns, centre, keep_velocity=was_tracking)
        self._last_row_centre = row_centre
        if self.config.estimate_readout:
            self._update_readout(row_centre)
        return FrameResult(R, status, res, n, offset, intensity_gain=gain)

    def _recover(self, gray: NDArray[np.uint8], K: Array, hint: Array,
                 motion: tuple[Array, float] | None) -> TrackResult | None:
        """Find a lost frame again from the relocaliser's hypotheses: the first one the tracker
        verifies (refined by a second pass), else the last failed attempt; None without any.

        (Tried in session 23: also starting from the rotation most of the previous lost frame
        agreed on when only the ratio tests had failed. On the graph bench bag 5 % more frames
        were tracked at the same accuracy, but seed 598's panorama tracking went 1.46 -> 1.61
        deg: frames found there map from a place the parallax has biased.)"""
        res: TrackResult | None = None
        for R_hyp in self.relocaliser.hypotheses(gray, K, hint, self.map):
            res = self.tracker.track(gray, K, R_hyp, self.map, self.config.wide_radius_px, row_motion=motion)
            if res.ok:
                # Second pass from the refined estimate: templates warped at the right pose.
                res2 = self.tracker.track(gray, K, res.R_pano_cam, self.map, row_motion=motion)
                return res2 if res2.ok else res
        return res

    def _only_ratios_failed(self, res: TrackResult) -> bool:
        """Whether a failed attempt found the view (enough inliers, ``min_inliers``) and failed
        only the consistency ratios: what a camera among near objects (parallax) gives."""
        return not res.ok and res.R_fit is not None and res.inliers >= self.config.tracker.min_inliers

    def _held_view(self, gray: NDArray[np.uint8], K: Array, motion: tuple[Array, float] | None) -> TrackResult | None:
        """The attempt at the held place (``hold_parallax_frames``) when it again finds the view
        and fails only its ratios; None when there is no held place or the attempt says
        otherwise (the frame may be back, or the view has gone): then the frame is relocalised
        as any lost frame, so that what is accepted never depends on the held place.

        On the graph bench bag 300 of its 309 lost frames were such parallax rejections, each a
        full relocalisation (~27 ms) and verification (~9 ms): more than the frame interval, so
        live the mapper fell behind in every long loss and dropped frames. The held attempt is
        one wide search (~5 ms), and the place follows the camera (the rejected fit,
        ``TrackResult.R_fit``).
        """
        if self._held is None or self._held_frames >= self.config.hold_parallax_frames:
            return None
        res = self.tracker.track(gray, K, self._held, self.map, self.config.wide_radius_px, row_motion=motion)
        return res if self._only_ratios_failed(res) else None

    def _update_readout(self, row_centre: float) -> None:
        """The readout in use from the estimator, and the map painted again when the estimate
        first replaces 0 (``row_centre``: the last tracked frame's, :meth:`_repaint`)."""
        self.readout_s = self.readout_estimator.readout(self.config.readout_s)
        if self._early is not None and self.readout_s != 0.0:
            self._repaint(row_centre)

    def _repaint(self, row_centre: float) -> None:
        """The readout estimate has just replaced 0: paint the map again from the frames kept
        (:mod:`.repaint`, once), and move the last frame into it (its R was fitted as a global
        shutter, at ``row_centre`` of the readout)."""
        early, self._early = self._early, None
        if early is None or not early.frames:
            if early is not None:
                logger.info('readout estimated after the early frames outgrew repaint_max_mb: not repainted')
            return
        readout = self.readout_s
        self.map, moved = repaint(early.frames, self._painted, readout, self.config.map, self.map.generation + 1)
        for i, R_i in moved.items():
            self._painted[i] = (R_i, self._painted[i][1], readout)
        if self._last_R is not None and self._last_centre is not None:
            omega = self._recent_rate if self._recent_rate is not None else np.zeros(3)
            R_fit, stamp, _ = self._last_centre
            self._last_centre = (R_fit, stamp, readout * row_centre)
            self._last_R = stamp_orientation(R_fit, omega, readout * row_centre)

    def _correction(self, res: TrackResult, stamp_ns: int | None, gray: NDArray[np.uint8],
                    K: Array, pixels: NewPixels | None) -> tuple[float, float]:
        """(offset, gain) of the EDR correction of a tracked frame (sec. 4.1)."""
        cfg = self.config
        if not cfg.map.edr:
            return 0.0, 1.0
        dt = (stamp_ns - self._last_stamp) * 1e-9 if stamp_ns is not None and self._last_stamp is not None else 0.0
        if cfg.edr_correction == 'overlap':
            # The keypoint offset filter runs along as the fallback for frames with no fit.
            fallback = self.offset_filter.update(res.intensity_offset, res.intensity_offset_se, dt)
            ov = cfg.overlap_exposure
            if pixels is None:  # nothing to map: nothing to correct
                return fallback, 1.0
            pairs = self.map.overlap_pairs(gray, K, res.R_pano_cam, ov.step_px)
            fit = None if pairs is None else fit_overlap_exposure(*pairs, ov, self._overlap_fit)
            if fit is None:
                return fallback, 1.0
            self._overlap_fit = fit
            return fit[1], fit[0]
        if cfg.edr_correction == 'offset':
            return self.offset_filter.update(res.intensity_offset, res.intensity_offset_se, dt), 1.0
        return 0.0, float(np.exp(self.exposure.update(res.log_gain, res.log_gain_se, dt)))

    def background(self) -> int:
        """Keypoints of finished tiles, with the per-frame budget (see MapperConfig)."""
        return self.map.process_queue(self.config.background_tiles, self.config.min_keypoints)

    def _painting(self, fit: RowFit, K: Array, height: int) -> tuple[RowFit | None, Painting | None]:
        """The fit's rays whose map pixels came from a frame of known rate, with how that frame
        painted them (:class:`.readout.Painting`)."""
        uv = self.map.keypoints()[1][fit.keypoints]
        ids = self.map.contribution[uv[:, 1].astype(np.int64), uv[:, 0].astype(np.int64)]
        painted = self._painted
        rows_all = painted.rows(ids)
        # Only the rays painted by a frame of known rate are computed (each ray's values are its own).
        known = np.flatnonzero(painted.known[rows_all])
        if known.size == 0:
            return None, None
        which = rows_all[known]
        R_j = painted.R[which]  # (n, 3, 3) the painting frame of each ray
        w_j = painted.rate[which]
        _, y, _ = project_to_image(K, np.einsum('nji,nj->ni', R_j, fit.rays[known] + fit.residuals[known]))
        rows = (y + 0.5) / height
        omega = np.einsum('nij,nj->ni', R_j, w_j)
        readout = painted.readout[which]
        keep = np.isfinite(rows)
        if not keep.any():
            return None, None
        ray = known[keep]
        sub = RowFit(fit.rays[ray], fit.residuals[ray], fit.rows[ray], fit.keypoints[ray])
        return sub, Painting(omega[keep], rows[keep], readout[keep])

    def _row_motion(self, omega: Array | None) -> tuple[Array, float] | None:
        """(omega, readout) for the tracker and the map when the camera has a rolling shutter."""
        if self.readout_s == 0.0 or omega is None:
            return None
        return np.asarray(omega, float), float(self.readout_s)

    @staticmethod
    def _row_centre(R: Array, stamp_ns: int | None, row_centre: float,
                    motion: tuple[Array, float] | None) -> tuple[Array, int, float] | None:
        """(R_pano_cam, stamp ns, s after it) of a frame at the mean read time of its inliers' rows
        (``row_centre``: their mean row position, (row + 0.5) / height).

        With a rolling shutter the fit turns each row by the assumed rate, so the stamp's
        orientation carries the rate's error times that mean time (the readout times the
        inliers' mean row position), while the orientation at the mean time does not (to first
        order). Differencing stamp orientations for the next
        frame's rate closes a loop whose gain is about (mean row time) / (frame interval): at a
        30 ms readout and 30 Hz, near or above one when the texture sits low in the image, and
        the rate then oscillates frame to frame and grows until tracking is lost. Differencing
        these centres opens the loop."""
        if stamp_ns is None:
            return None
        if motion is None:
            return R, stamp_ns, 0.0
        t = motion[1] * row_centre
        return R @ _exp_rotation(motion[0] * t), stamp_ns, t

    def _rate_to(self, centre: tuple[Array, int, float] | None, max_dt_s: float = 0.5) -> Array | None:
        """The camera's rate (rad/s, camera axes) from the last tracked frame to ``centre``
        (both at their rows' mean read time, :meth:`_row_centre`)."""
        if self._last_centre is None or centre is None:
            return None
        (R0, t0, d0), (R1, t1, d1) = self._last_centre, centre
        dt = (t1 - t0) * 1e-9 + (d1 - d0)
        return _log_rotation(R0.T @ R1) / dt if 0 < dt < max_dt_s else None

    def _accept(self, R: Array, stamp_ns: int | None, centre: tuple[Array, int, float] | None,
                keep_velocity: bool = False) -> None:
        self._velocity = self._rate_to(centre, math.inf) if keep_velocity else None
        if self._velocity is not None:
            self._recent_rate = self._velocity
        self._last_R = R
        self._last_stamp = stamp_ns
        self._last_centre = centre
        self._tracking = True
        self._held = None
        self._lost_since_ns = None

    def _restart_due(self, stamp_ns: int | None) -> bool:
        """Whether this lost frame ends the wait for the old map (``restart_lost_s``)."""
        limit = self.config.restart_lost_s
        if limit <= 0 or stamp_ns is None:
            return False
        if self._lost_since_ns is None or stamp_ns < self._lost_since_ns:
            self._lost_since_ns = stamp_ns
        return (stamp_ns - self._lost_since_ns) * 1e-9 >= limit

    def _restart(self) -> None:
        """A new panorama: the map and everything tied to it forgotten, the camera's readout
        (estimate and estimator) kept; the next frame initialises the new map."""
        readout_s, estimator, lost, restarts = self.readout_s, self.readout_estimator, self.lost_frames, self.restarts
        self.reset()
        self.readout_s, self.readout_estimator, self.lost_frames = readout_s, estimator, lost
        self.restarts = restarts + 1
        if readout_s > 0.0:
            self._early = None  # nothing to paint again: the readout is known

    def _lose(self, reason: str, res: TrackResult | None = None, hold: Array | None = None) -> FrameResult:
        if self.config.estimate_readout and self.readout_s == 0.0 and self._tracking:
            # Lost while mapping as a global shutter: from now on an early estimate of the
            # readout is used (ReadoutConfig.min_readings_lost) and the map painted again with
            # it, so that relocalisation and the frames after it meet an unsheared map.
            self.readout_estimator.tracker_lost()
            self._update_readout(self._last_row_centre)
        self.lost_frames += 1
        self._tracking = False
        self._velocity = None
        self._held = hold
        return FrameResult(None, 'lost', res, reason=reason)

    def seam_error(self, min_gap: int = 1, **kwargs: Any) -> dict[str, float]:
        """Seam measure of the current grey map (see :func:`map.seam_error`; ``kwargs`` go there)."""
        vals = self.map.gray.astype(np.float64)
        vals[~self.map.mapped] = np.nan
        return seam_error(vals, self.map.contribution, min_gap=min_gap, **kwargs)
