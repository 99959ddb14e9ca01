"""Ray batches with SAM encoder features for L_SAM (Eq 9).

nerfstudio's VanillaDataManager, plus `batch["sam_features"]` (num_rays, C): the cached SAM embedding
of each ray's image, sampled bilinearly at the ray's pixel centre. The encoder runs once per image at
start-up (`SamFeatureCache`); batches read only the cells they need from disk, so RAM stays bounded
however long the video is, and image-subset sampling (train_num_images_to_sample_from) works unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Tuple, Type

from jaxtyping import Float, Int
from torch import Tensor

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes

from gear_nerfstudio.sam.config import SamConfig
from gear_nerfstudio.sam.interface import Embedding, SamBackend
from gear_nerfstudio.sam_features import SamFeatureCache


@dataclass
class GearDataManagerConfig(VanillaDataManagerConfig):
    """VanillaDataManager with SAM feature targets (Sec 4.2)."""

    _target: Type = field(default_factory=lambda: GearDataManager)
    sam: SamConfig = field(default_factory=SamConfig)
    """SAM backend: its encoder gives the targets S(r) of Eq 9; its decoder serves Sec 4.3 and 4.5."""
    sam_cache_dir: Optional[Path] = None
    """Where encoder features are cached; default ~/.cache/gear-nerfstudio/sam (or $XDG_CACHE_HOME)."""
    use_sam_features: bool = True
    """Add SAM features to ray batches (Eq 9). False: the paper's "w/o embedding" ablation, no encoder run."""


class GearDataManager(VanillaDataManager):
    """Adds `sam_features` to train and eval ray batches; owns the SAM backend and its feature caches."""

    config: GearDataManagerConfig
    feature_cache: SamFeatureCache
    eval_feature_cache: SamFeatureCache
    _sam_backend: Optional[SamBackend] = None

    @property
    def sam_backend(self) -> SamBackend:
        """The SAM backend, created on first use (by `setup_train`, so that its errors surface at start-up)."""
        if self._sam_backend is None:
            self._sam_backend = self.config.sam.setup()
        return self._sam_backend

    def _cache(self, image_filenames: List[Path], description: str) -> SamFeatureCache:
        cache = SamFeatureCache(self.sam_backend, self.config.sam_cache_dir, image_filenames)
        if self.config.use_sam_features:
            cache.precompute(description=f"SAM features of the {description} images ({self.sam_backend.name})")
        return cache

    def setup_train(self) -> None:
        """Create the SAM backend, encode the training images not yet cached, then nerfstudio's setup."""
        self.feature_cache = self._cache(self.train_dataset.image_filenames, "training")
        super().setup_train()

    def setup_eval(self) -> None:
        """Encode the evaluation images not yet cached, then nerfstudio's setup."""
        self.eval_feature_cache = self._cache(self.eval_dataset.image_filenames, "evaluation")
        super().setup_eval()

    def _sam_features(
        self, cache: SamFeatureCache, indices: Int[Tensor, "num_rays 3"]
    ) -> Float[Tensor, "num_rays sam_dim"]:
        """Targets S(r) of Eq 9 at the pixel centres of rays given as rows (image index, y, x)."""
        # Pixels of a dataset resized by camera_res_scale_factor, in the coordinates of the image file.
        pixels = (indices[:, [2, 1]].float() + 0.5) / self.config.camera_res_scale_factor
        return cache.features_at(indices[:, 0], pixels, device=self.device)

    def next_train(self, step: int) -> Tuple[RayBundle, Dict]:
        """A training ray batch, with `sam_features` unless `use_sam_features` is off."""
        ray_bundle, batch = super().next_train(step)
        if self.config.use_sam_features:
            batch["sam_features"] = self._sam_features(self.feature_cache, batch["indices"])
        return ray_bundle, batch

    def next_eval(self, step: int) -> Tuple[RayBundle, Dict]:
        """An evaluation ray batch, with `sam_features` unless `use_sam_features` is off."""
        ray_bundle, batch = super().next_eval(step)
        if self.config.use_sam_features:
            batch["sam_features"] = self._sam_features(self.eval_feature_cache, batch["indices"])
        return ray_bundle, batch

    def train_embedding(self, image_index: int) -> Embedding:
        """The whole SAM embedding of training image `image_index` (gear update, Sec 4.3), computed if missing."""
        return self.feature_cache.embedding(self.train_dataset.image_filenames[image_index])

    def get_training_callbacks(
        self, training_callback_attributes: TrainingCallbackAttributes
    ) -> List[TrainingCallback]:
        """No callbacks; checks at pipeline set-up that the model's SAM head predicts the backend's C."""
        pipeline = training_callback_attributes.pipeline
        sam_dim = None if pipeline is None else getattr(pipeline.model.config, "sam_dim", None)
        if self.config.use_sam_features and sam_dim is not None and sam_dim != self.sam_backend.embedding_dim:
            raise ValueError(
                f"The model's sam_dim is {sam_dim} but the SAM backend {self.sam_backend.name!r} gives "
                f"{self.sam_backend.embedding_dim}-dimensional features: set --pipeline.model.sam-dim "
                f"{self.sam_backend.embedding_dim}."
            )
        return []
