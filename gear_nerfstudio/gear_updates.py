"""Gear-assignment updates (Gear-NeRF Sec 4.3, Eq 10-11) as a nerfstudio training callback.

Every L epochs: render a few training views (RGB and SAM features), compute the rendering loss map
L(r) = L_pho(r) + lambda L_SAM(r), patchify it, take the centres of the top-k highest / lowest patches
as positive / negative prompts, decode the upshift mask from the ground-truth frame's SAM embedding,
then push the gear function g towards p + 1 on points of rays inside the mask and towards p outside
(Eq 10). Updates stop once the mean variance of the loss maps falls below a threshold, or when fewer
than L' epochs of training remain.

Changes from the paper, to keep p = ceil(g) (Eq 5) away from its jumps and the update local:
- Eq 10 pulls g towards the number p + 1 (or p), exactly where ceil jumps (g slightly above 2 is
  already gear 3). Here each point is pulled into the interval of its target level q, shrunk by a
  margin, [q - 1 + margin, q - margin] (open-ended below for gear 1 and above for the top gear): a
  squared hinge, zero for points already there, so settled points do not move the planes;
- points along a ray count with their volume-rendering weights, so the update acts on the surfaces
  the pixel sees rather than on the empty space in front of them;
- Eq 11's single gradient step is repeated (at most `max_steps`) until the sampled points reach their
  target levels, since one small step rarely moves g across a level boundary.

Addition to the paper, the motion gate (`motion_threshold`; 0 gives the paper's behaviour): the rigs are
fixed, so a surface that moves changes the ground-truth pixels of its camera over time. A patch counts
as moving when its mean absolute RGB change to other frames of the same camera reaches the threshold;
only moving patches give positive prompts, and the upshift mask is cut to moving patches. High loss on
static texture (fine detail not yet fitted) thus never upshifts, and neither does a static scene: gear 1
already models everything that does not change in time, and higher gears there would only cost time.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Dict, List, Literal, Optional, Tuple

import numpy as np
import torch
import torch.nn.functional as F
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.model_components.ray_samplers import UniformSampler
from nerfstudio.utils import colormaps
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor, nn

from gear_nerfstudio.gear_field import gear_level
from gear_nerfstudio.sam.interface import sample_features

if TYPE_CHECKING:
    from gear_nerfstudio.gear_model import GearNeRFModel


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
    mask_source: Literal["sam", "loss_threshold"] = "sam"
    """'sam': SAM decoder on prompts; 'loss_threshold': RGB loss map above mean + k std (the paper's
    "w/o embedding" ablation)."""
    loss_threshold_std: float = 2.0
    """k for mask_source 'loss_threshold'."""
    rays_per_set: int = 4096
    """Rays sampled inside (S_upshift) and outside (S_stay) the masks, per update."""
    stay_weight: float = 1.0
    """lambda_stay of Eq 10."""
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
    motion_frames: int = 8
    """Other frames of the same camera compared with the view's frame (spread over the video)."""


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
    """The planned update steps, and what an interval between them is for this data in passes over it."""
    pixels = float((cameras.width * cameras.height).sum())
    passes = update_interval(config) * rays_per_batch / pixels
    return (
        f"Gear updates (Sec 4.3) planned at steps {', '.join(map(str, steps))}: every {update_interval(config)} "
        f"iterations (L = {config.epochs_between_updates:g} epochs of {config.iterations_per_epoch}), while "
        f"L' = {config.epochs_after_updates:g} epochs remain; an interval is {passes:.3g} passes over the "
        f"{pixels / 1e6:.4g} M training pixels. They end early once the loss maps' mean variance is below "
        f"{config.variance_threshold:g}."
    )


class NoGearUpdates(ValueError):
    """A training run with gear updates enabled would get none."""


