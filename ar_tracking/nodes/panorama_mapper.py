"""panorama_mapper: cylindrical panorama built on the fly and 3-DoF orientation tracking
against it, with an extended-dynamic-range map (Langlotz 2011 sec. 3.1, 4.1).

Subscribes ``camera/image_raw`` (sensor_msgs/Image) and ``camera/image_raw/compressed``
(CompressedImage), paired by stamp with ``camera/camera_info``; a lens distortion that
camera_info gives (``plumb_bob``, ``rational_polynomial``, ``equidistant``) is undone before
tracking (:mod:`ar_tracking.core.rectification`). Publishes, for every tracked
frame, ``panorama/orientation`` (TransformStamped, frame_id ``panorama``, child
``camera_optical``, rotation R_panorama_cam, the image's stamp), and at ``publish_rate_hz``
(by image stamps, so lockstep runs are reproducible) the map ``panorama/image`` (mono16 or
rgb16, linearly tone-mapped EDR map) and ``panorama/tiles`` (mono8, one pixel per tile, nonzero
finished: 255, one less each time the map is painted again), latched. A camera with a rolling
shutter whose readout is not given is mapped as a global shutter until the readout is estimated
(``estimate_readout``; sooner when tracking is lost first), then the map is painted again from
the frames so far (once, from up to ``repaint_max_mb`` of them). A frame that cannot be tracked
(lost, textureless, translating camera) is not published; bad messages are dropped with a
throttled warning. The algorithm is
:mod:`ar_tracking.core.panorama`; this node converts and publishes.
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import cv2
import numpy as np
from geometry_msgs.msg import TransformStamped
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from ..core.panorama import EDR_CORRECTIONS, MapConfig, MapperConfig, PanoramaError, PanoramaMapper, TrackerConfig
from ..core.panorama.exposure import OFFSET_EXPOSURE
from ..core.rectification import Rectification, RectificationCache, RectificationError, check_distortion
from ..core.stamp_pairing import NearestStampPairer
from ..ros.cdr_views import camera_info_view, compressed_image_view, image_view, rotation_transform_cdr
from ..ros.conversions import (
    ConversionError,
    array_to_image,
    compressed_to_array,
    image_to_array,
    stamp_ns,
    to_stamp,
)
from ..ros.node_base import CAMERA_QOS, LATCHED_QOS, RELIABLE_QOS, TrackingNode, run_node
from ..ros.param_table import ParamSpec, declare_params, one_of
from ..ros.stamp_guard import StampGuard, StampVerdict

Frame = tuple[np.ndarray, np.ndarray]  # (grey uint8, RGB uint8 or None)


def to_gray_rgb(arr: np.ndarray, encoding: str) -> Frame:
    """(grey, RGB) uint8 of an image array in ``encoding`` (Image encodings, or 'bgr' / 'mono'
    for decoded compressed images)."""
    if arr.dtype == np.uint16:
        arr = (arr >> 8).astype(np.uint8)
    elif arr.dtype != np.uint8:
        raise ConversionError(f'image encoding {encoding!r} is not supported by panorama_mapper')
    if arr.ndim == 2:
        return arr, None
    ch = arr.shape[2]
    if ch == 1:
        return arr[:, :, 0], None
    bgr = encoding.startswith('bgr') or encoding in ('bgr', '8UC3', '8UC4')
    if ch == 4:
        arr = cv2.cvtColor(arr, cv2.COLOR_BGRA2BGR if bgr else cv2.COLOR_RGBA2RGB)
    rgb = cv2.cvtColor(arr, cv2.COLOR_BGR2RGB) if bgr else arr
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), rgb


def _divides_512(v: Any) -> str | None:
    """A tile side must divide the map height (512; the width 2048 then too)."""
    return None if 512 % v == 0 else 'must divide 512'


#: The node's parameters.
PARAMS = (
    ParamSpec('edr', True,
              'Extended dynamic range map (Langlotz sec. 4.1): 16-bit map, each frame corrected for exposure before '
              'it is mapped (edr_correction); false: plain 8-bit map', read_only=True),
    ParamSpec('edr_smooth', True,
              'EDR offsets filtered over frames (per-frame estimation noise would be a small step at every frame '
              'boundary); false: each frame its own offset, as sec. 4.1 literally says', read_only=True),
    ParamSpec('edr_correction', 'overlap',
              'EDR correction of each frame before it is mapped: overlap (gain and offset fitted on every mapped '
              'pixel the frame overlaps, robustly), offset (mean intensity difference of the matched keypoint pairs, '
              'sec. 4.1) or gain (the same mean of log intensities)',
              read_only=True, validate=one_of(EDR_CORRECTIONS)),
    ParamSpec('color', False, 'Map colour (rgb16) instead of grey (mono16)', read_only=True),
    ParamSpec('tile_size_px', 64,
              'Side of a map tile, pixels (divides 2048 and 512); a tile whose pixels are all mapped is finished',
              min_value=8, max_value=256, read_only=True, validate=_divides_512),
    ParamSpec('fast_threshold', 12,
              'FAST threshold for the keypoints of finished tiles, 8-bit grey levels',
              min_value=1, max_value=255, read_only=True),
    ParamSpec('keypoints_per_tile', 12,
              'Strongest FAST keypoints kept per finished tile', min_value=1, max_value=200, read_only=True),
    ParamSpec('search_radius_px', 4,
              'Active search radius around the constant-motion prediction, pixels',
              min_value=1, max_value=32, read_only=True),
    ParamSpec('wide_radius_px', 10,
              'Search radius of the second attempt and of re-localisation, pixels',
              min_value=1, max_value=48, read_only=True),
    ParamSpec('max_features', 60, 'Map keypoints searched per frame', min_value=10, max_value=1000, read_only=True),
    ParamSpec('restart_lost_s', 0.0,
              'Lost this long with nothing in the map to relocalise against (the camera turned on into azimuths '
              'the map never saw), a new panorama starts from the current frame, s; 0 (default): wait for the old map',
              min_value=0.0, max_value=3600.0, read_only=True),
    ParamSpec('hold_parallax_frames', 30,
              'A lost frame whose view was found but rejected by the ratio tests (near objects: parallax) is tried '
              'at that place first, and lost without a full relocalisation when it is rejected the same way again, '
              'at most this many frames in a row (a lost frame costs ~8 instead of ~36 ms); 0: relocalise every lost '
              'frame', min_value=0, max_value=100000, read_only=True),
    ParamSpec('readout_s', 0.0,
              'Rolling-shutter readout of the camera, s (0: a global shutter); the tracker and the map turn each row '
              'by the camera\'s rate, and panorama/orientation is the orientation at the frame\'s stamp',
              min_value=0.0, max_value=0.1, read_only=True),
    ParamSpec('estimate_readout', True,
              'Estimate the rolling shutter\'s readout from the tracked frames and use it in place of readout_s once '
              'it is known (logged); readout_s is then only the start value', read_only=True),
    ParamSpec('repaint_max_mb', 96.0,
              'With readout_s 0 and estimate_readout, the frames mapped before the readout is known are kept, up to '
              'this many MB, and the map is painted again from them once it is (0: never)',
              min_value=0.0, max_value=4096.0, read_only=True),
    ParamSpec('min_inliers', 10,
              'A frame is tracked with at least this many inlier matches', min_value=3, max_value=1000, read_only=True),
    ParamSpec('min_inlier_ratio', 0.7,
              'and at least this fraction of the searched keypoints agreeing with the rotation: inliers, or '
              'keypoints whose correlation peak reached weak_ncc where the rotation puts them (a translating '
              'camera falls below it)',
              min_value=0.0, max_value=1.0, read_only=True),
    ParamSpec('min_matched_inlier_ratio', 0.7,
              'and at least this fraction of the matched keypoints (correlation >= min_ncc) being inliers',
              min_value=0.0, max_value=1.0, read_only=True),
    ParamSpec('weak_ncc', 0.5,
              'A keypoint below min_ncc whose correlation peak reaches this within 2 px of where the rotation '
              'puts it still agrees (fine detail weakened by blur: branches, grass, blinds)',
              min_value=0.0, max_value=1.0, read_only=True),
    ParamSpec('inlier_px', 1.5, 'RANSAC inlier threshold, pixels', min_value=0.1, max_value=20.0, read_only=True),
    ParamSpec('min_ncc', 0.75,
              'Smallest accepted normalised cross-correlation of a patch match',
              min_value=0.0, max_value=1.0, read_only=True),
    ParamSpec('background_tiles', 4,
              'Finished tiles whose keypoints are computed after each frame (off the critical path)',
              min_value=1, max_value=1024, read_only=True),
    ParamSpec('publish_rate_hz', 1.0,
              'Rate of panorama/image and panorama/tiles, by image stamps, Hz',
              min_value=0.01, max_value=100.0, read_only=True),
    ParamSpec('fallback_hfov_deg', 0.0,
              'Horizontal field of view used when no camera_info is received, degrees (0: frames without camera_info '
              'are skipped)', min_value=0.0, max_value=170.0, read_only=True),
    ParamSpec('camera_info_max_gap_s', 0.005,
              'Largest stamp difference between an image and the camera_info paired with it, s',
              min_value=0.0, max_value=1.0, read_only=True),
    ParamSpec('reset_after_s', 1.0,
              'An image stamp this much older than the previous one means the clock jumped back (bag loop): start a '
              'new panorama', min_value=0.0, max_value=3600.0),
    ParamSpec('frame_id', 'panorama', 'frame_id of the outputs (the panorama frame)'),
    ParamSpec('child_frame_id', 'camera_optical', 'child_frame_id of panorama/orientation'),
)


class PanoramaMapperNode(TrackingNode):
    INPUTS = {
        'camera/image_raw': 'sensor_msgs/msg/Image',
        'camera/image_raw/compressed': 'sensor_msgs/msg/CompressedImage',
        'camera/camera_info': 'sensor_msgs/msg/CameraInfo',
    }
    OUTPUTS = {
        'panorama/orientation': 'geometry_msgs/msg/TransformStamped',
        'panorama/image': 'sensor_msgs/msg/Image',
        'panorama/tiles': 'sensor_msgs/msg/Image',
    }
    #: Either image topic; camera_info may be replaced by ``fallback_hfov_deg``.
    REQUIRED_INPUTS = [('camera/image_raw', 'camera/image_raw/compressed')]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('panorama_mapper', **kwargs)
        v = declare_params(self, PARAMS)
        edr = v['edr']
        color = v['color']
        tile = v['tile_size_px']
        self.publish_period_ns = int(1e9 / v['publish_rate_hz'])
        self.fallback_hfov_rad = math.radians(v['fallback_hfov_deg'])
        self.max_info_gap_ns = int(1e9 * v['camera_info_max_gap_s'])
        reset_s = v['reset_after_s']
        self.frame_id: str = v['frame_id']
        self.child_frame_id: str = v['child_frame_id']

        self.config = MapperConfig(
            map=MapConfig(tile_size=tile, edr=edr, channels=3 if color else 1, fast_threshold=v['fast_threshold'],
                          keypoints_per_tile=v['keypoints_per_tile']),
            tracker=TrackerConfig(search_radius_px=v['search_radius_px'], max_features=v['max_features'],
                                  min_inliers=v['min_inliers'], min_inlier_ratio=v['min_inlier_ratio'],
                                  min_matched_inlier_ratio=v['min_matched_inlier_ratio'],
                                  weak_ncc=v['weak_ncc'], inlier_px=v['inlier_px'], min_ncc=v['min_ncc']),
            wide_radius_px=v['wide_radius_px'], background_tiles=v['background_tiles'], readout_s=v['readout_s'],
            estimate_readout=v['estimate_readout'], repaint_max_mb=v['repaint_max_mb'], restart_lost_s=v['restart_lost_s'],
            hold_parallax_frames=v['hold_parallax_frames'],
            offset_exposure=replace(OFFSET_EXPOSURE, smooth=v['edr_smooth']), edr_correction=v['edr_correction'],
        )
        self.core = PanoramaMapper(self.config)
        self.readout_logged_s = self.config.readout_s
        self.generation_logged = 0  # the map generation last logged (core/panorama/repaint.py)
        self.color = color
        self.guard = StampGuard(reset_s)
        #: image <-> camera_info (K, D, distortion model, (height, width)) by stamp
        self.pairer: NearestStampPairer[Frame, tuple[Any, ...]] = NearestStampPairer(self.max_info_gap_ns)
        self.info_seen = False
        #: The rectification of the calibration in use (camera_info's lens distortion undone).
        self.rectifications = RectificationCache()
        self.last_map_pub_ns: int | None = None
        self.published = 0
        self.lost = 0

        self.pub_orientation = self.advertise(TransformStamped, 'panorama/orientation', RELIABLE_QOS)
        self.pub_image = self.advertise(Image, 'panorama/image', LATCHED_QOS)
        self.pub_tiles = self.advertise(Image, 'panorama/tiles', LATCHED_QOS)
        # read in place from the received bytes (ros.cdr_views), not copied into a message
        self.subscribe(Image, 'camera/image_raw', self.on_image, CAMERA_QOS, view=image_view)
        self.subscribe(CompressedImage, 'camera/image_raw/compressed', self.on_compressed, CAMERA_QOS,
                       view=compressed_image_view)
        self.subscribe(CameraInfo, 'camera/camera_info', self.on_camera_info, CAMERA_QOS, view=camera_info_view)
        self.get_logger().info(f'panorama_mapper: {"EDR" if edr else "8-bit"} {"colour" if color else "grey"} map 2048x512, tiles {tile} px')

    # -- inputs ----------------------------------------------------------------------------

    def on_image(self, msg: Image) -> None:
        try:
            frame = to_gray_rgb(image_to_array(msg), msg.encoding)
        except ConversionError as exc:
            self.warn_throttled(f'camera/image_raw: {exc}, frame dropped')
            return
        self._on_frame(stamp_ns(msg.header), frame)

    def on_compressed(self, msg: CompressedImage) -> None:
        try:
            arr = compressed_to_array(msg)
            frame = to_gray_rgb(arr, 'bgr' if arr.ndim == 3 else 'mono')
        except ConversionError as exc:
            self.warn_throttled(f'camera/image_raw/compressed: {exc}, frame dropped')
            return
        self._on_frame(stamp_ns(msg.header), frame)

    def on_camera_info(self, msg: CameraInfo) -> None:
        K = np.asarray(msg.k, float).reshape(3, 3)
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or K[2, 2] != 1.0 or msg.width <= 0 or msg.height <= 0:
            self.warn_throttled('camera/camera_info: invalid K or size, ignored')
            return
        model = str(msg.distortion_model)
        try:
            D = check_distortion(msg.d, model)
        except RectificationError as exc:
            self.warn_throttled(f'camera/camera_info: {exc}, ignored')
            return
        self.info_seen = True
        size = (int(msg.height), int(msg.width))
        for t, frame, info in self.pairer.add_secondary(stamp_ns(msg.header), (K, D, model, size)):
            self._handle(t, frame, info)

    def _on_frame(self, t: int, frame: Frame) -> None:
        verdict = self.guard.check(t)
        if verdict is StampVerdict.RESET:
            self.get_logger().warning('camera: clock jumped back (bag loop?), starting a new panorama')
            self.core.reset()
            self.pairer.reset()
            self.last_map_pub_ns = None
        elif verdict is not StampVerdict.OK:
            self.warn_throttled(f'camera: {verdict.value}, frame dropped')
            return
        if not self.info_seen and self.fallback_hfov_rad > 0:
            self._handle(t, frame, None)
            return
        for t_, frame_, info in self.pairer.add_primary(t, frame):
            self._handle(t_, frame_, info)

    # -- processing ------------------------------------------------------------------------

    def _rectify(self, K: np.ndarray, D: np.ndarray, model: str, size: tuple[int, int]) -> Rectification:
        """The rectification of this calibration (logged when a new distorting one is built)."""
        rect, built = self.rectifications.get(K, D, size[1], size[0], model)
        if built and not rect.identity:
            Kn = rect.K
            self.get_logger().info(
                f'camera_info has a lens distortion ({model or "plumb_bob"}, {D.size} coefficients): frames are '
                f'rectified to a pinhole camera fx {Kn[0, 0]:.1f} fy {Kn[1, 1]:.1f} cx {Kn[0, 2]:.1f} cy {Kn[1, 2]:.1f}')
        return rect

    def _handle(self, t: int, frame: Frame, info: tuple[Any, ...] | None) -> None:
        gray, rgb = frame
        h, w = gray.shape
        if info is None:
            if self.fallback_hfov_rad <= 0:
                self.warn_throttled('camera: no camera_info with the image stamp (set fallback_hfov_deg to use a default), frame skipped')
                return
            f = w / 2 / math.tan(self.fallback_hfov_rad / 2)
            K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
        else:
            K, D, model, size = info
            if size != (h, w):
                self.warn_throttled(f'camera: frame is {w}x{h} but camera_info says {size[1]}x{size[0]}, frame skipped')
                return
            rectify = self._rectify(K, D, model, size)
            if not rectify.identity:
                K = rectify.K
                gray, rgb = rectify(gray), None if rgb is None else rectify(rgb)
        if self.core.frame_size is not None and self.core.frame_size != (h, w) and info is None:
            self.warn_throttled('camera: frame size changed, frame skipped')
            return
        to_map = rgb if (self.color and rgb is not None) else gray
        restarts = self.core.restarts
        try:
            res = self.core.process(to_map, K, t, gray=gray)
        except PanoramaError as exc:
            self.warn_throttled(f'camera: {exc}, frame skipped')
            return
        if self.core.restarts != restarts:
            self.get_logger().warning(
                f'panorama tracking lost for {self.config.restart_lost_s:g} s with nothing in the map to relocalise '
                'against: a new panorama starts from this frame')
        self._log_readout()
        R = res.R_pano_cam
        if R is not None and np.all(np.isfinite(R)):
            # as CDR bytes (ros.cdr_views): the TransformStamped set_quaternion would fill
            sec, nanosec = divmod(int(t), 1_000_000_000)
            self.pub_orientation.publish(rotation_transform_cdr(sec, nanosec, self.frame_id, self.child_frame_id, R))
            self.published += 1
        else:
            self.lost += 1
            self.warn_throttled(f'panorama tracking lost: {res.reason}')
        if not self.core.map.empty and (self.last_map_pub_ns is None or t - self.last_map_pub_ns >= self.publish_period_ns):
            self._publish_map(t)
        self.core.background()  # finished tiles' keypoints: after the frame's outputs

    def _log_readout(self) -> None:
        """Log the readout in use when the estimate first replaces readout_s, and when it moves
        by 2 ms or more (it moves a little with every frame); and when the map was painted
        again with it."""
        generation = self.core.map.generation
        if generation != self.generation_logged:
            self.generation_logged = generation
            if generation:
                self.get_logger().info('rolling shutter: the map is painted again from the frames mapped before the '
                                       'readout was known (they had been mapped as a global shutter)')
        now, last = self.core.readout_s, self.readout_logged_s
        if abs(now - last) < 0.002 and (now == 0.0) == (last == 0.0):
            return
        self.readout_logged_s = now
        est = self.core.readout_estimator.estimate()
        frames = self.core.readout_estimator.frames
        if now == 0.0:
            self.get_logger().info(f'rolling shutter: {frames} tracked frames say a global shutter (readout 0)')
        else:
            sigma = est[1] * 1e3 if est is not None else float('nan')
            self.get_logger().info(f'rolling shutter: readout {now * 1e3:.1f} +- {sigma:.1f} ms, estimated from '
                                   f'{frames} tracked frames (rows are turned by it)')

    def _publish_map(self, t: int) -> None:
        self.last_map_pub_ns = t
        stamp = to_stamp(t)
        img = array_to_image(self.core.map.tone_mapped(16), 'rgb16' if self.color else 'mono16')
        img.header.stamp = stamp
        img.header.frame_id = self.frame_id
        self.pub_image.publish(img)
        tiles = array_to_image(self.core.map.tiles_image(), 'mono8')
        tiles.header.stamp = to_stamp(t)
        tiles.header.frame_id = self.frame_id
        self.pub_tiles.publish(tiles)


def main(args: list[str] | None = None) -> int:
    return run_node(PanoramaMapperNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
