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

Addition to the paper, the guard (`guard_tolerance`): an update is reviewed L epochs later, when the next one
is due. Its training views are rendered again and compared with their renders just before it; an update after
which they are worse is undone and ends the updates. An update is not judged right after it: the regions that
move up start from the lower gear's columns, but a column of a space-time plane is shared by every point with
the same coordinate along its axis, and the split samples change the quadrature, so the views render worse at
first (about 3.5 dB on the synthetic loop scene) and recover with training. The held-out camera at the same
times is measured alike and logged, never used to decide.

Addition to the paper, S_static (``static_views``): the still pixels of other training cameras at each view's frame
are held at gear 1 in a term of Eq 10 of their own. The gear function is a sum of products of planes (Eq 4), so the
points an upshift lifts share plane cells with static surfaces that the update's views do not see; S_stay holds only
those they see.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import ContextManager, Dict, List, Optional, Protocol, Tuple

import numpy as np
import torch
import torch.nn.functional as F
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.utils import colormaps
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from gear_nerfstudio import distributed
from gear_nerfstudio.gears.config import GearUpdateConfig
from gear_nerfstudio.gears.loss_maps import (
    LossMap,
    frame_change,
    moving_patches,
    moving_pixels,
    patch_prompts,
    patches_to_pixels,
    resized_image,
    stay_focus,
)
from gear_nerfstudio.gears.schedule import (
    GearUpdateState,
    describe_plan,
    no_updates_error,
    planned_updates,
    spread_views,
    update_interval,
)
from gear_nerfstudio.gears.upshift import UpdatePoints, level_targets, select_points, shift_gears
from gear_nerfstudio.sam.builtin_backend import BuiltinSamBackend
from gear_nerfstudio.sam.interface import Embedding, SamBackend, sample_features


class UpdateTarget(Protocol):
    """What the updater needs of the model: its gears and its renders (the Gear-NeRF model has these)."""

    device: torch.device

    @property
    def num_gears(self) -> int:
        ...

    def gear_values(self, positions: Tensor, times: Optional[Tensor]) -> Tensor:
        """Eq 4 at world positions and times."""

    def gear_levels(self, positions: Tensor, times: Optional[Tensor]) -> Tensor:
        """Eq 5 at world positions and times."""

    def render_view(self, camera: Cameras) -> Dict[str, Tensor]:
        """A full render of one camera in evaluation mode: at least "rgb", "sam" (Eq 8) and "depth"."""

    def all_space(self) -> ContextManager[None]:
        """Inside, renders take the density everywhere, as training does (not only where the cameras see)."""

    def visible_surface(self, camera: Cameras, outputs: Dict[str, Tensor]) -> Tensor:
        """The world point (H, W, 3) each pixel of a render sees."""

    def sample_weights(self, camera: Cameras, pixels: Tensor) -> Tuple[Tensor, Tensor, Tensor]:
        """Base samples on the rays through pixels (row, col) of a camera: positions, times, rendering weights."""

    def gear_assignment(self) -> Dict[str, Tensor]:
        """A copy of what an update changes (the gear function and the planes' claimed columns)."""

    def restore_gear_assignment(self, assignment: Dict[str, Tensor]) -> None:
        """Undo an update: restore a ``gear_assignment`` copy."""


class TrainingViews(Protocol):
    """What the updater needs of the data: the training images with their cameras and metadata (camera_ids,
    frame_ids), and the SAM embedding of each (the datamanager has these)."""

    @property
    def train_dataset(self) -> InputDataset:
        ...

    @property
    def eval_dataset(self) -> InputDataset:
        """The held-out camera's images (each update's effect on them is logged, never used to decide)."""

    def train_embedding(self, image_index: int) -> Embedding:
        """The whole SAM embedding of a training image."""


def with_mask_source(config: GearUpdateConfig, backend: SamBackend) -> GearUpdateConfig:
    """The settings with mask_source 'auto' made concrete: 'loss_threshold' with the built-in stand-in, whose decoder
    covered few of the real captures' people (docs/decisions.md), and 'sam' with any other backend (SAM itself, as in
    the paper)."""
    if config.mask_source != "auto":
        return config
    return replace(config, mask_source="loss_threshold" if isinstance(backend, BuiltinSamBackend) else "sam")


