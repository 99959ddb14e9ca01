"""Settings of the gear-assignment updates (Sec 4.3; the paper's values where it states them)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass
class GearUpdateConfig:
    """Schedule and settings of the gear-assignment updates (Sec 4.3; paper values where stated)."""

    enabled: bool = True
    """False: never update gears (ablation "no gear updates")."""
    iterations_per_epoch: int = 1500
    """What L and L' count: as in the paper's code, an epoch is a fixed number of iterations, not a pass over
    the data (there 4,000 iterations, 20 epochs per run). The same schedule then holds at every scene size.
    The presets take 1/20 of their default iterations."""
    epochs_between_updates: float = 3.0
    """L: epochs of radiance-field training between updates."""
    epochs_after_updates: float = 10.0
    """L': epochs of training kept after the last update."""
    views_per_update: int = 4
    """Training views (camera, time) rendered per update."""
    loss_map_size: int = 128
    """Loss maps are rendered with this longest side (or the image's, if smaller)."""
    patch_size: int = 8
    """Patch side in loss-map pixels."""
    top_k: int = 3
    """k highest-loss patches give positive prompts, k lowest negative ones."""
    sam_loss_weight: float = 0.01
    """lambda in L(r) = L_pho(r) + lambda L_SAM(r)."""
    variance_threshold: float = 1e-4
    """Updates stop once the mean variance of the loss maps is below this."""
    mask_source: Literal["auto", "sam", "loss_threshold"] = "auto"
    """Where the upshift masks come from. 'sam': the SAM decoder on the loss map's prompts (the paper);
    'loss_threshold': the RGB loss map above mean + k std (the paper's "w/o embedding" ablation); 'auto' (the
    default): 'sam' with a SAM backend (`sam-onnx`), 'loss_threshold' with the built-in stand-in, whose decoder's
    masks covered a median 17-27 % of the real captures' people where the loss threshold's, with S_static, put the
    people at gear >= 2 on both (benchmarks/results/tracking_real.md, issue 26)."""
    depth_cue: bool = False
    """mask_source 'sam': the decoder also gets the loss map's rendered depth at its cells (`Embedding.depth`, the
    built-in stand-in's depth cue; SAM ignores it), so that an upshift mask stops at the moving object's outline
    where its colours match the background's. Off by default: on both real captures (3 seeds each) it put more of
    the people at gear >= 2 but also more of the static scene, and tracking on the models it trained was no better
    (benchmarks/results/tracking_real.md, issue 26)."""
    loss_threshold_std: float = 2.0
    """k for mask_source 'loss_threshold'."""
    rays_per_set: int = 4096
    """Rays sampled inside (S_upshift) and outside (S_stay) the masks, per update."""
    stay_weight: float = 1.0
    """lambda_stay of Eq 10."""
    static_views: int = 8
    """Addition to Eq 10, S_static (0 turns it off): per update view, this many other training cameras at the view's
    frame (fewer when the rig has fewer), each giving as many rays as the view's S_stay through its still pixels
    (outside every moving patch of its motion gate), pulled to gear 1 in a weighted mean of their own. Eq 4 is a sum
    of products of planes, so an upshift lifts every point that shares a plane cell with the upshifted ones; S_stay
    holds only what the update's views see. It needs the 32 gear channels (`GearNeRFModelConfig.gear_feature_dim`)
    and upshift masks that cover the moving objects: the 31-camera capture kept under 90 % of its walls and floor
    at gear 1 at two of three seeds with the built-in stand-in's masks, at three of six with the loss threshold's
    (``mask_source`` 'auto') and ``static_weight`` 1, and at one of three with weight 3
    (benchmarks/results/tracking_real.md, issue 26). It needs the motion gate (``motion_threshold`` > 0) to tell
    still pixels, and is off without it."""
    static_weight: float = 3.0
    """Weight of S_static's mean in Eq 10. With 1, the 31-camera capture kept 84-85 % of its static scene at gear 1
    at two of three seeds; with 3 it kept 89-95 % and `panoptic` 94-95 %, while 55-79 % and 56-72 % of the people
    went to gear >= 2 and tracking moved by less than its spread over seeds (3 seeds each, paired with weight 1;
    benchmarks/results/tracking_real.md, issue 26)."""
    margin: float = 0.25
    """Points are pulled this far inside the interval of their target level."""
    max_steps: int = 100
    """Gradient steps on the gear function per update (Eq 11, repeated until the targets are met, at most
    this many). Measured on the mixed synthetic scene (two updates, all 57k weighted points): the weight
    share of points at their target level was 0.971 / 0.886 after 10 steps, 0.983 / 0.972 after 80
    and 0.986 / 0.978 after 300, so steps past 100 cost time for almost nothing."""
    max_points: int = 8192
    """Points per set (S_upshift, S_stay) in the Eq 11 steps; larger sets are drawn by weight (``select_points``),
    so that a step costs the same whatever the rays and samples per ray."""
    motion_threshold: float = 0.03
    """Mean absolute RGB change over time (patch average, in [0, 1]) for a patch to count as moving;
    0 turns the motion gate off (the paper's behaviour)."""
    guard_tolerance: float = 0.1
    """The guard: each update is reviewed L epochs later (``GearUpdater.review``); when its training views then
    render more than this many dB worse than just before it, it is undone and no further update runs."""
    measure_held_out: bool = True
    """Log the held-out camera's PSNR, at the times of each update's views, before it and at its review (measured
    only: the guard decides on training views)."""
    motion_frames: int = 8
    """Other frames of the same camera compared with the view's frame (spread over the video)."""
