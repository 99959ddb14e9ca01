"""What moves in an evaluation view, and the scores inside and outside it (``model/moving_region.py``): on frames
made here, and on the real capture against its person masks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from nerfstudio.data.datasets.base_dataset import InputDataset

from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from gear_nerfstudio.model.metrics import MIN_MSE
from gear_nerfstudio.model.moving_region import EvalViews, changed_pixels, region_scores, region_sums
from tests.conftest import SHARED_REAL

VIDEO = SHARED_REAL / "panoptic_basketball_video"
MASKS = SHARED_REAL / "panoptic_basketball_video_masks"


def test_changed_pixels_find_a_moved_square_and_not_the_noise():
    """Sensor noise of +-0.03 is not motion; a square that changed colour is, with a margin of a few pixels."""
    generator = torch.Generator().manual_seed(0)
    background = torch.rand(40, 60, 3, generator=generator)
    image = (background + (torch.rand(40, 60, 3, generator=generator) - 0.5) * 0.06).clamp(0, 1)
    image[10:20, 30:40] = 1 - background[10:20, 30:40]
    region = changed_pixels(image, background)
    assert region[10:20, 30:40].all()
    rows, cols = torch.nonzero(region, as_tuple=True)
    assert rows.min() >= 6 and rows.max() <= 23 and cols.min() >= 26 and cols.max() <= 43


def test_region_scores_pool_the_pixels_and_leave_an_empty_region_missing():
    image = torch.zeros(8, 10, 3)
    rgb = image.clone()
    moving = torch.zeros(8, 10, dtype=torch.bool)
    moving[2:6, 2:6] = True
    rgb[moving] = 0.1  # squared error 0.01: 20 dB inside, exact (the MSE floor) outside
    levels = torch.ones(8, 10, dtype=torch.long)
    levels[2:4, 2:6] = 3  # half the moving pixels above gear 1
    levels[0, 0] = 2  # one of the 64 others
    scores = region_scores(region_sums(rgb, image, moving, levels), MIN_MSE)
    assert scores["psnr_moving"] == pytest.approx(20.0, abs=1e-4)
    assert scores["psnr_static"] == pytest.approx(100.0)
    assert scores["moving_at_gear_2"] == pytest.approx(0.5)
    assert scores["static_at_gear_1"] == pytest.approx(63 / 64)
    empty = region_scores(region_sums(rgb, image, None, levels), MIN_MSE)
    assert set(empty) == {"psnr_static", "static_at_gear_1"}


def held_out_views(tmp_path, frame_start: int, moving_masks=None) -> EvalViews:
    config = Neural3DVideoDataParserConfig(
        data=VIDEO, held_out_camera="cam20", frame_start=frame_start, frame_count=30, downscale_factor=2,
        cache_dir=tmp_path / "frames", moving_masks=moving_masks,
    )  # fmt: skip
    outputs = config.setup().get_dataparser_outputs("test")
    return EvalViews(InputDataset(outputs), outputs.metadata["moving_masks"])


@pytest.mark.skipif(not MASKS.is_dir(), reason="shared real data not present")
@pytest.mark.parametrize("frame_start", [0, 60])
def test_the_colour_change_of_the_real_capture_finds_its_people(tmp_path, frame_start):
    """Without masks, the region is where the held-out view's colour changes over the window. On the 31-camera
    capture (cam20 at 304x168) it overlaps the person masks (both dilated by 2 px) with an IoU of 0.69 on frames 0-29,
    where the threshold was chosen, and 0.66 on frames 60-89; each window must keep 0.6."""
    change = held_out_views(tmp_path, frame_start)
    masks = held_out_views(tmp_path, frame_start, MASKS)
    both = either = 0
    for index in range(len(change)):
        image = torch.from_numpy(change.dataset.get_numpy_image(index)[..., :3].astype(np.float32) / 255)
        found, truth = change.moving(index, image), masks.moving(index, image)
        both += int((found & truth).sum())
        either += int((found | truth).sum())
    assert both / either > 0.6, both / either
    assert masks.label(0) == f"cam20 frame {frame_start}"


@pytest.mark.skipif(not MASKS.is_dir(), reason="shared real data not present")
def test_a_missing_mask_stops_in_one_line_that_names_it(tmp_path):
    folder = tmp_path / "masks" / "cam20"
    folder.mkdir(parents=True)
    for number in range(29):  # frame 29 has none
        (folder / f"{number:05d}.png").write_bytes((MASKS / "cam20" / f"{number:05d}.png").read_bytes())
    with pytest.raises(DatasetError, match=r"cam20/00029\.png: no mask of what moves for the held-out camera at frame 29"):
        held_out_views(tmp_path, 0, tmp_path / "masks")
