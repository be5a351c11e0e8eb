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

from tracking.anchors import BOUNDARY, CORNER, JUNCTION, LEAF, detect_anchors_1d, detect_anchors_2d
from tracking.classify import ObjectClass, classify_object
from tracking.geometry import depth_to_points, farthest_point_sampling, project_points
from tracking.init import Initialisation, InitialisationError, Topology, initialise
from tracking.metrics import (
    anchor_error_mm,
    chamfer_mm,
    edge_rmse_mm,
    percent_below,
    sequence_summary,
    surface_error_mm,
)
from tracking.params import TrackingParams
from tracking.segmentation import (
    Segmentation,
    background_from_depths,
    foreground_mask,
    render_arm_depth,
    render_arm_mask,
    segment_against_background,
    segment_by_difference,
    update_background,
)
from tracking.solver import edge_colouring, solve_keypoints
from tracking.tracker import (
    FrameResult,
    Tracker,
    TrackStatus,
    assign_grasp_indices,
    match_anchors,
    smooth_causal,
    smooth_symmetric,
    track_frame,
    update_grasp_indices,
)

__all__ = [
    "BOUNDARY",
    "CORNER",
    "JUNCTION",
    "LEAF",
    "FrameResult",
    "Initialisation",
    "InitialisationError",
    "ObjectClass",
    "Segmentation",
    "Topology",
    "TrackStatus",
    "Tracker",
    "TrackingParams",
    "anchor_error_mm",
    "assign_grasp_indices",
    "background_from_depths",
    "chamfer_mm",
    "classify_object",
    "depth_to_points",
    "detect_anchors_1d",
    "detect_anchors_2d",
    "edge_colouring",
    "edge_rmse_mm",
    "farthest_point_sampling",
    "foreground_mask",
    "initialise",
    "match_anchors",
    "percent_below",
    "project_points",
    "render_arm_depth",
    "render_arm_mask",
    "segment_against_background",
    "segment_by_difference",
    "sequence_summary",
    "smooth_causal",
    "smooth_symmetric",
    "solve_keypoints",
    "surface_error_mm",
    "track_frame",
    "update_background",
    "update_grasp_indices",
]
