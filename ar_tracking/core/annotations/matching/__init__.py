"""Re-detection of annotations in a new panorama map (Langlotz 2011 sec. 3.2, 4.2, 4.3).

* :class:`TileMatcher` (sec. 3.2): the patches of the annotations are matched against one
  finished tile of the map at a time, each tile once. A Walsh-transform pre-check comes first:
  the low-sequency Walsh-Hadamard coefficients of the patch (4 x 4 blocks of block means, DC
  dropped, normalised, which makes them invariant to gain and offset) are compared with those
  of every patch position of the tile, for all annotations in one matrix product; only positions
  and annotations that pass ``walsh_min`` get normalised cross-correlation (NCC). The three best
  candidates per annotation are kept (:class:`CandidateList`).
* Sensor prior (sec. 4.2): with the expected map position of an annotation from the absolute
  orientation, the search is limited to a window of +-``prior_window_px`` (the compass error:
  10 deg = 57 px) around it, and a window three times larger is searched with the NCC score
  penalised by the distance from the inner window, so matches outside the inner window count
  only when they are very good.
* :func:`ransac_alignment` (sec. 4.3, Fig. 5): RANSAC over pairs of annotations and one of
  their candidates; each hypothesis is the rotation that best aligns the two pairs of unit
  vectors (absolute orientation, :func:`absolute_orientation`); annotations whose mapped
  position is within ``inlier_px`` (10 map pixels) of one of their candidates are inliers; a
  hypothesis needs more than 50 % inliers and (paper) the lowest normalised error (error /
  inliers) wins; it is refined on all its inliers. The winning rotation places every
  annotation (:func:`place_annotations`): at a candidate within ``placement_px`` of where the
  rotation puts it (matched) or, with none, at that position (inferred).
* Extensions of ours, because the two standing points differ by up to 2 m (sec. 6.1): anchors
  30-40 m away then move by up to 2-3 deg (12-17 px) of parallax that no rotation absorbs,
  while the doors and windows of the facades repeat every 15-20 px. Each is switchable:

  - placement gate and score: ``placement_px`` (25 px) is looser than the inlier gate, and
    the candidate placed is the one with the best NCC minus ``placement_penalty`` (0.2) x
    distance / ``placement_px`` (a look-alike one repetition further off needs an NCC ~0.12
    higher); ``placement_px = inlier_px``, ``placement_penalty = 0`` switch them off;
  - ``consensus_score``: among the valid hypotheses, the one with the highest placement score
    (the sum of those penalised NCCs, :meth:`_CandidateArrays.placement_score`) wins instead
    of the lowest normalised error, which prefers a rotation that lines up look-alikes one
    repetition away with near anchors' parallax over the true one; the winner is refined by
    least squares on all its placed matches (``refine_iterations``) while its score grows;
  - ``guided_search``: an inferred annotation is searched once more with NCC in a
    +-``placement_px`` window around its aligned position, which recovers true matches that
    were not among the three best candidates; with ``guided_all`` every matched annotation
    too, the window's best penalised NCC replacing its candidate when it scores better;
  - ``gravity_alignment`` (with the sensor prior): the accelerometers fix the tilt of both
    panoramas, so the alignment is the prior rotation turned about the vertical only (one
    degree of freedom, hypotheses from single matches and pairs), and a match must lie within
    ``gravity_v_px`` of the predicted elevation;
  - ``parallax_model``: the heading residuals of the matches are fitted with the parallax of a
    displaced standing point (:mod:`.parallax`; one trimmed refit, ``parallax_trim_sigmas``),
    each match judged against the fit of the others, and the annotations are placed again
    around the corrected positions, within a gate of ``parallax_gate_sigmas`` robust standard
    deviations of those leave-one-out residuals;
  - landmarks (:mod:`.landmarks`): distinctive patches of the source panorama stored with its
    annotations, matched and aligned like them but never placed for the user, so the rotation
    and the parallax are fitted on tens of matches instead of a handful.
* :class:`ReDetector` ties them together with the work queue of sec. 3.2 (finished tiles are
  queued and processed under a budget per frame) and the choice between several source
  panoramas near one GPS fix (sec. 6.1: the one whose annotations score best).

Map coordinates are those of :mod:`ar_tracking.core.panorama.cylinder` (u right, wrapping at
W; v down). A patch of side P with top-left pixel (x, y) has its centre at (x + (P-1)/2,
y + (P-1)/2).

The package: :mod:`.config` (:class:`MatchConfig`), :mod:`.tiles` (Walsh + NCC), :mod:`.alignment`
(hypotheses -> score -> select -> refine), :mod:`.placement`, :mod:`.redetector` (queue, budget,
guided search, support). The public names (and the two private ones the tests check) are
re-exported here.
"""
from .config import MatchConfig
from .tiles import Candidate, CandidateList, TileMatcher, patch_walsh
from .tiles import _walsh_basis as _walsh_basis  # the tests check the basis
from .placement import Alignment, Placement, best_candidate_placements, place_annotations
from .alignment import absolute_orientation, ransac_alignment
from .alignment import _frames as _frames  # the tests check the two-pair frames
from .redetector import ReDetector, expected_positions

__all__ = ['Alignment', 'Candidate', 'CandidateList', 'MatchConfig', 'Placement', 'ReDetector', 'TileMatcher',
           'absolute_orientation', 'best_candidate_placements', 'expected_positions', 'patch_walsh',
           'place_annotations', 'ransac_alignment']
