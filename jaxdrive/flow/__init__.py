"""Pure flow math over noise levels: rectified flow, timestep sampling and shifts, MiLA's TPD and
JDC schedules, the condition patterns (where given frames and anchors sit), the losses of MiLA,
LongDWM and STAGE, and the jitted sampler.

Convention: ``x_sigma = (1 - sigma) x + sigma noise`` (sigma = 1 noise, 0 data), velocity
``v = noise - x``; sigma is ``[B]`` or per frame ``[B, F]``; arrays are ``[B, ..., F, h, w, C]``.
"""

from jaxdrive.flow.degrade import dct_lowpass, degrade_frames
from jaxdrive.flow.distill import (
    coarse_from_ends,
    coarse_from_segments,
    coarse_indices,
    dense_to_coarse,
    distill_loss,
    split_segments,
)
from jaxdrive.flow.jdc import jdc_alpha2, jdc_anchor_sigma, jdc_noise_var, jdc_renoise, jdc_training_anchors
from jaxdrive.flow.losses import flow_loss, high_pass, high_pass_mask, per_frame_flow_loss, structure_loss
from jaxdrive.flow.patterns import PATTERNS, check_patterns, draw_condition_masks, max_cond, pattern_masks
from jaxdrive.flow.rectified import (
    add_noise,
    data_from_velocity,
    euler_step,
    expand_per_frame,
    noise_from_velocity,
    noise_given_frames,
    skip_coefficients,
    velocity_from_data,
    velocity_from_noise,
    velocity_from_output,
    velocity_target,
    warp_path,
)
from jaxdrive.flow.sampler import sample
from jaxdrive.flow.schedule import frame_schedule, frame_sigmas
from jaxdrive.flow.timesteps import resolution_shift, sample_sigmas, sampling_sigmas, shift_sigmas
from jaxdrive.flow.tpd import tpd_frame_sigmas, tpd_level, tpd_sigmas
from jaxdrive.flow.weights import foreground_weight_map

__all__ = [
    "add_noise",
    "noise_given_frames",
    "skip_coefficients",
    "warp_path",
    "velocity_target",
    "data_from_velocity",
    "noise_from_velocity",
    "velocity_from_data",
    "velocity_from_noise",
    "velocity_from_output",
    "euler_step",
    "expand_per_frame",
    "sample_sigmas",
    "shift_sigmas",
    "resolution_shift",
    "sampling_sigmas",
    "tpd_level",
    "tpd_sigmas",
    "tpd_frame_sigmas",
    "jdc_alpha2",
    "jdc_noise_var",
    "jdc_renoise",
    "jdc_anchor_sigma",
    "jdc_training_anchors",
    "PATTERNS",
    "pattern_masks",
    "max_cond",
    "check_patterns",
    "draw_condition_masks",
    "frame_sigmas",
    "frame_schedule",
    "flow_loss",
    "per_frame_flow_loss",
    "high_pass",
    "high_pass_mask",
    "structure_loss",
    "coarse_indices",
    "dense_to_coarse",
    "split_segments",
    "coarse_from_segments",
    "coarse_from_ends",
    "distill_loss",
    "foreground_weight_map",
    "dct_lowpass",
    "degrade_frames",
    "sample",
]
