"""Cylindrical panoramic mapping and 3-DoF tracking with extended dynamic range (Langlotz 2011
sec. 3.1, 4.1). ``PanoramaMapper`` is the entry point; no ROS imports in this subpackage."""
from .cylinder import CylinderGeometry
from .exposure import ExposureConfig, ExposureFilter, OverlapExposureConfig, fit_overlap_exposure
from .map import MapConfig, PanoramaMap, seam_error
from .mapper import EDR_CORRECTIONS, FrameResult, MapperConfig, PanoramaError, PanoramaMapper
from .relocalise import Relocaliser, RelocaliserConfig
from .tracker import ActiveSearchTracker, TrackerConfig, TrackResult

__all__ = ['ActiveSearchTracker', 'CylinderGeometry', 'EDR_CORRECTIONS', 'ExposureConfig', 'ExposureFilter',
           'FrameResult', 'MapConfig', 'MapperConfig', 'OverlapExposureConfig', 'PanoramaError', 'PanoramaMap',
           'PanoramaMapper', 'Relocaliser', 'RelocaliserConfig', 'TrackResult', 'TrackerConfig', 'fit_overlap_exposure',
           'seam_error']
