"""Gear-assignment update pieces (Sec 4.3): prompts, Eq 10 targets and loss, the Eq 11 steps."""

from __future__ import annotations

import torch

from gear_nerfstudio.gear_field import GearField
from gear_nerfstudio.gear_updates import (
    level_targets,
    moving_patches,
    patch_prompts,
    patches_to_pixels,
    shift_gears,
    upshift_loss,
)


def test_patch_prompts_pick_the_highest_and_lowest_patches():
    loss = torch.full((32, 48), 1.0)
    loss[8:16, 24:32] = 5.0  # the worst patch
    loss[24:32, 0:8] = 0.0  # the best patch
    points, labels = patch_prompts(loss, patch_size=8, top_k=3)
    assert labels.tolist() == [1, 1, 1, 0, 0, 0]
    assert points[0].tolist() == [28.0, 12.0] and points[3].tolist() == [4.0, 28.0]


def test_level_targets_add_one_inside_the_mask_and_never_pass_the_top_gear():
    levels = torch.tensor([1, 2, 4, 1, 3])
    upshift = torch.tensor([True, True, True, False, False])
    assert level_targets(levels, upshift, num_gears=4).tolist() == [2, 3, 4, 1, 3]


def test_upshift_loss_is_a_weighted_hinge_to_the_target_interval():
    # Targets 2 ([1.25, 1.75]), 2, 1 ((-inf, 0.75]), 4 ([3.25, inf)) with margin 0.25.
    g = torch.tensor([1.0, 1.5, 1.0, 5.0])
    targets = torch.tensor([2, 2, 1, 4])
    weights = torch.tensor([1.0, 3.0, 2.0, 1.0])
    upshift = torch.tensor([True, True, False, False])
    expected = (0.25**2 * 1 + 0.0 * 3) / 4 + 2.0 * (0.25**2 * 2 + 0.0) / 3
    loss = upshift_loss(g, targets, weights, upshift, stay_weight=2.0, num_gears=4, margin=0.25)
    assert torch.isclose(loss, torch.tensor(expected))


def test_shift_gears_upshifts_the_masked_region_only():
    torch.manual_seed(0)
    field = GearField(torch.tensor([[-1.0] * 3, [1.0] * 3]), num_frames=4, num_gears=4, resolutions=(16,),
                      feature_dim=8, gear_resolution=16, sam_dim=8, sam_head_dim=None)
    optimizer = torch.optim.Adam(field.gear_function.parameters(), lr=0.02)
    points = torch.rand(2000, 3) * 2 - 1
    times = torch.rand(2000, 1)
    upshift = points[:, 0] > 0.3  # a moving object on one side of the scene
    weights = torch.ones(2000)
    for expected in (2, 3):
        levels = field.gear_levels(points, times)
        targets = level_targets(levels, upshift, field.num_gears)
        steps = shift_gears(field, optimizer, points, times, weights, upshift, targets, 1.0, 0.25, max_steps=300)
        new_levels = field.gear_levels(points, times)
        assert steps < 300
        assert bool((new_levels[upshift] == expected).all())
        assert bool((new_levels[~upshift] == 1).all())
    assert all(p.grad is None for p in field.gear_function.parameters())


def test_positive_prompts_come_only_from_moving_patches():
    loss = torch.full((32, 48), 1.0)
    loss[8:16, 24:32] = 5.0  # the worst patch, but static (texture not yet fitted)
    loss[16:24, 0:8] = 3.0  # high loss where something moves
    change = torch.zeros(32, 48)
    change[16:24, 0:8] = 0.2
    moving = moving_patches(change, patch_size=8, threshold=0.03)
    points, labels = patch_prompts(loss, patch_size=8, top_k=3, moving=moving)
    assert labels.tolist() == [1, 0, 0, 0]
    assert points[0].tolist() == [4.0, 20.0]
    # Nothing moves: no positive prompt at all.
    _, labels = patch_prompts(loss, patch_size=8, top_k=3, moving=torch.zeros_like(moving))
    assert labels.tolist() == [0, 0, 0]


def test_moving_patches_average_the_change_and_spread_back_to_pixels():
    change = torch.zeros(20, 20)
    change[0:8, 0:8] = 0.05  # whole patch moves
    change[8, 8] = 1.0  # one noisy pixel: mean over its 8 x 8 patch is 1/64 < 0.03
    moving = moving_patches(change, patch_size=8, threshold=0.03)
    assert moving.shape == (3, 3)
    assert moving.tolist() == [[True, False, False], [False, False, False], [False, False, False]]
    pixels = patches_to_pixels(moving, (20, 20), patch_size=8)
    assert pixels.shape == (20, 20)
    assert int(pixels.sum()) == 64 and bool(pixels[:8, :8].all())
