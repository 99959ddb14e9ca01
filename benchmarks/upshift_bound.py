"""What the upshift masks bound in the gear target (issue 26): a trained run's gear updates (Sec 4.3) replayed on its
final model from a reset gear function, with the upshift masks its settings make (``mask_source``) or with the
people's true masks in their place, scored as ``gear_masks.py`` scores a run (people's pixels at gear >= 2 and the
rest at gear 1, at the held-out camera, every frame).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/upshift_bound.py <run>/config.yml \\
        ../shared/data/real/panoptic_basketball_masks --camera 00 [--true-masks] [--gear-feature-dim 8] \\
        [--overrides static_views=0]

The updates run at the steps the run planned, on the views its seed draws, with the run's update settings (changed
by ``--overrides``) and a fresh gear function (Eq 4's initial state, g = 1) of ``--gear-feature-dim`` channels.
Nothing trains between them: they see the final geometry, where the run's own updates saw the geometry of their
steps, so this bounds the masks' part, not a training's result. For every update view with a true mask it prints
the recall (share of the people's pixels inside the upshift mask) and precision of the mask its settings make;
views of cameras without masks keep that mask. It measures; it changes nothing on disk.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Optional, Tuple

import torch
import tyro
from nerfstudio.utils.eval_utils import eval_setup
from PIL import Image

from gear_masks import gear_map_picture, people_mask, pipeline_gear_shares
from speed_accuracy import mask_path
from gear_nerfstudio.fields.gear_function import GearFunction
from gear_nerfstudio.gears.loss_maps import LossMap
from gear_nerfstudio.gears.schedule import GearUpdateState, planned_updates
from gear_nerfstudio.gears.updater import GearUpdater


class MeasuredUpdater(GearUpdater):
    """The updater, with each upshift mask scored against the people's true mask of its view, and replaced by it
    when ``true_masks`` is set."""

    def __init__(self, *args, masks: Path, true_masks: bool, **kwargs):
        super().__init__(*args, **kwargs)
        self.masks = masks
        self.true_masks = true_masks

    def upshift_mask(self, loss_map: LossMap) -> Tuple[torch.Tensor, Optional[torch.Tensor], Optional[torch.Tensor]]:
        mask, points, labels = super().upshift_mask(loss_map)
        dataset = self.views.train_dataset
        index = loss_map.image_index
        camera = dataset.metadata["camera_names"][int(dataset.metadata["camera_ids"][index])]
        number = int(dataset.metadata["frame_numbers"][int(dataset.metadata["frame_ids"][index])])
        if not mask_path(self.masks, camera, number).exists():
            print(f"  view {camera} frame {number}: no true mask, the upshift mask is kept")
            return mask, points, labels
        truth = torch.from_numpy(people_mask(self.masks, camera, number, tuple(mask.shape))).to(mask.device)
        inside = float((mask & truth).sum())
        print(
            f"  view {camera} frame {number}: people {float(truth.float().mean()):.3f} of the view, upshift mask "
            f"{float(mask.float().mean()):.3f}, recall {inside / max(float(truth.sum()), 1):.2f}, "
            f"precision {inside / max(float(mask.sum()), 1):.2f}"
        )
        return (truth, points, labels) if self.true_masks else (mask, points, labels)


def main(
    config: tyro.conf.Positional[Path],
    masks: tyro.conf.Positional[Path],
    camera: str = "00",
    true_masks: bool = False,
    gear_feature_dim: Optional[int] = None,
    overrides: Tuple[str, ...] = (),
    picture: Optional[Path] = None,
    picture_frames: Tuple[int, ...] = (0, 10, 19),
) -> None:
    """Replay the run's updates and print the held-out camera's two shares.

    Args:
        config: the run's config.yml.
        masks: the capture's people masks, ``<camera>/<frame:05d>.png``.
        camera: the held-out camera (it must have masks).
        true_masks: use the people's true masks as upshift masks.
        gear_feature_dim: channels of the fresh gear function (the run's when None).
        overrides: update settings to change, ``name=value`` (``GearUpdateConfig``).
        picture: also save the held-out camera's renders and gear maps at ``picture_frames`` here (PNG).
        picture_frames: frames of that picture, numbered within the loaded window.
    """
    trainer_config, pipeline, _, _ = eval_setup(config, test_mode="test")
    model = pipeline.model
    field = model.field
    space, time = field.gear_function.space_planes.planes[0], field.gear_function.time_planes.planes[0]
    seed = trainer_config.machine.seed
    torch.manual_seed(seed)
    field.gear_function = GearFunction(gear_feature_dim or space.shape[1], space.shape[-1], time.shape[-2]).to(
        model.device
    )
    settings = pipeline.config.gear_updates
    for item in overrides:
        name, value = item.split("=", 1)
        kind = type(getattr(settings, name))
        settings = replace(settings, **{name: value == "True" if kind is bool else kind(value)})
    settings = replace(settings, measure_held_out=False)
    optimizer = trainer_config.optimizers["gear_field"]["optimizer"].setup(params=list(field.gear_function.parameters()))
    last_step = trainer_config.max_num_iterations - 1
    updater = MeasuredUpdater(
        settings, model, pipeline.datamanager, pipeline.sam_backend, optimizer,
        GearUpdateState(model.gear_assignment(), settings.views_per_update),
        pipeline.datamanager.config.train_num_rays_per_batch, 0, last_step, seed,
        masks=masks, true_masks=true_masks,
    )  # fmt: skip
    for step in planned_updates(settings, 0, last_step):
        with torch.enable_grad():
            updater.update(step)
    people, rest = pipeline_gear_shares(pipeline, masks, (camera,), held_out=True)
    if picture is not None:
        Image.fromarray(gear_map_picture(pipeline, masks, camera, picture_frames)).save(picture)
    source = "true masks" if true_masks else f"{updater.config.mask_source} masks"
    print(
        f"{config.parent.name} seed {seed}, {source}, {field.gear_function.space_planes.planes[0].shape[1]} channels, "
        f"static_views {settings.static_views}: people's pixels at gear >= 2: {people:.3f}; other pixels at gear 1: "
        f"{rest:.3f}"
    )


if __name__ == "__main__":
    tyro.cli(main)
