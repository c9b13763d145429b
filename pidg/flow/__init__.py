"""Optical-flow supervision (LPFM): flow preprocessing, backward motion-flow decomposition, rendered Gaussian and
velocity flow, and the loss. See NOTES.md sections 6-8 and the module docstrings for conventions."""
from pidg.flow.config import FlowConfig
from pidg.flow.decomposition import (
    BackwardDecomposition,
    FlowTarget,
    decompose_backward_flow,
    depth_change_target,
    dilate_mask,
    motion_flow_target,
    motion_mask_from_flow,
    warp_to_first_frame,
)
from pidg.flow.gaussian_flow import (
    FLOW_CHANNELS,
    decode_depth_changes,
    decode_flows,
    deformation_matrix,
    flow_channel_count,
    flow_features,
    gaussian_flow_features,
    project_velocity_means,
)
from pidg.flow.lpfm import (
    LPFMResult,
    depth_from_render,
    end_point_error,
    flow_target_for_pair,
    lpfm_loss,
    sample_tiles,
)
from pidg.flow.optical_flow import (
    FlowEstimatorUnavailable,
    forward_backward_consistency,
    make_estimator,
)
from pidg.flow.model_flow import (
    flow_camera_t1,
    flow_channels,
    model_flow_target,
    render_pair_flows,
    rendered_depth,
    supervised_flow_channels,
)
from pidg.flow.preprocess import FlowCache, FlowPair, open_flow_cache, preprocess_flow, run_preprocess

__all__ = [
    "FLOW_CHANNELS",
    "BackwardDecomposition",
    "FlowCache",
    "FlowConfig",
    "FlowEstimatorUnavailable",
    "FlowPair",
    "FlowTarget",
    "LPFMResult",
    "decode_depth_changes",
    "decode_flows",
    "decompose_backward_flow",
    "deformation_matrix",
    "depth_change_target",
    "depth_from_render",
    "dilate_mask",
    "end_point_error",
    "flow_camera_t1",
    "flow_channels",
    "flow_channel_count",
    "flow_features",
    "flow_target_for_pair",
    "forward_backward_consistency",
    "gaussian_flow_features",
    "lpfm_loss",
    "make_estimator",
    "model_flow_target",
    "supervised_flow_channels",
    "motion_flow_target",
    "motion_mask_from_flow",
    "open_flow_cache",
    "preprocess_flow",
    "project_velocity_means",
    "render_pair_flows",
    "rendered_depth",
    "run_preprocess",
    "sample_tiles",
    "warp_to_first_frame",
]
