"""Points triangulated from the training views at their poses (``data.sparse_points``) and the batches that carry
them (``GearDataManager``): depths against the synthetic scene's ray-cast truth, and colours against the images."""

from pathlib import Path

import numpy as np
import pytest
import torch
from nerfstudio.data.datasets.base_dataset import InputDataset

from gear_nerfstudio.data.datamanager import GearDataManagerConfig
from gear_nerfstudio.data.sparse_points import triangulate
from gear_nerfstudio.data_parsers.technicolor import TechnicolorDataParserConfig
from gear_nerfstudio.errors import InputError
from gear_nerfstudio.spread import evenly_spread
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene

pytestmark = pytest.mark.cost(5)


@pytest.fixture(scope="module")
def textured_scene(tmp_path_factory) -> Path:
    """A synthetic Technicolor capture (4 x 4 cameras, 2 frames) large enough for SIFT: 160 x 120."""
    root = tmp_path_factory.mktemp("sparse")
    return write_synthetic_scene(root / "scene", SyntheticSpec(dataset="technicolor", width=160, height=120, frames=2))


def test_instants_spread_over_the_window_and_the_share_is_checked_at_once():
    assert evenly_spread(30, 3) == [0, 14, 29]
    assert evenly_spread(2, 3) == [0, 1]
    assert evenly_spread(1, 3) == [0]
    for share in (-0.1, 1.0):
        with pytest.raises(InputError, match="sparse-depth-share must lie in"):
            GearDataManagerConfig(sparse_depth_share=share)


def test_triangulated_depths_are_the_scene_depths(textured_scene, tmp_path):
    outputs = TechnicolorDataParserConfig(data=textured_scene, cache_dir=tmp_path).setup().get_dataparser_outputs()
    frames = outputs.metadata["frame_ids"].tolist()
    rays = triangulate(InputDataset(outputs), [0, 1])
    assert len(rays) > 1000
    names, cameras = outputs.metadata["camera_names"], outputs.metadata["camera_ids"].tolist()
    truth = {name: np.load(textured_scene / "ground_truth" / f"{name}.npz")["depth"] for name in names}
    errors = []
    for (image, row, col), depth in zip(rays.indices.tolist(), rays.depth[:, 0].tolist()):
        true_depth = truth[names[cameras[image]]][frames[image], row, col]
        errors.append(abs(depth / outputs.dataparser_scale - true_depth) / true_depth)
    # The rig spans 0.2 units 4.5 units from the wall: 0.5 px is about 3 % of depth at 160 px (a median of 1.8 % seen),
    # and the wall's checkers repeat along the rig, so some points lie at a wrong repeat.
    assert np.median(errors) < 0.03
    assert np.mean(np.array(errors) < 0.1) > 0.8


def test_the_same_images_give_the_same_points_in_the_same_order(textured_scene, tmp_path):
    """Training draws its depth rays by their rows, so a run from a seed is repeatable only if they are."""
    outputs = TechnicolorDataParserConfig(data=textured_scene, cache_dir=tmp_path).setup().get_dataparser_outputs()
    first, *others = [triangulate(InputDataset(outputs), [0]) for _ in range(4)]
    for other in others:
        assert torch.equal(other.indices, first.indices) and torch.equal(other.depth, first.depth)


def test_batches_end_with_rays_through_points(textured_scene, tmp_path):
    config = GearDataManagerConfig(
        dataparser=TechnicolorDataParserConfig(data=textured_scene, cache_dir=tmp_path),
        train_num_rays_per_batch=64,
        use_sam_features=False,
        sparse_depth_share=0.25,
    )
    manager = config.setup(device="cpu", test_mode="val")
    rays, batch = manager.next_train(0)
    assert len(batch["indices"]) == len(batch["image"]) == len(rays) == 64
    depth = batch["sparse_depth"][:, 0]
    assert (depth[:48] == 0).all() and (depth[48:] > 0).all()
    for (image, row, col), colour in zip(batch["indices"][48:].tolist(), batch["image"][48:]):
        assert torch.allclose(colour, manager.train_dataset[image]["image"][row, col, :3])
    expected = manager.train_ray_generator(batch["indices"])
    assert torch.allclose(rays.origins, expected.origins) and torch.allclose(rays.directions, expected.directions)


def _ray_outputs(weights: torch.Tensor, bins: torch.Tensor) -> dict:
    """Outputs of one sampling level for rays with these weights on the bins between these edges."""
    from nerfstudio.cameras.rays import Frustums, RaySamples

    rays, samples = weights.shape
    edges = bins.expand(rays, samples + 1)[..., None]
    frustums = Frustums(
        origins=torch.zeros(rays, samples, 3), directions=torch.ones(rays, samples, 3) / 3**0.5,
        starts=edges[:, :-1], ends=edges[:, 1:], pixel_area=torch.ones(rays, samples, 1),
    )  # fmt: skip
    weights = weights[..., None]
    depth = (weights * (edges[:, :-1] + edges[:, 1:]) / 2).sum(1)
    return {"weights_list": [weights], "ray_samples_list": [RaySamples(frustums=frustums)], "depth": depth}


def test_the_sparse_depth_loss_is_lowest_with_the_weight_at_the_point():
    from gear_nerfstudio.model.losses import GearLosses, LossWeights

    losses = GearLosses(LossWeights(), renderer=None, proposal_networks=[])
    bins = torch.linspace(0.1, 2.0, 39)
    target = torch.tensor([[1.0]])

    def loss_with_weight_at(depth: float) -> float:
        weights = torch.zeros(1, 38)
        weights[0, int(torch.searchsorted(bins, torch.tensor(depth))) - 1] = 1.0
        return float(losses.sparse_depth(_ray_outputs(weights, bins), target))

    assert loss_with_weight_at(1.0) < min(loss_with_weight_at(0.5), loss_with_weight_at(1.5))
    # a point past the far plane, or none, adds nothing
    assert float(losses.sparse_depth(_ray_outputs(torch.full((1, 38), 1 / 38), bins), torch.tensor([[2.5]]))) == 0
    assert float(losses.sparse_depth(_ray_outputs(torch.full((1, 38), 1 / 38), bins), torch.tensor([[0.0]]))) == 0
