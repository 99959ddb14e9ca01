"""The Gear-NeRF pipeline: nerfstudio's VanillaPipeline that owns the SAM backend (Sec 4.2), the gear-update
callback (Sec 4.3), the viewer's tracking controls (Sec 4.5) and its resolutions (``viewer_speed``).

The backend is built once and handed to the datamanager (its encoder gives the targets of Eq 9), to the gear
updates (its decoder gives the upshift masks) and to tracking (its decoder gives the tracked masks). The
updates work on the model and the datamanager through narrow interfaces (``gears.updater.UpdateTarget`` and
``TrainingViews``), so that neither the model nor the datamanager knows about them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Type

from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from torch.cuda.amp.grad_scaler import GradScaler

from gear_nerfstudio.data.datamanager import GearDataManager, GearDataManagerConfig
from gear_nerfstudio.errors import InputError
from gear_nerfstudio.gears.config import GearUpdateConfig
from gear_nerfstudio.gears.schedule import GearUpdateState
from gear_nerfstudio.gears.updater import GearUpdater
from gear_nerfstudio.model.gear_model import GearNeRFModelConfig
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
        self.gear_update_state = GearUpdateState(self.model.gear_assignment(), config.gear_updates.views_per_update)
        self.viewer_tracking = ViewerTracking(self.model, self.sam_backend)
        self.model.render_hooks.append(self.viewer_tracking.render_hook)
        self.viewer_speed = ViewerSpeed(self.model)

    def get_average_eval_image_metrics(
        self, step: Optional[int] = None, output_path: Optional[Path] = None, get_std: bool = False
    ) -> Dict[str, float]:
        """nerfstudio's averages over the held-out images (ns-eval); the spread of a single image cannot be
        computed and is left out instead of being written as NaN."""
        metrics = super().get_average_eval_image_metrics(step, output_path, get_std)
        return {key: value for key, value in metrics.items() if not (key.endswith("_std") and math.isnan(value))}

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
