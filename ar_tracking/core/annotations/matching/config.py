"""Parameters of the re-detection: tile matching, the sensor prior, the alignment, the
placement and its support (one flat dataclass: the nodes, the CLI and the benchmarks set them by
keyword, ``MatchConfig(sensor_prior=False)``, and read them as attributes)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class MatchConfig:
    """Parameters of tile matching, the sensor prior and the alignment (units: map pixels)."""

    tile_size: int = 64
    #: Low-sequency Walsh coefficients compared by the pre-check (of 15 non-DC).
    walsh_coefficients: int = 10
    #: Smallest Walsh correlation for NCC to be computed at a position.
    walsh_min: float = 0.5
    #: Smallest NCC of a candidate.
    min_ncc: float = 0.55
    #: Candidates kept per annotation (sec. 4.3: three).
    candidates: int = 3
    #: Candidates of one annotation closer than this are one candidate.
    min_separation_px: float = 8.0
    #: Windows with a smaller grey-level standard deviation (8-bit units) are not matched.
    min_window_std: float = 2.0
    #: Sensor prior (sec. 4.2) on/off; half-width of the inner window (compass error), pixels.
    sensor_prior: bool = True
    prior_window_px: float = 57.0
    #: The outer window is this many times the inner one.
    prior_outer_factor: float = 3.0
    #: Score penalty at the edge of the outer window (linear in the distance from the inner).
    prior_penalty: float = 0.3
    #: Global alignment (sec. 4.3) on/off and its thresholds.
    ransac: bool = True
    inlier_px: float = 10.0
    #: Annotations are placed at a candidate within this distance of where the rotation puts
    #: them (parallax between the two standing points shifts them by up to ~17 pixels); with
    #: no candidate there, at the rotated position (inferred).
    placement_px: float = 25.0
    #: NCC penalty of a candidate at the edge of the placement gate (0.2: a look-alike one
    #: facade repetition, ~15 px, further from the aligned position needs an NCC ~0.12 higher).
    placement_penalty: float = 0.2
    #: Choose among the valid hypotheses by the placement score instead of the lowest normalised
    #: error (paper), and refine the winner on all its placed matches (extension of sec. 4.3).
    consensus_score: bool = True
    refine_iterations: int = 3
    min_inlier_ratio: float = 0.5
    min_inliers: int = 3
    max_hypotheses: int = 4000
    #: Guided re-detection of inferred annotations near their aligned position (an extension
    #: of sec. 4.3): on/off, smallest NCC, penalty at the edge of the +-placement_px window.
    guided_search: bool = True
    guided_min_ncc: float = 0.7
    guided_penalty: float = 0.2
    #: Guided re-match of the matched annotations too (after the alignment): a position in the
    #: window that scores better than their candidate replaces it.
    guided_all: bool = True
    #: With the sensor prior, a RANSAC hypothesis must lie within ``prior_window_px`` (the
    #: compass error) of the rotation the two absolute orientations give, and with no valid
    #: hypothesis that prior rotation aligns the panoramas (an extension joining sec. 4.2 and
    #: 4.3: a rotation the compass rules out is a coincidence of look-alikes).
    prior_alignment: bool = True
    #: With ``prior_alignment`` and the browsing panorama's up direction: the alignment is the
    #: prior rotation followed by a heading correction about the vertical (1 DoF). Gravity from
    #: the accelerometers fixes the tilt of both panoramas far better than the compass fixes
    #: the heading (averaged over a panorama the tilt error is a small fraction of a degree), so
    #: parallax and look-alikes can no longer tilt the rotation; a candidate whose elevation
    #: differs from the prior's by more than ``inlier_px`` makes no hypothesis.
    gravity_alignment: bool = True
    #: With ``gravity_alignment`` the rotation predicts the elevation to about a pixel (parallax
    #: moves anchors sideways): a candidate further above or below than this is not a match.
    gravity_v_px: float = 4.0
    #: After a gravity-constrained alignment with at least ``parallax_min_matches`` matches:
    #: fit the heading residuals with the parallax of a horizontal displacement (one common
    #: depth, :mod:`.parallax`) and place again around the corrected positions. Sigmas in rad:
    #: a match (with the depth differences), the prior on |t| / d.
    parallax_model: bool = True
    #: The parallax model raises and lowers the anchors too (:attr:`..parallax.ParallaxModel.elevation`:
    #: the radial part of the same displacement). Matcher replay (with ``matched_agreement_px``):
    #: spots 505-588 wrong label time 0.0076 -> 0.0046, redetection 0.967 -> 0.970; spots
    #: 371-504 0.0016 -> 0.0029 (one early label of spot 444), redetection 0.954 both.
    parallax_elevation: bool = True
    parallax_min_matches: int = 3
    parallax_sigma_match: float = 0.01
    parallax_sigma: float = 0.02
    #: One refit of the model without the matches beyond this many robust standard deviations
    #: of its residuals (landmarks far nearer than the anchors); 0: plain least squares.
    parallax_trim_sigmas: float = 3.0
    #: The annotations' parallax as a factor of the model's (:func:`.parallax.fit_depth_scale`),
    #: fitted on the matched annotations (leave-one-out for each of them), pulled to 1 with this
    #: sigma; 0: one common depth. The model is fitted mostly on landmarks, nearer on the whole
    #: than the facades the annotations are on (trees, poles, corners).
    parallax_scale_sigma: float = 0.3
    #: After the parallax model, matches must lie within this many robust standard deviations
    #: of the model's leave-one-out residuals of the matches (horizontal; between inlier_px and
    #: placement_px): fitted on tens of landmark matches the model predicts to a pixel or two,
    #: and a look-alike a facade repetition away no longer passes. 0: keep placement_px.
    parallax_gate_sigmas: float = 3.0
    #: An alignment is *supported* (its labels may be shown as placed) with at least this many
    #: matched annotations and landmarks, and, when both panoramas' orientations come with a
    #: heading covariance, with its rotation within ``support_prior_sigmas`` combined standard
    #: deviations (plus one inlier tolerance) of the prior rotation - or with at least
    #: ``strong_support_matches`` matches, which outvote a prior that is off. Unsupported
    #: placements are only approximate (see :attr:`Alignment.supported`).
    min_support_matches: int = 4
    support_prior_sigmas: float = 3.0
    strong_support_matches: int = 10
    #: An inferred placement (no match of its own) is supported only with at least
    #: ``local_support_matches`` matched annotations/landmarks within ``local_support_px`` columns
    #: of it: early on, with the matches all in the first finished tiles, the heading and the
    #: parallax fitted there are extrapolated to the far side of the panorama (1-3 deg off on the
    #: sample bag for the first seconds). The local tests apply to source panoramas with
    #: landmarks only (a handful of annotations alone is too sparse for them). 1 (was 2) since the
    #: annotations' own depth ratio (``parallax_scale_sigma``) keeps inferred labels within 1 deg
    #: (docs/annotations.md, "Session 11, later").
    local_support_matches: int = 1
    local_support_px: float = 171.0
    #: Matched labels too need ``local_support_matches`` other matches within ``local_support_px``
    #: (an isolated look-alike is then only approximate).
    local_support_matched: bool = True
    #: An inferred placement with fewer local matches is supported too when it is bracketed:
    #: a match on either side of it within ``bracket_support_px`` columns (0: off). Between
    #: matches the heading and the parallax are interpolated, not extrapolated as they are on the
    #: far side of the first finished tiles; late in a sweep a facade whose own anchor and
    #: supports do not match under the changed lighting lies between matched ones. 512 px = 90
    #: deg: the heading and the sinusoid of the parallax model are then pinned on both sides.
    bracket_support_px: float = 512.0
    #: An inferred annotation's placement carries the parallax model's term there times the
    #: annotations' depth ratio (``parallax_scale_sigma``), which a handful of matched annotations
    #: pin only loosely, and its own facade's depth differs from that common ratio by
    #: ``depth_ratio_scatter`` (1 sigma) whatever the matches. It is supported only while the two
    #: move it by at most ``depth_ratio_support_rad`` (1 sigma; 0: off), whatever the local
    #: matches: a label on the far side of the model's sinusoid is otherwise shown a degree off.
    #: 0.55 deg and 0.2 chosen on the matcher replay of development spots 371-504.
    depth_ratio_support_rad: float = 0.0096  # 0.55 deg
    depth_ratio_scatter: float = 0.2
    #: The same limit also counts the parallax model's own uncertainty at the label
    #: (:func:`.parallax.prediction_sigma`: the posterior of its heading and sinusoid, with the
    #: matches' residual scale): matches bunched in one sector pin it there only, and a label
    #: bracketed by matches 60 deg away is extrapolated more than the bracket rule assumes.
    #: Matcher replay of spots 371-504: wrong label time 0.0072 -> 0.0036, redetection 0.970 -> 0.960.
    prediction_support: bool = True
    #: A matched annotation is shown as placed only within ``matched_agreement_px`` (map
    #: distance; 0: off) of where the alignment puts it (:attr:`.placement.Placement.predicted`:
    #: the other matches with the parallax model, leave-one-out). Further apart, the patch and
    #: the other matches disagree by more than the 1 deg a label may be off, so one of them is:
    #: on spots 505-588 such labels were look-alikes one facade repetition away (2.3-2.9 deg
    #: off) in a quarter of their time (replay of 505-588: wrong label time 0.0097 -> 0.0076,
    #: redetection 0.970 -> 0.967). 6.8 px = 1.2 deg. A local test: with landmarks only.
    matched_agreement_px: float = 6.8
    #: Look-alike test of a matched annotation after the parallax model (0: off): when another
    #: local NCC maximum at least ``lookalike_sep_px`` from its match, inside the placement gate
    #: around its leave-one-out prediction, has an NCC within ``lookalike_margin`` of the
    #: match's, NCC cannot tell which is the anchor (a sign whose letters repeat, a facade
    #: repetition under changed lighting: the true position often matches worse). The
    #: annotation is then placed at the prediction, as inferred (fitted on the other matches,
    #: it is within a pixel or two where they surround it, and the local support rule decides
    #: whether it is shown). ``lookalike_sep_px`` ~ 1 deg: a runner-up closer than that does not
    #: make the label wrong. A match within ``matched_agreement_px`` of its prediction is kept
    #: whatever its rivals (session 13: the prediction carries the label's unknown depth, and a
    #: correct window match 1.2 deg from it was replaced by it on spot 627; replay of spots
    #: 589-644 wrong label time 0.0171 -> 0.0145, redetection 0.954 -> 0.958, and no change on
    #: the look-alikes of 341-354 the test was made for).
    lookalike_margin: float = 0.1
    lookalike_sep_px: float = 6.0
    seed: int = 0
