"""Ray batches with SAM encoder features for L_SAM (Eq 9), and rays through triangulated points.

nerfstudio's VanillaDataManager, plus `batch["sam_features"]` (num_rays, C): the cached SAM embedding
of each ray's image, sampled bilinearly at the ray's pixel centre. The pipeline hands over its SAM backend
(`attach_sam`); its encoder then runs once per image (`SamFeatureCache`); batches read only the cells they
need from disk, so RAM stays bounded however long the video is, and image-subset sampling
(train_num_images_to_sample_from) works unchanged.

With `sparse_depth_share`, the last rays of a training batch go through points triangulated from the training views
(``sparse_points``), and `batch["sparse_depth"]` holds their depth (0 for the other rays).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, Optional, Tuple, Type

import torch
from jaxtyping import Float, Int
from torch import Tensor

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.utils.rich_utils import CONSOLE

from gear_nerfstudio.data.sparse_points import SparseDepth, triangulate
from gear_nerfstudio.errors import InputError
from gear_nerfstudio.sam.interface import Embedding, SamBackend
from gear_nerfstudio.sam.feature_cache import SamFeatureCache
from gear_nerfstudio.spread import evenly_spread


@dataclass
class GearDataManagerConfig(VanillaDataManagerConfig):
    """VanillaDataManager with SAM feature targets (Sec 4.2)."""

    _target: Type = field(default_factory=lambda: GearDataManager)
    sam_cache_dir: Optional[Path] = None
    """Where encoder features are cached; default ~/.cache/gear-nerfstudio/sam (or $XDG_CACHE_HOME)."""
    use_sam_features: bool = True
    """Add SAM features to ray batches (Eq 9). False: the paper's "w/o embedding" ablation, no encoder run."""
    sparse_depth_share: float = 0.0
    """Share of each batch's rays drawn through points triangulated from the training views; 0: none."""
    sparse_depth_instants: int = 3
    """Instants of the window whose training views are triangulated, spread evenly."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if not 0 <= self.sparse_depth_share < 1:
            share = self.sparse_depth_share
            raise InputError(f"--pipeline.datamanager.sparse-depth-share must lie in [0, 1), got {share}")


class GearDataManager(VanillaDataManager):
    """Adds `sam_features` to train and eval ray batches from feature caches of the pipeline's SAM backend."""

    config: GearDataManagerConfig
    feature_cache: Optional[SamFeatureCache] = None
    eval_feature_cache: Optional[SamFeatureCache] = None
    sparse_depth: Optional[SparseDepth] = None

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
        """A training ray batch, with `sam_features` unless `use_sam_features` is off, and with rays through
        triangulated points when `sparse_depth_share` is set and there are some."""
        ray_bundle, batch = super().next_train(step)
        if self.config.sparse_depth_share > 0 and len(self.triangulated()):
            ray_bundle, batch = self._with_sparse_depth(batch)
        if self.config.use_sam_features:
            batch["sam_features"] = self._sam_features(self.feature_cache, batch["indices"])
        return ray_bundle, batch

    def triangulated(self) -> SparseDepth:
        """The rays through points triangulated from the training views (``sparse_points``), made at the first call."""
        if self.sparse_depth is None:
            at = evenly_spread(self.train_dataset.metadata.get("num_frames", 1), self.config.sparse_depth_instants)
            self.sparse_depth = triangulate(self.train_dataset, at)
            if len(self.sparse_depth):
                CONSOLE.log(f"Sparse depth: {len(self.sparse_depth)} rays through points triangulated at frames {at}")
            else:
                CONSOLE.log(
                    f"[yellow]Sparse depth: no point triangulated at frames {at} (pinhole cameras only); training "
                    "without it"
                )
        return self.sparse_depth

    def _with_sparse_depth(self, batch: Dict) -> Tuple[RayBundle, Dict]:
        """The batch with its last ``sparse_depth_share`` of rays replaced by rays through triangulated points;
        ``batch["sparse_depth"]`` is their depth (0 for the other rays)."""
        count = round(self.config.sparse_depth_share * len(batch["indices"]))
        kept = len(batch["indices"]) - count
        rays = self.triangulated().sample(count)
        indices = torch.cat([batch["indices"][:kept], rays.indices.to(batch["indices"])])
        batch = {
            **batch,
            "indices": indices,
            "image": torch.cat([batch["image"][:kept], rays.rgb.to(batch["image"])]),
            "sparse_depth": torch.cat([torch.zeros(kept, 1), rays.depth]),
        }
        return self.train_ray_generator(indices), batch

    def next_eval(self, step: int) -> Tuple[RayBundle, Dict]:
        """An evaluation ray batch, with `sam_features` unless `use_sam_features` is off."""
        ray_bundle, batch = super().next_eval(step)
        if self.config.use_sam_features:
            batch["sam_features"] = self._sam_features(self.eval_feature_cache, batch["indices"])
        return ray_bundle, batch

    def train_embedding(self, image_index: int) -> Embedding:
        """The whole SAM embedding of training image `image_index` (gear update, Sec 4.3), computed if missing."""
        return self._attached(self.feature_cache).embedding(self.train_dataset.image_filenames[image_index])