class GearUpdater:
    """Runs the updates; called after every training iteration.

    Args:
        config: schedule and settings.
        target: the model whose gears are updated.
        views: the training images and their SAM embeddings.
        backend: the SAM decoder for the upshift masks.
        optimizer: the optimizer of the gear function (Eq 11).
        state: the record of the updates (restored from a checkpoint on resume).
        rays_per_batch: training rays per iteration (for the plan's log line).
        first_step: first step of this run (0, or the step after the checkpoint).
        last_step: last step of this run.
        seed: the run's seed; the views of update u are drawn with (seed, u).
    """

    def __init__(
        self,
        config: GearUpdateConfig,
        target: UpdateTarget,
        views: TrainingViews,
        backend: SamBackend,
        optimizer: torch.optim.Optimizer,
        state: GearUpdateState,
        rays_per_batch: int,
        first_step: int,
        last_step: int,
        seed: int = 0,
    ):
        self.config = with_mask_source(config, backend)
        self.target = target
        self.views = views
        self.backend = backend
        self.optimizer = optimizer
        self.state = state
        self.last_step = last_step
        self.seed = seed
        self.interval = update_interval(config)
        self.rng = np.random.default_rng([seed, int(state.num_updates)])
        self.planned = planned_updates(config, first_step, last_step)
        if bool(state.finished):
            CONSOLE.log(f"Gear updates: finished before step {first_step} ({int(state.num_updates)} updates).")
        elif self.planned:
            CONSOLE.log(describe_plan(self.config, self.planned, views.train_dataset.cameras, rays_per_batch))
        elif int(state.num_updates) == 0:
            raise no_updates_error(config, first_step, last_step)

    def __call__(self, step: int) -> None:
        if int(self.state.review_update) and step >= int(self.state.review_step):
            self.review(step)
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
        frame_ids = self.views.train_dataset.metadata["frame_ids"].numpy()
        maps = [self.loss_map(index) for index in spread_views(frame_ids, config.views_per_update, self.rng)]
        # Under DDP every process renders the same views (same seed) and decides with the mean variance, so that
        # all take the same branch (and GearUpdateState agrees); the Eq 11 steps then agree by ``shift_gears``.
        variance = float(distributed.average(torch.stack([m.loss.var() for m in maps]).double().mean()))
        stats = {"loss_map_variance": variance}
        if variance < config.variance_threshold:
            self.state.finished.fill_(True)
            CONSOLE.log(f"Gear updates end at step {step}: loss-map variance {variance:.3g} is below the threshold.")
            writer.put_dict("gear_update", stats, step)
            return stats

        views = [m.image_index for m in maps]
        stats["views_psnr"] = views_psnr([m.rgb_loss.mean() / 3.0 for m in maps])
        held_out = self.held_out_views(views) if config.measure_held_out else []
        stats["held_out_psnr"] = self.psnr(held_out) if held_out else float("nan")
        self.state.remember(
            int(self.state.num_updates) + 1, step + self.interval, views, stats["views_psnr"], stats["held_out_psnr"],
            self.target.gear_assignment(),
        )
        shifts = [self.upshift_mask(m) for m in maps]
        masks = [mask for mask, _, _ in shifts]
        points = self.sample_points(maps, masks)
        generator = torch.Generator(points.weights.device).manual_seed(int(self.rng.integers(2**31)))
        points = select_points(points, config.max_points, generator)
        levels = self.target.gear_levels(points.positions, points.times)
        targets = level_targets(levels, points.upshift, self.target.num_gears, points.still)
        steps = shift_gears(self.target, self.optimizer, points, targets, config)
        new_levels = self.target.gear_levels(points.positions, points.times)
        self.state.num_updates += 1

        stats.update(
            {
                "upshift_mask_area": float(np.mean([float(mask.float().mean()) for mask in masks])),
                "steps": float(steps),
                "downshifted_fraction": float((new_levels < levels).float().mean()),
            }
        )
        seen = torch.cat(
            [self.target.gear_levels(m.surface, m.camera.times.expand(*m.surface.shape[:-1], 1)).reshape(-1) for m in maps]
        )
        histogram = torch.bincount(seen, minlength=self.target.num_gears + 1)[1:].float() / len(seen)
        stats.update({f"gear_{g + 1}_fraction": float(f) for g, f in enumerate(histogram)})
        writer.put_dict("gear_update", stats, step)
        for k, (loss_map, shift) in enumerate(zip(maps, shifts)):
            writer.put_image(f"gear_update/view_{k}", picture(loss_map, *shift), step)
        CONSOLE.log(
            f"Gear update {int(self.state.num_updates)} at step {step}: loss-map variance {variance:.3g}, "
            f"upshift area {stats['upshift_mask_area']:.2f}, gears "
            + " ".join(f"{float(f):.2f}" for f in histogram)
            + f"; its views {stats['views_psnr']:.2f} dB"
            + (f", held-out view {stats['held_out_psnr']:.2f} dB" if held_out else "")
            + f" (reviewed at step {step + self.interval})"
        )
        return {key: value for key, value in stats.items() if not math.isnan(value)}

    def review(self, step: int) -> Dict[str, float]:
        """The guard: an update's views, rendered again after its L epochs of training, against their PSNR just
        before it. An update after which they are more than ``guard_tolerance`` dB worse is undone (the gear
        assignment goes back to what it was before it) and no further update runs. The held-out camera at the
        same times is measured alike and logged, never used to decide."""
        from nerfstudio.utils import writer

        state, update = self.state, int(self.state.review_update)
        views = [index for index in state.review_views.tolist() if index >= 0]
        stats = {"views_psnr_before": float(state.review_psnr), "held_out_psnr_before": float(state.review_held_out_psnr)}
        stats["views_psnr_after"] = self.psnr([self.view(self.views.train_dataset, index) for index in views])
        held_out = self.held_out_views(views) if self.config.measure_held_out else []
        stats["held_out_psnr_after"] = self.psnr(held_out) if held_out else float("nan")
        undone = stats["views_psnr_after"] < stats["views_psnr_before"] - self.config.guard_tolerance
        if undone:
            self.target.restore_gear_assignment(state.assignment_before())
            state.num_undone += 1
            state.finished.fill_(True)
        state.review_update.fill_(0)
        stats["undone"] = float(undone)
        stats = {key: value for key, value in stats.items() if not math.isnan(value)}
        writer.put_dict("gear_update_review", stats, step)
        CONSOLE.log(
            f"Gear update {update} reviewed at step {step}: its views {stats['views_psnr_before']:.2f} -> "
            f"{stats['views_psnr_after']:.2f} dB"
            + (
                f", held-out view {stats['held_out_psnr_before']:.2f} -> {stats['held_out_psnr_after']:.2f} dB"
                if "held_out_psnr_after" in stats
                else ""
            )
            + (
                f"; more than {self.config.guard_tolerance:g} dB worse: undone, and no further gear update"
                if undone
                else ": kept"
            )
        )
        return stats

    def held_out_views(self, views: List[int]) -> List[Tuple[Cameras, Tensor]]:
        """The held-out camera at the times of training views (camera and ground truth at loss-map size)."""
        dataset = self.views.eval_dataset
        frame_ids = dataset.metadata["frame_ids"].tolist()
        frames = [int(self.views.train_dataset.metadata["frame_ids"][index]) for index in views]
        indices = [frame_ids.index(frame) for frame in frames if frame in frame_ids]
        return [self.view(dataset, index) for index in dict.fromkeys(indices)]

    def psnr(self, views: List[Tuple[Cameras, Tensor]]) -> float:
        """PSNR of the renders of views (camera, ground truth) over all their pixels (``views_psnr``)."""
        device = self.target.device
        return views_psnr([(self.render(camera)["rgb"] - rgb.to(device)).square().mean() for camera, rgb in views])

    def render(self, camera: Cameras) -> Dict[str, Tensor]:
        """The target's render of a view as training sees the scene (``UpdateTarget.all_space``): the updates and
        the guard measure what training fits."""
        with self.target.all_space():
            return self.target.render_view(camera)

    def view(self, dataset: InputDataset, image_index: int) -> Tuple[Cameras, Tensor]:
        """Camera of an image, rescaled to the loss-map size (on the model's device), and the image resized to match
        (on the CPU, where it is read)."""
        camera = dataset.cameras[image_index : image_index + 1].to(self.target.device)
        full_size = (int(camera.height[0, 0]), int(camera.width[0, 0]))
        camera.rescale_output_resolution(min(1.0, self.config.loss_map_size / max(full_size)))
        size = (int(camera.height[0, 0]), int(camera.width[0, 0]))
        return camera, resized_image(dataset, image_index, size)

    def loss_map(self, image_index: int) -> LossMap:
        """Render a training view (`render`) and its per-pixel loss L(r) = L_pho(r) + lambda L_SAM(r)."""
        camera, image = self.view(self.views.train_dataset, image_index)
        size = tuple(image.shape[:2])
        rgb = image.to(self.target.device)
        outputs = self.render(camera)
        loss = (outputs["rgb"] - rgb).square().sum(-1)
        rgb_loss = loss.clone()
        if self.config.mask_source == "sam":
            embedding = self.views.train_embedding(image_index)
            ys, xs = torch.meshgrid(torch.arange(size[0]) + 0.5, torch.arange(size[1]) + 0.5, indexing="ij")
            # Loss-map pixels -> pixels of the embedded image (its size can differ from the camera's).
            to_image = torch.tensor([embedding.image_size[1] / size[1], embedding.image_size[0] / size[0]])
            pixels = torch.stack([xs, ys], dim=-1).reshape(-1, 2) * to_image
            target = sample_features(torch.from_numpy(embedding.features), pixels, embedding.image_size)
            sam_error = (outputs["sam"].reshape(-1, target.shape[-1]) - target.to(self.target.device)).square().sum(-1)
            loss = loss + self.config.sam_loss_weight * sam_error.reshape(size)
        surface = self.target.visible_surface(camera, outputs)
        return LossMap(
            image_index, camera, rgb, loss, rgb_loss, surface,
            self.change(image_index, image, self.config.motion_frames), self.change(image_index, image, 2, window=1),
        )  # fmt: skip

    def change(self, image_index: int, image: Tensor, num_frames: int, window: Optional[int] = None) -> Tensor:
        """Motion gate of one view at the loss-map size (``frame_change`` on the view's resized image; zero when
        the gate is off)."""
        if self.config.motion_threshold <= 0:
            return torch.zeros(image.shape[:2], device=self.target.device)
        return frame_change(self.views.train_dataset, image_index, image, num_frames, window).to(self.target.device)

    def upshift_mask(self, loss_map: LossMap) -> Tuple[Tensor, Optional[Tensor], Optional[Tensor]]:
        """The upshift mask (h, w) of one view and its prompts (x, y), labels in loss-map pixels.

        mask_source 'sam': the SAM decoder on the loss-map prompts and the ground-truth embedding;
        'loss_threshold': the RGB loss map above its mean + k std, without prompts. Either is cut to the
        moving patches (motion gate); with none, the mask is empty and no prompts are made.
        """
        config = self.config
        shape = tuple(loss_map.loss.shape)
        moving = moving_patches(loss_map.change, config.patch_size, config.motion_threshold)
        in_motion = patches_to_pixels(moving, shape, config.patch_size)
        if config.mask_source == "loss_threshold":
            values = loss_map.rgb_loss
            return (values > values.mean() + config.loss_threshold_std * values.std()) & in_motion, None, None
        if not bool(moving.any()):
            return torch.zeros(shape, dtype=torch.bool, device=loss_map.loss.device), None, None
        points, labels = patch_prompts(loss_map.loss, config.patch_size, config.top_k, moving)
        embedding = self.views.train_embedding(loss_map.image_index)
        height, width = shape
        scale = np.array([embedding.image_size[1] / width, embedding.image_size[0] / height])
        masks, _ = self.backend.decode(embedding, points=points.cpu().numpy() * scale, labels=labels.numpy().astype(np.int64))
        mask = torch.from_numpy(masks[0]).float()[None, None]
        mask = F.interpolate(mask, size=shape, mode="area")[0, 0].to(self.target.device) > 0.5
        return mask & in_motion, points, labels

    def sample_points(self, maps: List[LossMap], masks: List[Tensor]) -> UpdatePoints:
        """Points on rays inside (S_upshift) and outside (S_stay) the masks, and of S_static (``static_rays``), with
        their rendering weights; ``still``: on a pixel that stays still around the view's time (motion gate on;
        every point of S_static). Half of each view's S_stay rays come from the pixels at risk of moving up with the
        mask (``stay_focus``)."""
        config = self.config
        per_view = max(1, config.rays_per_set // len(maps))
        parts: List[UpdatePoints] = []

        def add(camera: Cameras, pixels: Tensor, inside: bool, unchanged: Tensor, held: bool) -> None:
            positions, times, weights = self.target.sample_weights(camera, pixels)
            samples = len(weights) // len(pixels)
            parts.append(
                UpdatePoints(
                    positions,
                    times,
                    weights,
                    upshift=torch.full((len(weights),), inside, dtype=torch.bool, device=weights.device),
                    still=unchanged.to(weights.device).repeat_interleave(samples),
                    static=torch.full((len(weights),), held, dtype=torch.bool, device=weights.device),
                )
            )

        for loss_map, mask in zip(maps, masks):
            moving = moving_pixels(loss_map.change, config.patch_size, config.motion_threshold)
            focus = stay_focus(mask, moving, config.patch_size)
            chosen_focus = self.choose_pixels(focus, per_view // 2)
            for inside, pixels in (
                (True, self.choose_pixels(mask, per_view)),
                (False, torch.cat([chosen_focus, self.choose_pixels(~mask, per_view - len(chosen_focus))])),
            ):
                if len(pixels):
                    rows, cols = pixels.long().unbind(-1)
                    unchanged = (loss_map.local_change[rows, cols] < config.motion_threshold) & ~mask[rows, cols]
                    add(loss_map.camera, pixels, inside, unchanged & (config.motion_threshold > 0), False)
            for camera, pixels in self.static_rays(loss_map, per_view):
                add(camera, pixels, False, torch.ones(len(pixels), dtype=torch.bool), True)
        return UpdatePoints.cat(parts)

    def static_rays(self, loss_map: LossMap, count: int) -> List[Tuple[Cameras, Tensor]]:
        """S_static's rays for one view (``GearUpdateConfig.static_views``): up to ``static_views`` other training
        cameras at the view's frame, drawn at random, each with up to ``count`` of its still pixels (outside every
        moving patch of its motion gate), at the loss-map size. No rays when S_static is off, or without the motion
        gate to tell still pixels."""
        config = self.config
        if config.static_views <= 0 or config.motion_threshold <= 0:
            return []
        dataset = self.views.train_dataset
        camera_ids, frame_ids = dataset.metadata["camera_ids"], dataset.metadata["frame_ids"]
        view = loss_map.image_index
        others = torch.nonzero((frame_ids == frame_ids[view]) & (camera_ids != camera_ids[view]))[:, 0].numpy()
        rays = []
        for index in self.rng.permutation(others)[: config.static_views].tolist():
            camera, image = self.view(dataset, index)
            change = self.change(index, image, config.motion_frames)
            pixels = self.choose_pixels(~moving_pixels(change, config.patch_size, config.motion_threshold), count)
            if len(pixels):
                rays.append((camera, pixels))
        return rays

    def choose_pixels(self, selected: Tensor, count: int) -> Tensor:
        """Up to ``count`` distinct pixels (row, col) of a boolean map, drawn at random."""
        pixels = torch.nonzero(selected).float()
        return pixels[torch.from_numpy(self.rng.permutation(len(pixels))[:count]).to(pixels.device)]


def views_psnr(errors: List[Tensor]) -> float:
    """PSNR of views from their mean squared errors (the mean over views: views of one size weigh alike), the same
    on every process."""
    mse = distributed.average(torch.stack(errors).mean().double())
    return float(-10.0 * torch.log10(mse.clamp(min=1e-10)))


def picture(loss_map: LossMap, mask: Tensor, points: Optional[Tensor], labels: Optional[Tensor]) -> Tensor:
    """Loss map (turbo) with the prompts (red: positive, green: negative) and the upshift mask (red) over the
    ground truth, side by side (tensorboard)."""
    loss = loss_map.loss / loss_map.loss.max().clamp(min=1e-12)
    heat = colormaps.apply_colormap(loss[..., None], colormaps.ColormapOptions(colormap="turbo")).clone()
    overlay = loss_map.rgb * 0.5 + mask[..., None].float() * torch.tensor([0.5, 0.0, 0.0], device=mask.device)
    if points is not None:
        height, width = mask.shape
        for (x, y), label in zip(points.long().tolist(), labels.tolist()):
            colour = torch.tensor([1.0, 0.0, 0.0] if label > 0 else [0.0, 1.0, 0.0], device=mask.device)
            heat[max(0, y - 1) : min(height, y + 2), max(0, x - 1) : min(width, x + 2)] = colour
    return torch.cat([heat, overlay], dim=1)
