"""When the gear-assignment updates run (Sec 4.3: every L epochs until L' remain), which training views each
update uses, and the record of what the updates have done (kept in checkpoints)."""

from __future__ import annotations

from typing import Dict, List

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras
from torch import Tensor, nn

from gear_nerfstudio.errors import InputError
from gear_nerfstudio.gears.config import GearUpdateConfig


def update_interval(config: GearUpdateConfig) -> int:
    """Iterations between two updates: L epochs of ``iterations_per_epoch`` iterations."""
    return max(1, round(config.epochs_between_updates * config.iterations_per_epoch))


def planned_updates(config: GearUpdateConfig, first_step: int, last_step: int) -> List[int]:
    """Steps of a run from ``first_step`` to ``last_step`` at which an update is due (Sec 4.3): every L epochs,
    while at least L' epochs of training remain after it. The updates end earlier if the loss maps' mean
    variance falls below the threshold."""
    interval = update_interval(config)
    kept = config.epochs_after_updates * config.iterations_per_epoch
    start = -(-max(1, first_step) // interval) * interval
    return [step for step in range(start, last_step + 1, interval) if last_step - step >= kept]


def describe_plan(config: GearUpdateConfig, steps: List[int], cameras: Cameras, rays_per_batch: int) -> str:
    """The planned update steps, what an interval between them is for this data in passes over it, and where the
    upshift masks come from (``config.mask_source``, 'sam' or 'loss_threshold')."""
    pixels = float((cameras.width * cameras.height).sum())
    passes = update_interval(config) * rays_per_batch / pixels
    masks = "the SAM decoder on the loss maps' prompts" if config.mask_source == "sam" else "the RGB loss threshold"
    return (
        f"Gear updates (Sec 4.3) planned at steps {', '.join(map(str, steps))}: every {update_interval(config)} "
        f"iterations (L = {config.epochs_between_updates:g} epochs of {config.iterations_per_epoch}), while "
        f"L' = {config.epochs_after_updates:g} epochs remain; an interval is {passes:.3g} passes over the "
        f"{pixels / 1e6:.4g} M training pixels. They end early once the loss maps' mean variance is below "
        f"{config.variance_threshold:g}. Upshift masks from {masks}."
    )


class NoGearUpdates(InputError):
    """A training run with gear updates enabled would get none."""


def no_updates_error(config: GearUpdateConfig, first_step: int, last_step: int) -> NoGearUpdates:
    """The error for a run from ``first_step`` to ``last_step`` with no planned update, naming what fixes it."""
    return NoGearUpdates(
        f"Gear updates are on but none would run in steps {first_step}..{last_step}: they come every "
        f"{update_interval(config)} iterations while L' = {config.epochs_after_updates:g} epochs of "
        f"{config.iterations_per_epoch} iterations remain; raise --max-num-iterations, lower "
        "--pipeline.gear-updates.iterations-per-epoch (or .epochs-between-updates / "
        ".epochs-after-updates), or set --pipeline.gear-updates.enabled False."
    )


class GearUpdateState(nn.Module):
    """What the updates have done so far, as buffers, so that checkpoints keep it and a resumed run goes on: the
    counts, and the update waiting for its review (``GearUpdater.review``) with what it is judged against: its
    views, their PSNR and the held-out view's just before it, and the gear assignment to go back to.

    Args:
        assignment: the model's gear assignment (``gear_assignment``), for the shapes of the copy.
        views_per_update: training views of an update.
    """

    def __init__(self, assignment: Dict[str, Tensor], views_per_update: int) -> None:
        super().__init__()
        self.register_buffer("num_updates", torch.zeros((), dtype=torch.long))
        self.register_buffer("finished", torch.zeros((), dtype=torch.bool))
        self.register_buffer("num_undone", torch.zeros((), dtype=torch.long))
        self.register_buffer("review_update", torch.zeros((), dtype=torch.long))
        """The update waiting for its review (1-based), 0 for none."""
        self.register_buffer("review_step", torch.zeros((), dtype=torch.long))
        self.register_buffer("review_views", torch.full((views_per_update,), -1, dtype=torch.long))
        self.register_buffer("review_psnr", torch.zeros((), dtype=torch.float64))
        self.register_buffer("review_held_out_psnr", torch.zeros((), dtype=torch.float64))
        self.before = nn.Module()
        for key, value in assignment.items():
            self.before.register_buffer(key.replace(".", "__"), torch.zeros_like(value))

    def remember(
        self, update: int, due: int, views: List[int], psnr: float, held_out_psnr: float, assignment: Dict[str, Tensor]
    ) -> None:
        """Keep an update for its review at step ``due``."""
        self.review_update.fill_(update)
        self.review_step.fill_(due)
        self.review_views.fill_(-1)
        self.review_views[: len(views)] = torch.tensor(views, dtype=torch.long)
        self.review_psnr.fill_(psnr)
        self.review_held_out_psnr.fill_(held_out_psnr)
        for key, value in assignment.items():
            getattr(self.before, key.replace(".", "__")).copy_(value)

    def assignment_before(self) -> Dict[str, Tensor]:
        """The gear assignment just before the update under review."""
        return {key.replace("__", "."): value for key, value in self.before.named_buffers()}


def spread_views(frame_ids: np.ndarray, count: int, rng: np.random.Generator) -> List[int]:
    """Training images for one update: ``count`` frames evenly spread over the video (a random offset), each from
    a random camera. The gear function changes only at the times it is updated, so every update spreads its
    views over time, and successive updates (other offsets) cover the frames between."""
    frames = np.unique(frame_ids)
    count = min(count, len(frame_ids))
    positions = (rng.random() + np.arange(count)) * len(frames) / count
    chosen = frames[np.floor(positions).astype(int) % len(frames)]
    return [int(rng.choice(np.flatnonzero(frame_ids == frame))) for frame in chosen]
