"""Ray importance sampling (ISG, `gear_nerfstudio.data.importance`): the weights, the draws, and what they do to
the training batches of the real capture."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from gear_nerfstudio.data.datamanager import GearDataManagerConfig
from gear_nerfstudio.data.importance import IsgDataset, isg_weight, weighted_pixels
from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from tests.conftest import SHARED_REAL

VIDEO = SHARED_REAL / "panoptic_basketball_video"
MASKS = SHARED_REAL / "panoptic_basketball_video_masks"


def test_the_weight_is_the_geman_mcclure_function_of_the_change_from_the_median_at_least_the_floor():
    median = torch.full((3, 1, 3), 0.5)
    image = median + torch.tensor([0.0, 0.02, 0.5])[:, None, None]
    weight = isg_weight(image, median, gamma=0.02, floor=0.1)
    # unchanged: the floor; changed by gamma: 1/2; changed by 0.5: 0.25 / (0.25 + 0.0004)
    torch.testing.assert_close(weight.flatten(), torch.tensor([0.1, 0.5, 0.25 / 0.2504]))


def test_pixels_are_drawn_in_proportion_to_their_weights():
    weights = torch.full((3, 4, 5), 0.1)
    weights[1, 2, 3] = 2.0
    weights[2] = 0.4
    torch.manual_seed(0)
    rows = weighted_pixels(weights, 200_000)
    assert rows.shape == (200_000, 3)
    assert (rows >= 0).all() and (rows < torch.tensor([3, 4, 5])).all()
    counts = torch.zeros_like(weights)
    counts.index_put_(tuple(rows.T), torch.ones(len(rows)), accumulate=True)
    expected = weights / weights.sum() * len(rows)
    assert (counts - expected).abs().max() < 5 * expected.sqrt().max()


def people_mask(dataset, image_index: int, shape) -> np.ndarray:
    """The person mask of a training image of the real capture (False where its camera has none)."""
    metadata = dataset.metadata
    camera = metadata["camera_names"][int(metadata["camera_ids"][image_index])]
    frame = metadata["frame_numbers"][int(metadata["frame_ids"][image_index])]
    path = MASKS / camera / f"{frame:05d}.png"
    if not path.exists():
        return np.zeros(shape, bool)
    return np.asarray(Image.open(path).convert("L").resize(shape[::-1], Image.NEAREST)) > 127


def shares_on_people(tmp_path: Path, isg_gamma, start: int, steps: int) -> tuple:
    """Shares of the training rays that fall on the people, before and from step ``start`` (``steps`` batches each),
    and the people's share of the pixels of the images the rays came from; with the dataset."""
    manager = GearDataManagerConfig(
        dataparser=Neural3DVideoDataParserConfig(
            data=VIDEO, downscale_factor=4, frame_count=10, cache_dir=tmp_path / "frames"
        ),
        use_sam_features=False,
        isg_gamma=isg_gamma,
        isg_start_step=start,
        train_num_rays_per_batch=1024,
        train_num_images_to_sample_from=40,
        train_num_times_to_repeat_images=5,
    ).setup(device="cpu", test_mode="val")
    dataset = manager.train_dataset
    torch.manual_seed(0)
    masks: dict = {}
    shares = []
    for first in (start - steps, start):
        on_people = 0
        for step in range(first, first + steps):
            _, batch = manager.next_train(step)
            for index, y, x in batch["indices"].tolist():
                if index not in masks:
                    shape = (int(dataset.cameras.height[index]), int(dataset.cameras.width[index]))
                    masks[index] = people_mask(dataset, index, shape)
                on_people += bool(masks[index][y, x])
        shares.append(on_people / (steps * 1024))
    pixel_share = float(np.mean([mask.mean() for mask in masks.values()]))
    return shares[0], shares[1], pixel_share, dataset


@pytest.mark.skipif(not VIDEO.exists(), reason="the shared real capture is not on this machine")
def test_the_people_of_the_real_capture_get_several_times_their_share_of_the_rays_after_the_uniform_start(tmp_path):
    before, after, people, dataset = shares_on_people(tmp_path, 2e-2, start=20, steps=10)
    assert isinstance(dataset, IsgDataset)
    assert before < 1.5 * people, (before, people)
    assert after > 2.5 * people, (after, people)
    _, uniform, people, dataset = shares_on_people(tmp_path, None, start=20, steps=10)
    assert not isinstance(dataset, IsgDataset)
    assert uniform < 1.5 * people, (uniform, people)
