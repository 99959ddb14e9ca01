"""The Gear-NeRF pipeline: nerfstudio's VanillaPipeline that owns the SAM backend (Sec 4.2), the gear-update
callback (Sec 4.3), the viewer's tracking controls (Sec 4.5) and its resolutions (``viewer_speed``).

The backend is built once and handed to the datamanager (its encoder gives the targets of Eq 9), to the gear
updates (its decoder gives the upshift masks) and to tracking (its decoder gives the tracked masks). The
updates work on the model and the datamanager through narrow interfaces (``gears.updater.UpdateTarget`` and
``TrainingViews``), so that neither the model nor the datamanager knows about them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Tuple, Type

import torch
import torchvision.utils
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils.rich_utils import CONSOLE
from rich.progress import track
from torch.cuda.amp.grad_scaler import GradScaler

from gear_nerfstudio.data.datamanager import GearDataManager, GearDataManagerConfig
from gear_nerfstudio.errors import InputError
from gear_nerfstudio.gears.config import GearUpdateConfig
from gear_nerfstudio.gears.schedule import GearUpdateState
from gear_nerfstudio.gears.updater import GearUpdater
from gear_nerfstudio.model.gear_model import GearNeRFModelConfig
from gear_nerfstudio.model.metrics import MIN_MSE, near_layer_warning
from gear_nerfstudio.model.moving_region import SUMS, EvalViews, region_scores
from gear_nerfstudio.sam.config import BuiltinSamConfig, SamConfigChoice
from gear_nerfstudio.sam.interface import SamBackend
from gear_nerfstudio.tracking.viewer import ViewerTracking
from gear_nerfstudio.viewer_speed import ViewerSpeed


@dataclass
class GearPipelineConfig(VanillaPipelineConfig):
    """Gear-NeRF pipeline: datamanager with SAM features, model, SAM backend, gear updates."""

    _target: Type = field(default_factory=lambda: GearPipeline)
    datamanager: GearDataManagerConfig = field(default_factory=GearDataManagerConfig)
    model: GearNeRFModelConfig = field(default_factory=GearNeRFModelConfig)
    sam: SamConfigChoice = field(default_factory=BuiltinSamConfig)
    """SAM backend (Sec 4.2): its encoder gives the targets S(r) of Eq 9, its decoder the masks of Sec 4.3 and
    4.5."""
    gear_updates: GearUpdateConfig = field(default_factory=GearUpdateConfig)
    """Gear-assignment updates during training (Sec 4.3)."""


def check_sam_dim(config: GearPipelineConfig, backend: SamBackend) -> None:
    """The model's SAM embedding has the backend's feature dimension (Eq 9 compares the two)."""
    sam_dim = config.model.sam_dim
    if config.datamanager.use_sam_features and sam_dim != backend.embedding_dim:
        raise InputError(
            f"the model's sam_dim is {sam_dim} but the SAM backend {backend.name!r} gives "
            f"{backend.embedding_dim}-dimensional features: set --pipeline.model.sam-dim {backend.embedding_dim}"
        )


class GearPipeline(VanillaPipeline):
    """VanillaPipeline plus the SAM backend, the gear updates' callback and state, and the viewer's tracking."""

    config: GearPipelineConfig
    datamanager: GearDataManager

    def __init__(
        self,
        config: GearPipelineConfig,
        device: str,
        test_mode: Literal["test", "val", "inference"] = "val",
        world_size: int = 1,
        local_rank: int = 0,
        grad_scaler: Optional[GradScaler] = None,
    ):
        super().__init__(config, device, test_mode, world_size, local_rank, grad_scaler)
        self.sam_backend = config.sam.setup()
        check_sam_dim(config, self.sam_backend)
        self.datamanager.attach_sam(self.sam_backend)
        self.model.see_from(self.datamanager.train_dataparser_outputs.cameras)
        if test_mode != "inference":
            eval_dataset = self.datamanager.eval_dataset
            self.model.eval_views = EvalViews(eval_dataset, eval_dataset.metadata.get("moving_masks"))
        self.gear_update_state = GearUpdateState(self.model.gear_assignment(), config.gear_updates.views_per_update)
        self.viewer_tracking = ViewerTracking(self.model, self.sam_backend)
        self.model.render_hooks.append(self.viewer_tracking.render_hook)
        self.viewer_speed = ViewerSpeed(self.model)

    def get_eval_image_metrics_and_images(self, step: int) -> Tuple[Dict[str, float], Dict[str, torch.Tensor]]:
        """One held-out view's metrics during training, with its moving-region scores (``region_scores``); a near
        layer in it is reported in one line that names it."""
        self.eval()
        camera, batch = self.datamanager.next_eval_image(step)
        outputs = self.model.get_outputs_for_camera(camera)
        metrics, images = self.model.get_image_metrics_and_images(outputs, batch)
        metrics["num_rays"] = int(camera.height * camera.width * camera.size)
        self.train()
        self._warn_near_layer([{**metrics, "view": int(batch["image_idx"])}])
        return self._scored(metrics), images

    def get_average_eval_image_metrics(
        self, step: Optional[int] = None, output_path: Optional[Path] = None, get_std: bool = False
    ) -> Dict[str, float]:
        """ns-eval: the image metrics of every held-out view, averaged (with their spread over views when asked and
        there are several); PSNR inside and outside the moving region and the gear shares over the pixels of all
        views (``region_scores``). Views with a near layer are named in one warning line. ``output_path``: the
        model's images of each view, as nerfstudio writes them."""
        self.eval()
        views: List[Dict[str, float]] = []
        if output_path is not None:
            output_path.mkdir(parents=True, exist_ok=True)
        loader = self.datamanager.fixed_indices_eval_dataloader
        for camera, batch in track(loader, description="Evaluating the held-out views", transient=True):
            started = time.perf_counter()
            outputs = self.model.get_outputs_for_camera(camera=camera)
            metrics, images = self.model.get_image_metrics_and_images(outputs, batch)
            metrics["fps"] = 1.0 / (time.perf_counter() - started)
            metrics["num_rays_per_sec"] = metrics["fps"] * int(camera.height) * int(camera.width)
            metrics["view"] = int(batch["image_idx"])
            if output_path is not None:
                for key, image in images.items():
                    torchvision.utils.save_image(
                        image.permute(2, 0, 1).cpu(), output_path / f"eval_{key}_{len(views):04d}.png"
                    )
            views.append(metrics)
        self.train()
        self._warn_near_layer(views)
        averages: Dict[str, float] = {}
        for key in sorted({key for view in views for key in view} - {"view"}):
            values = torch.tensor([view[key] for view in views if key in view], dtype=torch.float64)
            averages[key] = float(values.mean())
            if get_std and len(values) > 1 and key not in SUMS:
                averages[f"{key}_std"] = float(values.std())
        return self._scored(averages)

    @staticmethod
    def _scored(metrics: Dict[str, float]) -> Dict[str, float]:
        """The metrics with their ``moving_region`` sums replaced by the scores (``region_scores``)."""
        sums = {key: metrics.pop(key) for key in SUMS if key in metrics}
        return {**metrics, **(region_scores(sums, MIN_MSE) if len(sums) == len(SUMS) else {})}

    def _warn_near_layer(self, views: List[Dict[str, float]]) -> None:
        labelled = [(self.model.eval_views.label(int(view["view"])), view) for view in views if "view" in view]
        warning = near_layer_warning(labelled, float(self.model.training_depth))
        if warning:
            CONSOLE.log(f"[yellow]{warning}")

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        """The datamanager's and the model's callbacks, the viewer tracking's (a training step makes its kept
        features stale), and the gear-assignment updates (Sec 4.3) when the model has more than one gear."""
        after_step = [TrainingCallbackLocation.AFTER_TRAIN_ITERATION]
        callbacks = super().get_training_callbacks(training_callback_attributes)
        callbacks.append(TrainingCallback(after_step, self.viewer_tracking.forget))
        trainer = training_callback_attributes.trainer
        if not self.config.gear_updates.enabled or self.model.num_gears == 1 or trainer is None:
            return callbacks
        first_step = getattr(trainer, "_start_step", 0)
        updater = GearUpdater(
            self.config.gear_updates,
            self.model,
            self.datamanager,
            self.sam_backend,
            training_callback_attributes.optimizers.optimizers["gear_field"],
            self.gear_update_state,
            rays_per_batch=self.datamanager.config.train_num_rays_per_batch,
            first_step=first_step,
            last_step=first_step + trainer.config.max_num_iterations - 1,
            seed=trainer.config.machine.seed,
        )
        return callbacks + [TrainingCallback(after_step, updater)]
