"""TrackDeform3D keypoint tracking as pure functions on numpy arrays (no zenoh, no files, no config classes).

Typical use by a worker (all arrays SI, world frame z up, camera frame OpenCV):

    params = TrackingParams()
    arm = render_arm_mask(arm_V, arm_F, K, T_world_cam, depth.shape, params.arm_margin_px, depth, params.arm_margin_m)
    seg = segment_by_difference(np.stack([d0, d2]), d1, K, T_world_cam, params, arm)     # initial frame
    tracker = Tracker(params, K, T_world_cam)
    ini, res = tracker.initialise(seg.points, tcp=tcp)
    background = update_background(background_from_depths(np.stack([d0, d2])), d1, params, arm)
    ...per frame:
    seg = segment_against_background(depth, background, K, T_world_cam, params, arm, tracker.keypoints)
    res = tracker.step(seg.points, tcp=tcp, gripper_closed=closed)   # res.status LOST -> initialise again
"""

# The names below are loaded on first use (PEP 562), so importing one submodule (tracking.params, which a CLI
# needs to start) does not load open3d, scikit-image and the rest.
import importlib
from typing import Any

_EXPORTS = {  # name -> the submodule that defines it (imported on first use: see __getattr__)
    "BOUNDARY": "tracking.anchors",
    "CORNER": "tracking.anchors",
    "JUNCTION": "tracking.anchors",
    "LEAF": "tracking.anchors",
    "detect_anchors_1d": "tracking.anchors",
    "detect_anchors_2d": "tracking.anchors",
    "ObjectClass": "tracking.classify",
    "classify_object": "tracking.classify",
    "depth_to_points": "tracking.geometry",
    "farthest_point_sampling": "tracking.geometry",
    "project_points": "tracking.geometry",
    "Initialisation": "tracking.init",
    "InitialisationError": "tracking.init",
    "Topology": "tracking.init",
    "initialise": "tracking.init",
    "anchor_error_mm": "tracking.metrics",
    "chamfer_mm": "tracking.metrics",
    "edge_rmse_mm": "tracking.metrics",
    "percent_below": "tracking.metrics",
    "sequence_summary": "tracking.metrics",
    "surface_error_mm": "tracking.metrics",
    "TrackingParams": "tracking.params",
    "Segmentation": "tracking.segmentation",
    "background_from_depths": "tracking.segmentation",
    "foreground_mask": "tracking.segmentation",
    "render_arm_depth": "tracking.segmentation",
    "render_arm_mask": "tracking.segmentation",
    "segment_against_background": "tracking.segmentation",
    "segment_by_difference": "tracking.segmentation",
    "update_background": "tracking.segmentation",
    "edge_colouring": "tracking.solver",
    "solve_keypoints": "tracking.solver",
    "FrameResult": "tracking.tracker",
    "FrameSolve": "tracking.tracker",
    "Tracker": "tracking.tracker",
    "TrackStatus": "tracking.tracker",
    "assign_grasp_indices": "tracking.tracker",
    "match_anchors": "tracking.tracker",
    "smooth_causal": "tracking.tracker",
    "smooth_symmetric": "tracking.tracker",
    "track_frame": "tracking.tracker",
    "update_grasp_indices": "tracking.tracker",
}


def __getattr__(name: str) -> Any:
    """``tracking.Tracker`` and the other re-exported names, imported from their submodule when first asked for."""
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'tracking' has no attribute {name!r}")


__all__ = sorted(_EXPORTS)
