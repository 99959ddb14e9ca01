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
    """Iterations in an epoch, the unit of L and L' (a fixed count, as the paper's code); presets: 1/20 of a run."""
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
    """Upshift masks: 'sam', the SAM decoder on the loss map's prompts (paper); 'loss_threshold', RGB loss above
    mean + k std; 'auto': 'loss_threshold' with sam-builtin, else 'sam'."""
    loss_threshold_std: float = 2.0
    """k for mask_source 'loss_threshold'."""
    rays_per_set: int = 4096
    """Rays sampled inside (S_upshift) and outside (S_stay) the masks, per update."""
    stay_weight: float = 1.0
    """lambda_stay of Eq 10."""
    static_views: int = 8
    """S_static (added to Eq 10): other training cameras per update view whose still pixels' rays go to gear 1;
    0: off."""
    static_weight: float = 3.0
    """Weight of S_static's mean in Eq 10."""
    margin: float = 0.25
    """Points are pulled this far inside the interval of their target level."""
    max_steps: int = 100
    """Most gradient steps of Eq 11 per update (repeated until the points reach their target levels)."""
    max_points: int = 8192
    """Points per set (S_upshift, S_stay) in the Eq 11 steps; larger sets are drawn by weight."""
    motion_threshold: float = 0.03
    """Mean absolute RGB change over time (patch mean, in [0, 1]) of a moving patch; 0: no motion gate (paper)."""
    guard_tolerance: float = 0.1
    """dB: an update whose training views render this much worse L epochs later is undone, and updates stop."""
    measure_held_out: bool = True
    """Log the held-out camera's PSNR at each update's times, before it and at its review (not used to decide)."""
    motion_frames: int = 8
    """Other frames of the same camera compared with the view's frame (spread over the video)."""
