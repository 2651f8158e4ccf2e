"""Square fiducial markers (Caarls et al. 2009, sec. 2.4): detection with OpenCV's ArUco /
AprilTag dictionaries, the seed's edge-model corner refinement, its lens model (eq. 2), and the
camera pose from all corners of all visible markers with a covariance."""

from ...errors import ArTrackingError


class MarkerError(ArTrackingError, ValueError):
    """Bad marker-map or detector configuration (one line for the user)."""
