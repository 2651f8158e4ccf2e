"""annotation_matcher: re-detects stored annotations in the panorama being built (Langlotz 2011
sec. 3.2, 4.2, 4.3).

Subscribes ``panorama/image`` (mono16/mono8 map) and ``panorama/tiles`` (mono8, nonzero finished,
same stamp as the map; a new nonzero value means the map was painted again - the rolling
shutter's readout became known - and its tiles are matched again) from panorama_mapper,
``gps/fix`` (NavSatFix) to load the annotations within ``radius_m`` from the store (all of them
when GPS is poor), and for the sensor prior ``orientation/panorama_in_world`` (TransformStamped
enu -> panorama) or ``orientation/global``
(Imu, camera in ENU, paired by stamp with ``panorama/orientation``), averaged over all samples
of the current panorama (chordal mean: the panorama does not turn; weighted by the inverse heading
variance of ``orientation/global``). Newly finished tiles go to a
work queue; every map and orientation message (the frame clock) drains it within
``budget_ms``, counted with a fixed cost per tile x annotation (``op_cost_ms``) so that lockstep
runs stay reproducible. Publishes ``annotations/markers`` (MarkerArray, one TEXT marker per
placed annotation in the panorama frame, ns ``matched`` or ``inferred``) and
``annotations/alignment`` (TransformStamped panorama <- source panorama, child_frame_id = the
source panorama id). With ``landmarks`` the source panoramas' landmarks (stored by
``ar-tracking annotate``) are matched and aligned with the annotations but never published.

No label is shown as placed before the alignment supports it (``min_support_matches`` matched
annotations and landmarks, and a rotation within ``support_prior_sigmas`` of the sensor prior
given both panoramas' heading covariances - the store's panorama record and
``orientation/global``'s covariance - unless ``strong_support_matches`` outvote it; an inferred
label also needs ``local_support_matches`` matches within ``local_support_deg`` of it, or matches on
both sides within ``bracket_support_deg``, and its placement uncertainty - the depth ratio's and
the parallax model's - within ``depth_ratio_support_deg``): until then
the labels go to the namespace ``approximate`` (grey, ``scale.x`` = the 3-sigma direction
uncertainty in rad; ``show_approximate: false`` publishes nothing instead), and
``annotations/alignment`` is not published. The algorithm is :mod:`ar_tracking.core.annotations`; this node converts.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from geometry_msgs.msg import TransformStamped
from sensor_msgs.msg import Image, Imu, NavSatFix, NavSatStatus
from visualization_msgs.msg import Marker, MarkerArray

from ..core.annotations.matching import MatchConfig, ReDetector
from ..core.annotations.store import Annotation, Landmark, PanoramaInfo, StoreError
from ..core.panorama.cylinder import CylinderGeometry
from ..core.rotations import nearest_rotation, quat_xyzw_to_matrix
from ..io.stores import RetryBackoff, describe, open_store
from ..ros.cdr_views import image_view, imu_view, transform_stamped_view
from ..ros.conversions import ConversionError, image_to_array, rotation_from_quaternion, set_quaternion, stamp_ns, to_stamp
from ..ros.node_base import LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, TrackingNode, run_node
from ..ros.param_table import ParamSpec, declare_params
from ..ros.stamp_guard import StampGuard, StampVerdict


#: The node's parameters.
PARAMS = (
    ParamSpec('store_path', '', 'Annotation store (SQLite file) to load annotations from', read_only=True),
    ParamSpec('store_url', '',
              'Annotation store by URL, instead of store_path: sqlite:///path/notes.db or '
              'postgresql://user@host/db[?schema=NAME] (PostGIS, shared by many users; password in PGPASSWORD or '
              '~/.pgpass)', read_only=True),
    ParamSpec('radius_m', 50.0,
              'Annotations authored within this distance of the GPS fix are loaded (sec. 4.3), m',
              min_value=1.0, max_value=100000.0),
    ParamSpec('poor_gps_sigma_m', 25.0,
              'A fix whose horizontal 1-sigma exceeds this is poor: every annotation of the store is loaded, m',
              min_value=0.0, max_value=100000.0),
    ParamSpec('reload_period_s', 10.0,
              'Least time between two store queries (new fix, nothing loaded yet), s', min_value=0.0, max_value=3600.0),
    ParamSpec('budget_ms', 10.0,
              'Matching work per frame (map or orientation message), ms (sec. 3.2)', min_value=0.1, max_value=1000.0),
    ParamSpec('op_cost_ms', 0.25,
              'Planned cost of matching one tile against one annotation, ms (the budget counts these, so runs are '
              'reproducible)', min_value=0.001, max_value=100.0),
    ParamSpec('sensor_prior', True,
              'Sensor prior (sec. 4.2): search around the position expected from the absolute orientation'),
    ParamSpec('prior_window_deg', 10.0,
              'Half-width of the inner prior window (compass error), degrees', min_value=0.5, max_value=180.0),
    ParamSpec('prior_outer_factor', 3.0,
              'The penalised outer window is this many times the inner one', min_value=1.0, max_value=20.0),
    ParamSpec('prior_penalty', 0.3, 'NCC penalty at the edge of the outer window', min_value=0.0, max_value=2.0),
    ParamSpec('ransac', True,
              'Global alignment (sec. 4.3): RANSAC rotation between source and current panorama; places unmatched '
              'annotations too'),
    ParamSpec('inlier_px', 10.0, 'RANSAC inlier threshold, map pixels', min_value=0.5, max_value=100.0),
    ParamSpec('min_inlier_ratio', 0.5,
              'A hypothesis needs more than this share of inliers', min_value=0.0, max_value=1.0),
    ParamSpec('placement_px', 25.0,
              'Annotations are placed at their best candidate within this distance of the aligned position, map '
              'pixels', min_value=0.5, max_value=200.0),
    ParamSpec('guided_search', True,
              'Search inferred annotations again with NCC around their aligned position (extension of sec. 4.3)'),
    ParamSpec('placement_penalty', 0.2,
              'NCC penalty of a candidate at the edge of the placement gate (look-alikes further from the aligned '
              'position lose)', min_value=0.0, max_value=2.0),
    ParamSpec('consensus_score', True,
              'Choose the RANSAC hypothesis by the placement score (penalised NCC of the placed matches) instead of '
              'the lowest normalised error, refine it on all matches (extension of sec. 4.3)'),
    ParamSpec('guided_all', True,
              'Search the matched annotations again around their aligned position too (with guided_search)'),
    ParamSpec('prior_alignment', True,
              'With the sensor prior: RANSAC rotations beyond the compass error of the absolute orientations are not '
              'valid, the compass votes in the choice, and with no valid hypothesis the prior rotation places the '
              'annotations (extension of sec. 4.2/4.3)'),
    ParamSpec('gravity_alignment', True,
              'With prior_alignment: the alignment turns the prior rotation about the vertical only (gravity fixes '
              'the tilt of both panoramas); candidates more than gravity_v_px above or below are not matches'),
    ParamSpec('gravity_v_px', 4.0,
              'Vertical tolerance of a match after the gravity-constrained alignment, map pixels',
              min_value=0.5, max_value=100.0),
    ParamSpec('parallax_model', True,
              'With gravity_alignment: fit the heading residuals of the matches with the parallax of a displaced '
              'standing point and place again (extension of sec. 4.3)'),
    ParamSpec('parallax_elevation', True,
              'The parallax model also raises or lowers the labels by the same displacement (nearer: higher above '
              'eye level)'),
    ParamSpec('parallax_trim_sigmas', 3.0,
              'Refit the parallax model once without the matches beyond this many robust standard deviations of its '
              'residuals (landmarks much nearer than the anchors); 0: off', min_value=0.0, max_value=100.0),
    ParamSpec('parallax_scale_sigma', 0.3,
              "The annotations' parallax as a factor of the model's, fitted on the matched annotations and pulled "
              'to 1 with this sigma (facades farther than the landmarks the model is fitted on); 0: off',
              min_value=0.0, max_value=100.0),
    ParamSpec('parallax_gate_sigmas', 3.0,
              'After the parallax model, matches must lie within this many robust standard deviations of its '
              'leave-one-out residuals (between inlier_px and placement_px); 0: off', min_value=0.0, max_value=100.0),
    ParamSpec('landmarks', True,
              "Load the source panoramas' landmarks with their annotations: matched and aligned like annotations, "
              'never shown'),
    ParamSpec('min_ncc', 0.55, 'Smallest NCC of a candidate match', min_value=-1.0, max_value=1.0),
    ParamSpec('walsh_min', 0.5,
              'Walsh pre-check threshold (sec. 3.2): positions below it get no NCC', min_value=-1.0, max_value=1.0),
    ParamSpec('marker_distance_m', 10.0,
              'Markers are placed at this distance along their direction, m', min_value=0.01, max_value=10000.0),
    ParamSpec('marker_height_m', 0.5, 'Text height of the markers, m', min_value=0.01, max_value=100.0),
    ParamSpec('local_support_matches', 1,
              'An inferred label (no match of its own) is shown as placed only with this many matches within '
              'local_support_deg of it', min_value=0, max_value=1000),
    ParamSpec('local_support_deg', 30.0,
              'Azimuth range of the local support of an inferred label, degrees', min_value=0.0, max_value=180.0),
    ParamSpec('bracket_support_deg', 90.0,
              'An inferred label with fewer local matches is shown as placed when matches lie on both sides of it '
              'within this azimuth (interpolated, not extrapolated), degrees; 0: off', min_value=0.0, max_value=180.0),
    ParamSpec('depth_ratio_support_deg', 0.55,
              'An inferred label is shown as placed only while the uncertainty of its depth ratio to the parallax '
              'model (the fitted ratio\'s and depth_ratio_scatter) moves it by at most this much (1 sigma), degrees; '
              '0: off', min_value=0.0, max_value=180.0),
    ParamSpec('depth_ratio_scatter', 0.2,
              'Spread (1 sigma) of one annotation\'s depth ratio about the ratio fitted on the matched ones',
              min_value=0.0, max_value=10.0),
    ParamSpec('prediction_support', True,
              'depth_ratio_support_deg also counts the parallax model\'s own uncertainty at the label (matches '
              'bunched in one sector pin the model there only)'),
    ParamSpec('matched_agreement_deg', 1.2,
              'A matched label is shown as placed only within this of where the other matches put it (the '
              'alignment with the parallax model), degrees; 0: off', min_value=0.0, max_value=180.0),
    ParamSpec('local_support_matched', True,
              'Matched labels too need local_support_matches other matches within local_support_deg (an isolated '
              'match is only approximate)'),
    ParamSpec('lookalike_margin', 0.1,
              'Look-alike test after the parallax model: a match with another NCC peak in its gate (at least '
              'lookalike_sep_px away) within this NCC of its own is placed at its prediction instead (inferred); 0: '
              'off', min_value=0.0, max_value=2.0),
    ParamSpec('lookalike_sep_px', 6.0,
              'Least distance of a rival peak in the look-alike test (about 1 deg), map pixels',
              min_value=0.0, max_value=100.0),
    ParamSpec('min_support_matches', 4,
              'Labels are shown as placed only when at least this many annotations and landmarks matched the '
              'alignment', min_value=1, max_value=1000),
    ParamSpec('support_prior_sigmas', 3.0,
              "...and the alignment is within this many standard deviations of the sensor prior (both panoramas' "
              'heading covariance), unless strong_support_matches matched', min_value=0.0, max_value=100.0),
    ParamSpec('strong_support_matches', 10,
              'This many matches support an alignment however far it is from the sensor prior',
              min_value=1, max_value=1000),
    ParamSpec('show_approximate', True,
              "Before the alignment is supported, publish the labels in the 'approximate' namespace with their "
              'uncertainty (false: publish none)'),
    ParamSpec('frame_id', 'panorama', 'frame_id of the outputs (the current panorama)'),
    ParamSpec('reset_after_s', 1.0,
              'A map stamp this much older than the previous one means a new panorama (bag loop): start over',
              min_value=0.0, max_value=3600.0),
)


#: Node parameters in degrees whose :class:`MatchConfig` field is in map pixels.
_DEG_TO_PX = {'prior_window_deg': 'prior_window_px', 'local_support_deg': 'local_support_px',
              'bracket_support_deg': 'bracket_support_px', 'matched_agreement_deg': 'matched_agreement_px'}


def _tile_generation(tiles: np.ndarray) -> int | None:
    """The value of the finished tiles of a ``panorama/tiles`` image (255 as first painted, one
    less each time the map was painted again), None while none is finished."""
    finished = tiles[tiles > 0]
    return int(finished.max()) if finished.size else None


def match_config(values: dict[str, Any], f: float) -> MatchConfig:
    """The matcher's configuration from the node's parameter ``values``: those named as a
    :class:`MatchConfig` field as they are, the ones in degrees in map pixels (``f`` pixels per
    radian) or, for ``depth_ratio_support_deg``, in radians."""
    kw = {k: values[k] for k in values.keys() & {field.name for field in dataclasses.fields(MatchConfig)}}
    kw.update({px: math.radians(values[deg]) * f for deg, px in _DEG_TO_PX.items()})
    kw['depth_ratio_support_rad'] = math.radians(values['depth_ratio_support_deg'])
    return MatchConfig(**kw)


class AnnotationMatcherNode(TrackingNode):
    INPUTS = {
        'panorama/image': 'sensor_msgs/msg/Image',
        'panorama/tiles': 'sensor_msgs/msg/Image',
        'gps/fix': 'sensor_msgs/msg/NavSatFix',
        'orientation/panorama_in_world': 'geometry_msgs/msg/TransformStamped',
        'orientation/global': 'sensor_msgs/msg/Imu',
        'panorama/orientation': 'geometry_msgs/msg/TransformStamped',
    }
    OUTPUTS = {
        'annotations/markers': 'visualization_msgs/msg/MarkerArray',
        'annotations/alignment': 'geometry_msgs/msg/TransformStamped',
    }
    REQUIRED_INPUTS = ['panorama/image', 'panorama/tiles', 'gps/fix']
    REQUIRED_PARAMS = [('store_path', 'store_url')]

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('annotation_matcher', **kwargs)
        v = declare_params(self, PARAMS)
        self.store_path: str = v['store_path']
        self.store_url: str = v['store_url']
        #: what on_fix opens; a store that cannot be reached is tried again after 1, 2, 4 ... 60 s (bag time)
        self.store_ref: str = self.store_url or self.store_path
        self.store_backoff = RetryBackoff(initial_s=1.0, max_s=60.0)
        self.radius_m = v['radius_m']
        self.poor_gps_m = v['poor_gps_sigma_m']
        self.reload_period_ns = int(1e9 * v['reload_period_s'])
        self.budget_ms = v['budget_ms']
        self.op_cost_ms = v['op_cost_ms']
        self.use_landmarks = v['landmarks']
        self.marker_distance_m = v['marker_distance_m']
        self.marker_height_m = v['marker_height_m']
        self.show_approximate: bool = v['show_approximate']
        self.frame_id: str = v['frame_id']
        reset_s = v['reset_after_s']
        f = CylinderGeometry().f

        self.match_config = match_config(v, f)
        self.geometry = CylinderGeometry()
        self.annotations: list[Annotation] = []
        self.landmarks: list[Landmark] = []
        self.panoramas: dict[str, PanoramaInfo] = {}
        self.target_sigma = float('nan')
        self.detector: ReDetector | None = None
        self.gray: np.ndarray | None = None
        self.mapped: np.ndarray | None = None
        self.map_stamp: int | None = None
        self.pending_tiles: tuple[int, np.ndarray] | None = None
        self.finished_tiles: np.ndarray | None = None
        #: The finished tiles' value in the last panorama/tiles (_tile_generation), None before any.
        self.tile_value: int | None = None
        self.last_query_ns: int | None = None
        self.R_enu_pano: np.ndarray | None = None
        self.prior_sum = np.zeros((3, 3))  # sum of the orientation samples of this panorama
        self.pano_orientation: dict[int, np.ndarray] = {}
        #: the latest orientation for the detector (R_enu_panorama sample, heading sigma), handed
        #: over only when it matches a tile: the detector projects every annotation with it
        #: (~0.5 ms), and on most of the 2 x 30 orientation messages per second nothing is queued
        self._orientation: tuple[np.ndarray, float] | None = None
        self.guard = StampGuard(reset_s)
        self.published = 0
        self._last_reason = ''

        self.pub_markers = self.advertise(MarkerArray, 'annotations/markers', LATCHED_QOS)
        self.pub_alignment = self.advertise(TransformStamped, 'annotations/alignment', RELIABLE_QOS)
        self.subscribe(Image, 'panorama/image', self.on_map, LATCHED_QOS, view=image_view)
        self.subscribe(Image, 'panorama/tiles', self.on_tiles, LATCHED_QOS, view=image_view)
        self.subscribe(NavSatFix, 'gps/fix', self.on_fix, SENSOR_QOS)
        self.subscribe(TransformStamped, 'orientation/panorama_in_world', self.on_panorama_in_world, RELIABLE_QOS,
                       view=transform_stamped_view)
        self.subscribe(Imu, 'orientation/global', self.on_global, RELIABLE_QOS, view=imu_view)
        self.subscribe(TransformStamped, 'panorama/orientation', self.on_panorama_orientation, RELIABLE_QOS,
                       view=transform_stamped_view)
        if not self.store_path:
            self.get_logger().warning('annotation_matcher: no store_path set; nothing to match (in a params '
                                      'file: annotation_matcher: {ros__parameters: {store_path: notes.db}})')
        self.get_logger().info(f'annotation_matcher: store {describe(self.store_ref) if self.store_ref else "-"}, prior {"on" if self.match_config.sensor_prior else "off"}, '
                               f'RANSAC {"on" if self.match_config.ransac else "off"}, budget {self.budget_ms} ms')

    # -- annotations -----------------------------------------------------------------------

    def on_fix(self, msg: NavSatFix) -> None:
        lat, lon = float(msg.latitude), float(msg.longitude)
        if msg.status.status < NavSatStatus.STATUS_FIX:
            self.warn_throttled('gps/fix: no fix (status NO_FIX), ignored')
            return
        if not (math.isfinite(lat) and math.isfinite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180):
            self.warn_throttled(f'gps/fix: invalid position ({lat}, {lon}), ignored')
            return
        t = stamp_ns(msg.header)
        if self.detector is not None or not self.store_ref or not self.store_backoff.ready(t * 1e-9):
            return
        if self.last_query_ns is not None and 0 <= t - self.last_query_ns < self.reload_period_ns:
            return
        self.last_query_ns = t
        cov = float(msg.position_covariance[0])
        poor = (msg.position_covariance_type == NavSatFix.COVARIANCE_TYPE_UNKNOWN or not math.isfinite(cov)
                or cov < 0 or math.sqrt(cov) > self.poor_gps_m)
        try:
            with open_store(self.store_ref, read_only=True) as store:
                found = store.all() if poor else store.near(lat, lon, self.radius_m)
                skipped = list(store.skipped)
                landmarks: list[Landmark] = []
                if found and self.use_landmarks:
                    landmarks = store.landmarks({a.panorama_id for a in found})
                    skipped += store.skipped
                self.panoramas = store.panoramas({a.panorama_id for a in found}) if found else {}
                skipped += store.skipped
        except StoreError as exc:  # down, wrong credentials, a query timed out: go on without, try again later
            wait = self.store_backoff.failed(t * 1e-9)
            self.get_logger().warning(f'annotation store: {exc}; no annotations for now, next try in {wait:g} s')
            return
        self.store_backoff.succeeded()
        for reason in skipped:
            self.warn_throttled(f'annotation store: {reason}, skipped')
        if not found:
            self.warn_throttled(f'no annotations within {self.radius_m:g} m of ({lat:.6f}, {lon:.6f})' if not poor
                                else 'GPS is poor and the annotation store is empty')
            return
        self.set_annotations(found, landmarks)
        self.get_logger().info(f'{len(found)} annotations and {len(landmarks)} landmarks of '
                               f'{len({a.panorama_id for a in found})} source panorama(s) loaded'
                               f'{" (GPS poor: all of them)" if poor else ""}')

    def set_annotations(self, annotations: list[Annotation], landmarks: list[Landmark] | None = None) -> None:
        """A new detector for these annotations and landmarks (None: keep the current ones);
        landmarks follow the annotations, so placement indices are annotation indices."""
        self.annotations = list(annotations)
        if landmarks is not None:
            pids = {a.panorama_id for a in self.annotations}
            self.landmarks = [lm for lm in landmarks if lm.panorama_id in pids]
        R_src = [quat_xyzw_to_matrix(np.asarray(a.panorama_in_world_quat_xyzw)) if a.has_world_orientation() else None
                 for a in self.annotations]
        R_pano = {a.panorama_id: R for a, R in zip(self.annotations, R_src) if R is not None}
        R_src += [R_pano.get(lm.panorama_id) for lm in self.landmarks]  # their panorama's orientation
        records: list[Annotation | Landmark] = [*self.annotations, *self.landmarks]
        sigma = [self.panoramas[r.panorama_id].heading_sigma_rad() if r.panorama_id in self.panoramas
                 else float('nan') for r in records]
        self.detector = ReDetector([r.patch for r in records], np.array([r.direction for r in records]),
                                   [r.panorama_id for r in records], self.match_config, self.geometry, R_src,
                                   landmark=[isinstance(r, Landmark) for r in records],
                                   source_heading_sigma_rad=sigma)
        self._orientation = None if self.R_enu_pano is None else (self.R_enu_pano, self.target_sigma)

    # -- map -------------------------------------------------------------------------------

    def on_map(self, msg: Image) -> None:
        t = stamp_ns(msg.header)
        verdict = self.guard.check(t)
        if verdict is StampVerdict.RESET:
            self.get_logger().warning('panorama/image: clock jumped back (new panorama?), matching starts over')
            self._reset_panorama()
        elif verdict is not StampVerdict.OK:
            self.warn_throttled(f'panorama/image: {verdict.value}, dropped')
            return
        try:
            arr = image_to_array(msg)
        except ConversionError as exc:
            self.warn_throttled(f'panorama/image: {exc}, dropped')
            return
        if arr.ndim == 3:
            arr = arr.mean(axis=2)
        if arr.shape != (self.geometry.height, self.geometry.width):
            self.warn_throttled(f'panorama/image: map is {arr.shape[1]}x{arr.shape[0]}, expected '
                                f'{self.geometry.width}x{self.geometry.height}; dropped')
            return
        scale = 255.0 / 65535.0 if arr.dtype == np.uint16 else 1.0
        self.mapped = arr > 0
        self.gray = arr.astype(np.float32) * np.float32(scale)
        self.map_stamp = t
        if self.pending_tiles is not None and self.pending_tiles[0] == t:
            self._queue_tiles(self.pending_tiles[1])
            self.pending_tiles = None
        self._work(t)

    def on_tiles(self, msg: Image) -> None:
        try:
            tiles = image_to_array(msg)
        except ConversionError as exc:
            self.warn_throttled(f'panorama/tiles: {exc}, dropped')
            return
        if tiles.ndim != 2 or self.geometry.width % max(tiles.shape[1], 1) or \
                self.geometry.width // tiles.shape[1] != self.geometry.height // max(tiles.shape[0], 1):
            self.warn_throttled(f'panorama/tiles: {tiles.shape} does not tile the map, dropped')
            return
        if self.match_config.tile_size != self.geometry.width // tiles.shape[1]:
            self.match_config = dataclasses.replace(self.match_config, tile_size=self.geometry.width // tiles.shape[1])
            if self.annotations:
                self.set_annotations(self.annotations)
        t = stamp_ns(msg.header)
        if self.map_stamp == t:
            self._queue_tiles(tiles)
            self._work(t)
        else:  # the map with this stamp has not arrived yet
            self.pending_tiles = (t, tiles)

    def _queue_tiles(self, tiles: np.ndarray) -> None:
        self.finished_tiles = tiles
        value = _tile_generation(tiles)
        if value is not None:
            if self.detector is not None and self.tile_value is not None and value != self.tile_value:
                # What was matched in the old tiles was matched in pixels that are no longer there.
                self.get_logger().info('panorama/tiles: the map was painted again (its camera\'s rolling shutter '
                                       'became known): matching starts over on its tiles')
                self.set_annotations(self.annotations)
            self.tile_value = value
        if self.detector is not None:
            self.detector.add_finished_tiles(tiles)

    def _reset_panorama(self) -> None:
        self.finished_tiles = None
        self.tile_value = None
        self.gray = self.mapped = None
        self.map_stamp = None
        self.pending_tiles = None
        self.R_enu_pano = None
        self.prior_sum = np.zeros((3, 3))
        self.pano_orientation.clear()
        if self.annotations:
            self.set_annotations(self.annotations)

    # -- prior -----------------------------------------------------------------------------

    def on_panorama_in_world(self, msg: TransformStamped) -> None:
        try:
            R = rotation_from_quaternion(msg.transform.rotation, 'orientation/panorama_in_world')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, dropped')
            return
        self._set_prior(R, stamp_ns(msg.header))

    def on_panorama_orientation(self, msg: TransformStamped) -> None:
        try:
            R = rotation_from_quaternion(msg.transform.rotation, 'panorama/orientation')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, dropped')
            return
        self.pano_orientation[stamp_ns(msg.header)] = R
        while len(self.pano_orientation) > 50:
            self.pano_orientation.pop(next(iter(self.pano_orientation)))

    def on_global(self, msg: Imu) -> None:
        if msg.orientation_covariance[0] == -1.0:
            return
        var = float(msg.orientation_covariance[8])  # heading (about ENU z), rad^2
        self.target_sigma = math.sqrt(var) if math.isfinite(var) and var >= 0 else float('nan')
        t = stamp_ns(msg.header)
        R_pano_cam = self.pano_orientation.get(t)
        if R_pano_cam is None:
            self._work(t)
            return
        try:
            R_enu_cam = rotation_from_quaternion(msg.orientation, 'orientation/global')
        except ConversionError as exc:
            self.warn_throttled(f'{exc}, dropped')
            return
        self._set_prior(R_enu_cam @ R_pano_cam.T, t)

    def _set_prior(self, R_enu_pano: np.ndarray, t: int) -> None:
        # The panorama's orientation in ENU is constant: every sample estimates it, and their
        # chordal mean averages the compass and accelerometer noise (the gravity-constrained
        # alignment relies on the tilt), each weighted by its inverse heading variance (from
        # orientation/global): the hybrid filter's estimate converges over the session, and an
        # equal-weight mean kept its first seconds' errors (development spots 371-504, matcher
        # replay: wrong label time 0.0144 equal weights, 0.0133 the latest sample, 0.0108 these).
        w = 1.0 / self.target_sigma ** 2 if math.isfinite(self.target_sigma) and self.target_sigma > 0 else 1.0
        self.prior_sum += w * R_enu_pano
        self.R_enu_pano = nearest_rotation(self.prior_sum)
        if self.detector is not None:
            self._orientation = (self.R_enu_pano, self.target_sigma)
        self._work(t)

    # -- work and outputs ------------------------------------------------------------------

    def _work(self, t: int) -> None:
        det = self.detector
        if det is None or self.gray is None or not det.queue:
            return
        if self._orientation is not None:  # what the detector would have had since the last sample
            det.set_orientation(*self._orientation)
            self._orientation = None
        det.step(self.gray, self.mapped, max(1, int(self.budget_ms / self.op_cost_ms)))
        if det.dirty:
            self._publish(t)  # stamped when the result is available (the frame that did the work)

    def _publish(self, t: int) -> None:
        assert self.detector is not None
        source, alignment = self.detector.result()
        stamp = to_stamp(t)
        out = MarkerArray()
        clear = Marker()
        clear.header.stamp = stamp
        clear.header.frame_id = self.frame_id
        clear.action = Marker.DELETEALL
        out.markers.append(clear)
        approx = not alignment.supported
        if approx and alignment.support_reason != self._last_reason:
            self._last_reason = alignment.support_reason
            self.get_logger().info(f'alignment not supported yet ({alignment.support_reason}): labels are approximate')
        sigma = self._approximate_sigma(source)
        for pl in alignment.placements:
            shaky = approx or not pl.supported
            if shaky and not self.show_approximate:
                continue
            a = self.annotations[pl.index]
            m = Marker()
            m.header.stamp = stamp
            m.header.frame_id = self.frame_id
            m.ns = 'approximate' if shaky else pl.status
            m.id = int(a.id if a.id is not None else pl.index)
            m.type = Marker.TEXT_VIEW_FACING
            m.action = Marker.ADD
            d = np.asarray(pl.direction, float) * self.marker_distance_m
            m.pose.position.x, m.pose.position.y, m.pose.position.z = (float(x) for x in d)
            m.pose.orientation.w = 1.0
            m.scale.z = self.marker_height_m
            m.color.a = 1.0
            if shaky:
                m.color.r = m.color.g = m.color.b = 0.6
                m.scale.x = 3.0 * sigma  # the 3-sigma direction uncertainty, rad
            elif pl.status == 'matched':
                m.color.g = 1.0
            else:
                m.color.r, m.color.g = 1.0, 0.55
            m.text = a.text
            out.markers.append(m)
        self.pub_markers.publish(out)
        self.published += 1
        if alignment.supported and alignment.R_target_source is not None and source is not None:
            tf = TransformStamped()
            tf.header.stamp = stamp
            tf.header.frame_id = self.frame_id
            tf.child_frame_id = source
            set_quaternion(tf.transform.rotation, alignment.R_target_source)
            self.pub_alignment.publish(tf)

    def _approximate_sigma(self, source: str | None) -> float:
        """1-sigma direction uncertainty of an approximate label, rad: both panoramas' heading
        sigmas when known, else the compass error the prior window assumes."""
        info = self.panoramas.get(source) if source is not None else None
        s = math.hypot(info.heading_sigma_rad() if info is not None else float('nan'), self.target_sigma)
        return s if math.isfinite(s) else self.match_config.prior_window_px / self.geometry.f


def main(args: list[str] | None = None) -> int:
    return run_node(AnnotationMatcherNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
