"""Ray batches with SAM encoder features for L_SAM (Eq 9).

nerfstudio's VanillaDataManager, plus `batch["sam_features"]` (num_rays, C): the cached SAM embedding
of each ray's image, sampled bilinearly at the ray's pixel centre. The pipeline hands over its SAM backend
(`attach_sam`); its encoder then runs once per image (`SamFeatureCache`); batches read only the cells they
need from disk, so RAM stays bounded however long the video is, and image-subset sampling
(train_num_images_to_sample_from) works unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional, Tuple, Type

from jaxtyping import Float, Int
from torch import Tensor

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig

from gear_nerfstudio.sam.interface import Embedding, SamBackend
from gear_nerfstudio.sam.feature_cache import SamFeatureCache


@dataclass
class GearDataManagerConfig(VanillaDataManagerConfig):
    """VanillaDataManager with SAM feature targets (Sec 4.2)."""

    _target: Type = field(default_factory=lambda: GearDataManager)
    sam_cache_dir: Optional[Path] = None
    """Where encoder features are cached; default ~/.cache/gear-nerfstudio/sam (or $XDG_CACHE_HOME)."""
    use_sam_features: bool = True
    """Add SAM features to ray batches (Eq 9). False: the paper's "w/o embedding" ablation, no encoder run."""


class GearDataManager(VanillaDataManager):
    """Adds `sam_features` to train and eval ray batches from feature caches of the pipeline's SAM backend."""

    config: GearDataManagerConfig
    feature_cache: Optional[SamFeatureCache] = None
    eval_feature_cache: Optional[SamFeatureCache] = None

    def attach_sam(self, backend: SamBackend) -> None:
        """Feature caches of the training and evaluation images for a SAM backend; the images not yet cached
        are encoded now, unless SAM features are off or no dataset is loaded (``test_mode`` 'inference')."""
        encode = self.config.use_sam_features and self.test_mode != "inference"
        caches = []
        for dataset, description in ((self.train_dataset, "training"), (self.eval_dataset, "evaluation")):
            cache = SamFeatureCache(backend, self.config.sam_cache_dir, dataset.image_filenames)
            if encode:
                cache.precompute(description=f"SAM features of the {description} images ({backend.name})")
            caches.append(cache)
        self.feature_cache, self.eval_feature_cache = caches

    @staticmethod
    def _attached(cache: Optional[SamFeatureCache]) -> SamFeatureCache:
        if cache is None:
            raise RuntimeError(
                "GearDataManager has no SAM backend: use it in a GearPipelineConfig (which attaches one), or set "
                "use_sam_features False"
            )
        return cache

    def _sam_features(
        self, cache: Optional[SamFeatureCache], indices: Int[Tensor, "num_rays 3"]
    ) -> Float[Tensor, "num_rays sam_dim"]:
        """Targets S(r) of Eq 9 at the pixel centres of rays given as rows (image index, y, x)."""
        # Pixels of a dataset resized by camera_res_scale_factor, in the coordinates of the image file.
        pixels = (indices[:, [2, 1]].float() + 0.5) / self.config.camera_res_scale_factor
        return self._attached(cache).features_at(indices[:, 0], pixels, device=self.device)

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
        return self._attached(self.feature_cache).embedding(self.train_dataset.image_filenames[image_index])
