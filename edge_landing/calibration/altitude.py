"""In-flight depth scale from the height above ground (ARCHITECTURE.md §7).

The estimator runs on the drone, so it lives in :mod:`edge_landing.runtime.perception.scale` (which may not import this
package); it is re-exported here so that both scale sources are found under ``calibration``.
"""
from edge_landing.runtime.perception.scale import (
                                AltitudeScaleConfig,
                                AltitudeScaleEstimator,
                                FrameScale,
                                ScaleEstimate,
                                frame_scale,
                                ground_plane_depth,
)

__all__ = ["AltitudeScaleConfig", "AltitudeScaleEstimator", "FrameScale", "ScaleEstimate", "frame_scale",
           "ground_plane_depth"]