class GearUpdateState(nn.Module):
    """What the updates have done so far, as buffers, so that checkpoints keep it and a resumed run goes on."""

    def __init__(self) -> None:
        super().__init__()
        self.register_buffer("num_updates", torch.zeros((), dtype=torch.long))
        self.register_buffer("finished", torch.zeros((), dtype=torch.bool))


def patch_size_for(shape: Tuple[int, int], patch_size: int) -> int:
    """Patch side used on a loss map of this (h, w): at most the map's shorter side."""
    return max(1, min(patch_size, *shape))


def patch_means(values: Tensor, size: int) -> Tensor:
    """Average of a (h, w) map over size x size patches (the last row / column may be partial)."""
    return F.avg_pool2d(values[None, None], size, stride=size, ceil_mode=True)[0, 0]


def patch_prompts(
    loss_map: Tensor, patch_size: int, top_k: int, moving: Optional[Tensor] = None
) -> Tuple[Tensor, Tensor]:
    """Centres (x, y) of the top-k highest (label 1) and lowest (label 0) average-loss patches.

    moving: (rows, cols) bool per patch; only moving patches can give positive prompts (fewer than k
    positives, or none, when fewer patches move).
    """
    height, width = loss_map.shape
    size = patch_size_for((height, width), patch_size)
    pooled = patch_means(loss_map, size)
    k = min(top_k, pooled.numel() // 2)
    flat = pooled.flatten()
    candidates = flat if moving is None else torch.where(moving.flatten(), flat, -torch.inf)
    num_high = min(k, int(torch.isfinite(candidates).sum()))
    high = torch.topk(candidates, num_high).indices
    low = torch.topk(-flat, k).indices
    index = torch.cat([high, low])
    rows, cols = index // pooled.shape[1], index % pooled.shape[1]
    centres_x = torch.clamp((cols.float() + 0.5) * size, max=width - 0.5)
    centres_y = torch.clamp((rows.float() + 0.5) * size, max=height - 0.5)
    labels = torch.cat([torch.ones(num_high), torch.zeros(k)])
    return torch.stack([centres_x, centres_y], dim=-1), labels


def moving_patches(change: Tensor, patch_size: int, threshold: float) -> Tensor:
    """Patches (rows, cols) whose mean over-time change of the ground truth reaches the threshold."""
    return patch_means(change, patch_size_for(tuple(change.shape), patch_size)) >= threshold


def patches_to_pixels(patches: Tensor, shape: Tuple[int, int], patch_size: int) -> Tensor:
    """Per-patch booleans (rows, cols) spread to the pixels (h, w) of the map they were pooled from."""
    size = patch_size_for(shape, patch_size)
    pixels = patches.repeat_interleave(size, dim=0).repeat_interleave(size, dim=1)
    return pixels[: shape[0], : shape[1]]


def spread_views(frame_ids: np.ndarray, count: int, rng: np.random.Generator) -> List[int]:
    """Training images for one update: ``count`` frames evenly spread over the video (a random offset), each from
    a random camera. The gear function changes only at the times it is updated, so every update spreads its
    views over time, and successive updates (other offsets) cover the frames between."""
    frames = np.unique(frame_ids)
    count = min(count, len(frame_ids))
    positions = (rng.random() + np.arange(count)) * len(frames) / count
    chosen = frames[np.floor(positions).astype(int) % len(frames)]
    return [int(rng.choice(np.flatnonzero(frame_ids == frame))) for frame in chosen]


def stay_focus(mask: Tensor, moving_pixels: Tensor, patch_size: int) -> Tensor:
    """Pixels of S_stay at risk of moving up with the upshift mask (h, w): outside it, but within one patch of it,
    or in a moving patch (where the object is at other times). The gear function is smooth in space and time,
    so these are where an upshift spills over."""
    near = F.max_pool2d(mask[None, None].float(), 2 * patch_size + 1, stride=1, padding=patch_size)[0, 0] > 0
    return (near | moving_pixels) & ~mask


def level_targets(levels: Tensor, upshift: Tensor, num_gears: int, still: Optional[Tensor] = None) -> Tensor:
    """Target levels of Eq 10: p + 1 for S_upshift (never above N_gear), p for S_stay, and 1 for the points of
    S_stay in ``still`` (motion gate: pixels whose ground truth does not change around the view's time)."""
    stay = levels if still is None else torch.where(still, torch.ones_like(levels), levels)
    return torch.where(upshift, (levels + 1).clamp(max=num_gears), stay)


def upshift_loss(
    g: Tensor, targets: Tensor, weights: Tensor, upshift: Tensor, stay_weight: float, num_gears: int, margin: float
) -> Tensor:
    """Eq 10 as a weighted squared hinge: the distance of g from the interval of its target level q,
    [q - 1 + margin, q - margin] (no lower bound for q = 1, no upper bound for q = N_gear)."""
    low = torch.where(targets > 1, targets - 1 + margin, torch.full_like(g, -torch.inf))
    high = torch.where(targets < num_gears, targets - margin, torch.full_like(g, torch.inf))
    error = (torch.relu(low - g) + torch.relu(g - high)).square() * weights
    up = error[upshift].sum() / weights[upshift].sum().clamp(min=1e-12)
    stay = error[~upshift].sum() / weights[~upshift].sum().clamp(min=1e-12)
    return up + stay_weight * stay


def select_points(
    weights: Tensor, upshift: Tensor, max_points: int, generator: torch.Generator
) -> Tuple[Tensor, Tensor]:
    """The points of S_upshift and S_stay that take part in the Eq 11 steps, and their weights.

    Only points whose weight is at least 1e-3 of the largest count: the others (most samples of a ray, in the
    empty space before and behind the surface it sees) add almost nothing to Eq 10. A set with more than
    ``max_points`` such points is replaced by ``max_points`` draws with probability proportional to weight, each
    of weight 1: Eq 10 normalises each set by its total weight, so the expected loss is the same, and the cost
    of a step no longer grows with the number of rays and samples.
    """
    counted = weights >= 1e-3 * weights.max().clamp(min=1e-12)
    indices, selected = [], []
    for in_set in (upshift, ~upshift):
        members = torch.nonzero(counted & in_set)[:, 0]
        if len(members) > max_points:
            draws = torch.multinomial(weights[members], max_points, replacement=True, generator=generator)
            indices.append(members[draws])
            selected.append(torch.ones(max_points, device=weights.device))
        else:
            indices.append(members)
            selected.append(weights[members])
    return torch.cat(indices), torch.cat(selected)


def shift_gears(
    field,
    optimizer: torch.optim.Optimizer,
    points: Tensor,
    times: Tensor,
    weights: Tensor,
    upshift: Tensor,
    targets: Tensor,
    stay_weight: float,
    margin: float,
    max_steps: int,
) -> int:
    """Eq 11 steps of `optimizer` (on the gear function only) until the points sit at their target levels, at
    most max_steps; returns the number of steps taken."""
    steps = 0
    while steps < max_steps:
        optimizer.zero_grad(set_to_none=True)
        g = field.gear_values(points, times)
        if bool((gear_level(g.detach(), field.num_gears) == targets).all()):
            break
        upshift_loss(g, targets, weights, upshift, stay_weight, field.num_gears, margin).backward()
        optimizer.step()
        steps += 1
    optimizer.zero_grad(set_to_none=True)
    return steps


def resized_image(dataset: InputDataset, image_index: int, size: Tuple[int, int]) -> Tensor:
    """Image ``image_index`` of a dataset as RGB (h, w, 3), area-resampled to size (h, w)."""
    image = dataset.get_image_float32(image_index)[..., :3].permute(2, 0, 1)[None]
    return F.interpolate(image, size=size, mode="area")[0].permute(1, 2, 0)


def frame_change(
    dataset: InputDataset, image_index: int, size: Tuple[int, int], num_frames: int, window: Optional[int] = None
) -> Tensor:
    """Motion gate: per pixel at size (h, w), the largest mean absolute RGB difference between an image and up to
    ``num_frames`` other frames of the same camera, spread over the video or, with ``window``, over the frames at
    most ``window`` frames away (0 with none). Uses the dataparser's ``camera_ids`` and ``frame_ids`` metadata."""
    cameras, frames = dataset.metadata["camera_ids"], dataset.metadata["frame_ids"]
    near = torch.ones_like(frames, dtype=torch.bool) if window is None else (frames - frames[image_index]).abs() <= window
    others = torch.nonzero((cameras == cameras[image_index]) & (frames != frames[image_index]) & near)[:, 0]
    change = torch.zeros(size)
    if len(others) == 0:
        return change
    rgb = resized_image(dataset, image_index, size)
    picks = np.unique(np.linspace(0, len(others) - 1, min(num_frames, len(others))).round())
    for index in others[torch.from_numpy(picks.astype(np.int64))].tolist():
        change = torch.maximum(change, (rgb - resized_image(dataset, int(index), size)).abs().mean(-1))
    return change


@dataclass
class LossMap:
    """One rendered training view at loss-map resolution."""

    image_index: int
    camera: Cameras
    rgb: Tensor  # (h, w, 3) ground truth
    loss: Tensor  # (h, w) L(r)
    rgb_loss: Tensor  # (h, w) L_pho(r)
    surface: Tensor  # (h * w, 3) points at the rendered depth of each pixel
    change: Tensor  # (h, w) ground-truth change over the video (motion gate)
    local_change: Tensor  # (h, w) ground-truth change to the previous and next frames


class GearUpdater:
    """Runs the updates; called after every training iteration.

    Args:
        config: schedule and settings.
        model: the Gear-NeRF model (field, collider, base sample count, SAM head).
        datamanager: training images, their SAM embeddings and the SAM backend.
        optimizer: the optimizer of the gear function (Eq 11).
        state: the model's record of the updates (restored from a checkpoint on resume).
        first_step: first step of this run (0, or the step after the checkpoint).
        last_step: last step of this run.
        seed: the run's seed; the views of update u are drawn with (seed, u).
    """

    def __init__(
        self,
        config: GearUpdateConfig,
        model: "GearNeRFModel",
        datamanager,
        optimizer,
        state: GearUpdateState,
        first_step: int,
        last_step: int,
        seed: int = 0,
    ):
        self.config = config
        self.model = model
        self.datamanager = datamanager
        self.optimizer = optimizer
        self.state = state
        self.last_step = last_step
        self.seed = seed
        self.interval = update_interval(config)
        if config.mask_source == "sam" and getattr(datamanager, "feature_cache", None) is None:
            raise ValueError("gear updates with mask_source 'sam' need SAM features: enable them in the datamanager")
        self.planned = planned_updates(config, first_step, last_step)
        if bool(state.finished):
            CONSOLE.log(f"Gear updates: finished before step {first_step} ({int(state.num_updates)} updates).")
        elif self.planned:
            rays_per_batch = datamanager.config.train_num_rays_per_batch
            CONSOLE.log(describe_plan(config, self.planned, datamanager.train_dataset.cameras, rays_per_batch))
        elif int(state.num_updates) == 0:
            raise NoGearUpdates(
                f"Gear updates are on but none would run in steps {first_step}..{last_step}: they come every "
                f"{self.interval} iterations while L' = {config.epochs_after_updates:g} epochs of "
                f"{config.iterations_per_epoch} iterations remain; raise --max-num-iterations, lower "
                "--pipeline.model.gear-updates.iterations-per-epoch (or .epochs-between-updates / "
                ".epochs-after-updates), or set --pipeline.model.gear-updates.enabled False."
            )

    def __call__(self, step: int) -> None:
        if bool(self.state.finished) or step == 0 or step % self.interval:
            return
        if self.last_step - step < self.config.epochs_after_updates * self.config.iterations_per_epoch:
            self.state.finished.fill_(True)
            CONSOLE.log(f"Gear updates end at step {step}: L' epochs of training remain.")
            return
        self.update(step)

    def update(self, step: int) -> Dict[str, float]:
        """One gear-assignment update; returns the logged statistics."""
        from nerfstudio.utils import writer  # imported here: importing it before nerfstudio's configs is circular

        config = self.config
        self.rng = np.random.default_rng([self.seed, int(self.state.num_updates)])
        frame_ids = self.datamanager.train_dataset.metadata["frame_ids"].numpy()
        maps = [self.loss_map(index) for index in spread_views(frame_ids, config.views_per_update, self.rng)]
        variance = float(np.mean([float(m.loss.var()) for m in maps]))
        stats = {"loss_map_variance": variance}
        if variance < config.variance_threshold:
            self.state.finished.fill_(True)
            CONSOLE.log(f"Gear updates end at step {step}: loss-map variance {variance:.3g} is below the threshold.")
            writer.put_dict("gear_update", stats, step)
            return stats

        shifts = [self.upshift_mask(m) for m in maps]
        masks = [mask for mask, _, _ in shifts]
        points, times, weights, upshift, still = self.sample_points(maps, masks)
        generator = torch.Generator(weights.device).manual_seed(int(self.rng.integers(2**31)))
        index, weights = select_points(weights, upshift, config.max_points, generator)
        points, times, upshift, still = points[index], times[index], upshift[index], still[index]
        with torch.no_grad():
            levels = self.model.field.gear_levels(points, times)
        targets = level_targets(levels, upshift, self.model.config.num_gears, still)
        steps = shift_gears(
            self.model.field, self.optimizer, points, times, weights, upshift, targets, self.config.stay_weight,
            self.config.margin, self.config.max_steps,
        )
        with torch.no_grad():
            new_levels = self.model.field.gear_levels(points, times)
        self.state.num_updates += 1

        stats.update(
            {
                "upshift_mask_area": float(np.mean([float(mask.float().mean()) for mask in masks])),
                "steps": float(steps),
                "downshifted_fraction": float((new_levels < levels).float().mean()),
            }
        )
        histogram = self.visible_gear_histogram(maps)
        stats.update({f"gear_{g + 1}_fraction": float(f) for g, f in enumerate(histogram)})
        writer.put_dict("gear_update", stats, step)
        for k, (loss_map, shift) in enumerate(zip(maps, shifts)):
            writer.put_image(f"gear_update/view_{k}", self.picture(loss_map, *shift), step)
        CONSOLE.log(
            f"Gear update {int(self.state.num_updates)} at step {step}: loss-map variance {variance:.3g}, "
            f"upshift area {stats['upshift_mask_area']:.2f}, gears "
            + " ".join(f"{float(f):.2f}" for f in histogram)
        )
        return stats

    @torch.no_grad()
    def visible_gear_histogram(self, maps: List[LossMap]) -> Tensor:
        """Fraction of the rendered pixels whose visible surface is at each gear level."""
        levels = torch.cat(
            [
                self.model.field.gear_levels(m.surface, m.camera.times.reshape(1, 1).expand(len(m.surface), 1))
                for m in maps
            ]
        )
        counts = torch.bincount(levels, minlength=self.model.config.num_gears + 1)[1:].float()
        return counts / counts.sum()

    def loss_map(self, image_index: int) -> LossMap:
        """Render a training view and its per-pixel loss L(r) = L_pho(r) + lambda L_SAM(r)."""
        dataset = self.datamanager.train_dataset
        camera = dataset.cameras[image_index : image_index + 1].to(self.model.device)
        full_size = (int(camera.height[0, 0]), int(camera.width[0, 0]))
        scale = min(1.0, self.config.loss_map_size / max(full_size))
        camera.rescale_output_resolution(scale)
        height, width = int(camera.height[0, 0]), int(camera.width[0, 0])
        rgb = self.ground_truth(image_index, (height, width))

        was_training = self.model.training
        self.model.eval()
        rays = camera.generate_rays(camera_indices=0, keep_shape=True)
        outputs = self.model.get_outputs_for_camera_ray_bundle(rays)
        self.model.train(was_training)
        surface = (rays.origins + rays.directions * outputs["depth"]).reshape(-1, 3)
        loss = (outputs["rgb"] - rgb).square().sum(-1)
        rgb_loss = loss.clone()
        if self.config.mask_source == "sam":
            embedding = self.datamanager.train_embedding(image_index)
            ys, xs = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
            # Loss-map pixels -> pixels of the embedded image (its size can differ from the camera's).
            to_image = torch.tensor([embedding.image_size[1] / width, embedding.image_size[0] / height])
            pixels = torch.stack([xs, ys], dim=-1).reshape(-1, 2) * to_image
            features = torch.from_numpy(embedding.features)
            target = sample_features(features, pixels, embedding.image_size).to(self.model.device)
            sam_error = (outputs["sam"].reshape(-1, target.shape[-1]) - target).square().sum(-1)
            loss = loss + self.config.sam_loss_weight * sam_error.reshape(height, width)
        return LossMap(
            image_index, camera, rgb, loss, rgb_loss, surface,
            self.change(image_index, rgb, self.config.motion_frames), self.change(image_index, rgb, 2, window=1),
        )  # fmt: skip

    def ground_truth(self, image_index: int, size: Tuple[int, int]) -> Tensor:
        """Training image (h, w, 3) area-resampled to the loss-map size."""
        return resized_image(self.datamanager.train_dataset, image_index, size).to(self.model.device)

    def change(self, image_index: int, rgb: Tensor, num_frames: int, window: Optional[int] = None) -> Tensor:
        """Motion gate of one view (``frame_change``; zero when the gate is off)."""
        if self.config.motion_threshold <= 0:
            return torch.zeros(rgb.shape[:2], device=rgb.device)
        dataset = self.datamanager.train_dataset
        return frame_change(dataset, image_index, tuple(rgb.shape[:2]), num_frames, window).to(rgb.device)

    def upshift_mask(self, loss_map: LossMap) -> Tuple[Tensor, Optional[Tensor], Optional[Tensor]]:
        """The upshift mask (h, w) of one view and its prompts (x, y), labels in loss-map pixels.

        mask_source 'sam': the SAM decoder on the loss-map prompts and the ground-truth embedding;
        'loss_threshold': the RGB loss map above its mean + k std, without prompts. Either is cut to the
        moving patches (motion gate); with none, the mask is empty and no prompts are made.
        """
        config = self.config
        shape = tuple(loss_map.loss.shape)
        moving = moving_patches(loss_map.change, config.patch_size, config.motion_threshold)
        moving_pixels = patches_to_pixels(moving, shape, config.patch_size)
        if config.mask_source == "loss_threshold":
            values = loss_map.rgb_loss
            return (values > values.mean() + config.loss_threshold_std * values.std()) & moving_pixels, None, None
        if not bool(moving.any()):
            return torch.zeros(shape, dtype=torch.bool, device=loss_map.loss.device), None, None
        points, labels = patch_prompts(loss_map.loss, config.patch_size, config.top_k, moving)
        embedding = self.datamanager.train_embedding(loss_map.image_index)
        height, width = loss_map.loss.shape
        scale = np.array([embedding.image_size[1] / width, embedding.image_size[0] / height])
        masks, _ = self.datamanager.sam_backend.decode(
            embedding, points=points.numpy() * scale, labels=labels.numpy().astype(np.int64)
        )
        mask = torch.from_numpy(masks[0]).float()[None, None]
        mask = F.interpolate(mask, size=(height, width), mode="area")[0, 0].to(self.model.device) > 0.5
        return mask & moving_pixels, points, labels

    def sample_points(
        self, maps: List[LossMap], masks: List[Tensor]
    ) -> Tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Points on rays inside (S_upshift) and outside (S_stay) the masks: positions, times, rendering weights,
        whether in S_upshift, and whether on a pixel that stays still around the view's time (motion gate on).
        Half of each view's S_stay rays come from the pixels at risk of moving up with the mask (``stay_focus``)."""
        per_view = max(1, self.config.rays_per_set // len(maps))
        points, times, weights, upshift, still = [], [], [], [], []
        for loss_map, mask in zip(maps, masks):
            shape = tuple(mask.shape)
            moving = moving_patches(loss_map.change, self.config.patch_size, self.config.motion_threshold)
            focus = stay_focus(mask, patches_to_pixels(moving, shape, self.config.patch_size), self.config.patch_size)
            chosen_focus = self.choose_pixels(focus, per_view // 2)
            for inside, pixels in (
                (True, self.choose_pixels(mask, per_view)),
                (False, torch.cat([chosen_focus, self.choose_pixels(~mask, per_view - len(chosen_focus))])),
            ):
                if len(pixels) == 0:
                    continue
                position, time, weight = self.weighted_samples(loss_map.camera, pixels)
                points.append(position)
                times.append(time)
                weights.append(weight)
                upshift.append(torch.full((len(weight),), inside, dtype=torch.bool, device=weight.device))
                rows, cols = pixels.long().unbind(-1)
                unchanged = (loss_map.local_change[rows, cols] < self.config.motion_threshold) & ~mask[rows, cols]
                still.append(unchanged.repeat_interleave(len(weight) // len(pixels)) & (self.config.motion_threshold > 0))
        return torch.cat(points), torch.cat(times), torch.cat(weights), torch.cat(upshift), torch.cat(still)

    def choose_pixels(self, selected: Tensor, count: int) -> Tensor:
        """Up to ``count`` distinct pixels (row, col) of a boolean map, drawn at random."""
        pixels = torch.nonzero(selected).float()
        return pixels[torch.from_numpy(self.rng.permutation(len(pixels))[:count]).to(pixels.device)]

    @torch.no_grad()
    def weighted_samples(self, camera: Cameras, pixels: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """Base samples (n per ray, uniform) on the rays through loss-map pixels (row, col): positions, times and
        volume-rendering weights."""
        bundle = camera.generate_rays(camera_indices=0, coords=pixels + 0.5)
        samples = UniformSampler(num_samples=self.model.config.num_samples)(self.model.collider(bundle))
        positions = samples.frustums.get_positions()
        density = self.model.field(
            positions.reshape(-1, 3), samples.frustums.directions.reshape(-1, 3), samples.times.reshape(-1, 1)
        )["density"]
        weights = samples.get_weights(density.reshape(*positions.shape[:-1], 1))[..., 0]
        return positions.reshape(-1, 3), samples.times.reshape(-1, 1), weights.reshape(-1)

    @staticmethod
    def picture(loss_map: LossMap, mask: Tensor, points: Optional[Tensor], labels: Optional[Tensor]) -> Tensor:
        """Loss map (turbo) with the prompts (red: positive, green: negative) and the upshift mask (red)
        over the ground truth, side by side."""
        loss = loss_map.loss / loss_map.loss.max().clamp(min=1e-12)
        heat = colormaps.apply_colormap(loss[..., None], colormaps.ColormapOptions(colormap="turbo")).clone()
        overlay = loss_map.rgb * 0.5 + mask[..., None].float() * torch.tensor([0.5, 0.0, 0.0], device=mask.device)
        if points is not None:
            height, width = mask.shape
            for (x, y), label in zip(points.long().tolist(), labels.tolist()):
                colour = torch.tensor([1.0, 0.0, 0.0] if label > 0 else [0.0, 1.0, 0.0], device=mask.device)
                heat[max(0, y - 1) : min(height, y + 2), max(0, x - 1) : min(width, x + 2)] = colour
        return torch.cat([heat, overlay], dim=1)
