"""Gear-assignment updates (Sec 4.3): prompts, Eq 10 targets and loss, the Eq 11 steps, and the whole loop in
nerfstudio's trainer (updates, both stop rules, resume)."""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path
from typing import Optional, Tuple

import numpy as np
import pytest
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.scripts.train import _set_random_seed

from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from gear_nerfstudio.fields.gear_field import GearField
from gear_nerfstudio.gears.config import GearUpdateConfig
from gear_nerfstudio.gears.loss_maps import moving_patches, moving_pixels, patch_prompts, patches_to_pixels
from gear_nerfstudio.gears.schedule import GearUpdateState, NoGearUpdates, describe_plan, planned_updates
from gear_nerfstudio.gears.updater import GearUpdater
from gear_nerfstudio.gears.upshift import UpdatePoints, level_targets, select_points, shift_gears, upshift_loss
from gear_nerfstudio.method_configs.gear_nerf import gear_nerf, gear_nerf_small
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, rig_for, write_synthetic_scene

pytestmark = pytest.mark.cost(360)


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
    settings = GearUpdateConfig(stay_weight=2.0, margin=0.25)
    loss = upshift_loss(g, targets, UpdatePoints(g, g, weights, upshift), 4, settings)
    assert torch.isclose(loss, torch.tensor(expected))


def test_s_static_is_a_weighted_mean_of_its_own_in_the_loss_and_in_the_point_draws():
    g = torch.tensor([1.0, 1.5, 1.0, 5.0, 2.0, 0.5])
    targets = torch.tensor([2, 2, 1, 4, 1, 1])
    weights = torch.tensor([1.0, 3.0, 2.0, 1.0, 4.0, 1.0])
    upshift = torch.tensor([True, True, False, False, False, False])
    static = torch.tensor([False, False, False, False, True, True])  # targets 1: (-inf, 0.75]
    expected = (0.25**2 * 1) / 4 + 2.0 * (0.25**2 * 2) / 3 + 0.5 * (1.25**2 * 4) / 5
    points = UpdatePoints(g, g, weights, upshift, static=static)
    loss = upshift_loss(g, targets, points, 4, GearUpdateConfig(stay_weight=2.0, margin=0.25, static_weight=0.5))
    assert torch.isclose(loss, torch.tensor(expected))
    # Each set is drawn on its own: a large S_static does not crowd out S_stay.
    weights = torch.ones(300)
    upshift, static = torch.arange(300) < 10, torch.arange(300) >= 20
    index = torch.arange(300)
    points = UpdatePoints(index, index, weights, upshift, static=static)
    index = select_points(points, 50, torch.Generator().manual_seed(0)).positions
    assert (index < 10).sum() == 10 and ((index >= 10) & (index < 20)).sum() == 10 and (index >= 20).sum() == 50


def test_s_static_keeps_the_static_points_that_share_plane_cells_with_the_upshift_at_gear_1():
    """Eq 4 is a sum of products of planes: upshifting an object also lifts points elsewhere that share its plane
    cells (here a box at the object's x and y, below it in z: the planes h'_xy, k'_xt and k'_yt are shared; all of
    it moved up with the object with 8 gear channels, 62 % with 32). Holding that box in S_static keeps it at gear 1
    while the object still moves up."""
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(3000, 3, generator=generator) * 2 - 1
    times = torch.rand(3000, 1, generator=generator)
    upshift = (points[:, 0] > 0.3) & (points[:, 1] > 0.3) & (points[:, 2] > 0.3)
    slab = (points[:, 0] > 0.3) & (points[:, 1] > 0.3) & (points[:, 2] < -0.3)
    stay = points[:, 0] < -0.3  # what the update's own views see outside the object
    lifted = {}
    for held in (False, True):
        torch.manual_seed(0)
        field = GearField(torch.tensor([[-1.0] * 3, [1.0] * 3]), num_frames=4, num_gears=4, resolutions=(16,),
                          feature_dim=8, gear_resolution=16, sam_dim=8, sam_head_dim=None)
        optimizer = torch.optim.Adam(field.gear_function.parameters(), lr=0.02)
        used = upshift | stay | (slab if held else torch.zeros_like(slab))
        static = slab[used] if held else None
        levels = field.gear_levels(points[used], times[used])
        targets = level_targets(levels, upshift[used], field.num_gears, static)
        chosen = UpdatePoints(points[used], times[used], torch.ones(int(used.sum())), upshift[used], static=static)
        settings = GearUpdateConfig(stay_weight=1.0, static_weight=1.0, margin=0.25, max_steps=300)
        shift_gears(field, optimizer, chosen, targets, settings)
        levels = field.gear_levels(points, times)
        assert bool((levels[upshift] == 2).all()) and bool((levels[stay] == 1).all())
        lifted[held] = float((levels[slab] > 1).float().mean())
    assert lifted[False] > 0.3 and lifted[True] == 0.0, lifted


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
        settings = GearUpdateConfig(stay_weight=1.0, margin=0.25, max_steps=300)
        steps = shift_gears(field, optimizer, UpdatePoints(points, times, weights, upshift), targets, settings)
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


# Sec 4.3 as a whole: nerfstudio's Trainer, in this process, on a small synthetic scene with ground truth.

LOOP_SPEC = SyntheticSpec(dataset="n3d", width=64, height=48, frames=6, cameras=5, motion="mixed")
LOOP_ITERATIONS = 280
EPOCH = 20
AFTER = 4
"""Iterations per epoch of the loop test and epochs after the updates (L'): updates every 60 iterations while 80
remain (60, 120, 180); the run ends 40 iterations after the last update's review at 240 (the gear function no longer
changes after the last update)."""


def loop_config(root: Path, name: str, iterations: int, load_dir: Optional[Path] = None, **updates) -> TrainerConfig:
    config = copy.deepcopy(gear_nerf_small.config)
    config.output_dir, config.experiment_name, config.timestamp = root / "runs", "loop", name
    config.machine.device_type, config.vis = "cpu", "tensorboard"
    config.max_num_iterations, config.load_dir = iterations, load_dir
    config.steps_per_save, config.save_only_latest_checkpoint = 100, False
    config.steps_per_eval_batch = config.steps_per_eval_image = config.steps_per_eval_all_images = 0
    config.pipeline.datamanager.dataparser = Neural3DVideoDataParserConfig(data=root / "scene", cache_dir=root / "cache")
    config.pipeline.datamanager.sam_cache_dir = root / "sam"
    config.pipeline.gear_updates = dataclasses.replace(
        config.pipeline.gear_updates, iterations_per_epoch=EPOCH, epochs_after_updates=AFTER, **updates
    )
    return config


def train(config: TrainerConfig) -> Tuple[Trainer, GearUpdater]:
    """nerfstudio's train loop for one process (``ns-train``'s ``train_loop``, seeds included: nerfstudio's image
    loader orders the cached images with Python's ``random``), returning the trainer and updater."""
    _set_random_seed(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    trainer.train()
    updater = next(c.func for c in trainer.callbacks if isinstance(c.func, GearUpdater))
    return trainer, updater


@pytest.fixture(scope="module")
def loop_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("gear-loop")
    write_synthetic_scene(root / "scene", LOOP_SPEC)
    # The guard reviews every update but undoes none (its undo has its own test below): whether a review on this
    # toy run finds its 4 views 0.1 dB worse depends on the machine's rounding. Here all 20 runs tried
    # (seeds, CPU instruction sets) gained 1.2-3.3 dB at each review; one CI run undid update 2.
    return root, *train(loop_config(root, "first", LOOP_ITERATIONS, guard_tolerance=math.inf))


def ground_truth_gear_levels(root: Path, trainer: Trainer) -> Tuple[np.ndarray, np.ndarray]:
    """Gear levels (Eq 5) of the true surface points that the held-out camera cam00 sees at every frame (from the
    scene's ground-truth depth), and which of them lie on a moving object."""
    truth = np.load(root / "scene" / "ground_truth" / "cam00.npz")
    camera = rig_for(LOOP_SPEC)[0]
    rows, cols = np.mgrid[0 : camera.height, 0 : camera.width]
    origins, directions = camera.rays(np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5], axis=-1))
    outputs = trainer.pipeline.datamanager.train_dataparser_outputs
    transform = outputs.dataparser_transform.double()
    field = trainer.pipeline.model.field
    levels = []
    for frame, depth in enumerate(truth["depth"]):
        world = torch.from_numpy(origins + directions * depth.reshape(-1, 1))
        scene = ((world @ transform[:, :3].T + transform[:, 3]) * outputs.dataparser_scale).float()
        times = torch.full((len(scene), 1), frame / (LOOP_SPEC.frames - 1))
        levels.append(field.gear_levels(scene, times).reshape(depth.shape).numpy())
    return np.stack(levels), truth["motion"] > 0


def test_updates_move_moving_objects_up_and_keep_the_static_scene_in_gear_1(loop_run):
    """Three updates of 4 views each on a 280-iteration run. Over seeds 42-49 on one machine, with the earlier
    defaults (8 gear channels, no S_static, the stand-in's masks), the true surfaces of
    the moving spheres were at gear >= 2 for 73-97 % of cam00's pixels and the static ones at gear 1 for 91-95 %;
    on CI's machine seed 42 gave 61 % (91 % here), so the bound is a majority.
    Without updates the first share is 0, and an updater that upshifts everything brings the second towards 0."""
    root, trainer, updater = loop_run
    assert updater.planned == [60, 120, 180]
    assert int(updater.state.num_updates) == 3 and bool(updater.state.finished)  # then the L' rule ended them
    levels, moving = ground_truth_gear_levels(root, trainer)
    assert moving.mean() > 0.03  # the spheres cover part of the held-out view
    assert (levels[moving] >= 2).mean() >= 0.5  # most of the moving surface
    assert (levels[~moving] == 1).mean() >= 0.85


def test_updates_end_when_the_loss_maps_are_flat(loop_run):
    """The variance rule: an update whose loss maps vary less than the threshold ends the updates, unchanged."""
    _, trainer, updater = loop_run
    pipeline = trainer.pipeline
    flat = GearUpdater(
        dataclasses.replace(updater.config, variance_threshold=1e9), pipeline.model, pipeline.datamanager,
        pipeline.sam_backend, updater.optimizer, GearUpdateState(pipeline.model.gear_assignment(), 4), rays_per_batch=1024, first_step=0,
        last_step=LOOP_ITERATIONS - 1,
    )
    before = [p.detach().clone() for p in trainer.pipeline.model.field.gear_function.parameters()]
    stats = flat.update(60)
    assert stats["loss_map_variance"] < 1e9 and bool(flat.state.finished) and int(flat.state.num_updates) == 0
    assert all(torch.equal(p, b) for p, b in zip(trainer.pipeline.model.field.gear_function.parameters(), before))
    flat(120)  # finished: a later due step does nothing
    assert int(flat.state.num_updates) == 0


def test_with_the_built_in_stand_in_the_upshift_masks_are_the_loss_maps_high_rgb_loss_where_it_moves(loop_run):
    """mask_source 'auto' (the default) with the built-in stand-in is 'loss_threshold': the upshift mask is the RGB
    loss above its mean + k std, cut to the moving patches, without prompts; with k = 0 it grows."""
    _, trainer, updater = loop_run
    assert trainer.pipeline.config.gear_updates.mask_source == "auto" and updater.config.mask_source == "loss_threshold"
    config = updater.config
    sizes = []
    for k in (config.loss_threshold_std, 0.0):
        updater.config = dataclasses.replace(config, loss_threshold_std=k)
        try:
            loss_map = updater.loss_map(5)
            mask, points, labels = updater.upshift_mask(loss_map)
        finally:
            updater.config = config
        moving = moving_pixels(loss_map.change, config.patch_size, config.motion_threshold)
        values = loss_map.rgb_loss
        assert points is None and labels is None and bool(moving.any())
        assert torch.equal(mask, (values > values.mean() + k * values.std()) & moving)
        sizes.append(int(mask.sum()))
    assert 0 < sizes[0] < sizes[1], sizes


def test_s_static_rays_come_from_the_still_pixels_of_other_cameras_at_the_views_frame(loop_run):
    """S_static (``static_views``): per update view, other training cameras at its frame (at most ``static_views``),
    each with the view's S_stay count of rays through pixels outside every moving patch of its motion gate; none
    without the motion gate, which tells them."""
    _, trainer, updater = loop_run
    dataset = trainer.pipeline.datamanager.train_dataset
    camera_ids, frame_ids = dataset.metadata["camera_ids"], dataset.metadata["frame_ids"]
    config = updater.config
    loss_map = updater.loss_map(5)
    for static_views, expected in ((8, 3), (2, 2)):  # the loop scene trains 4 cameras: 3 others at each frame
        updater.config = dataclasses.replace(config, static_views=static_views)
        try:
            rays = updater.static_rays(loss_map, 40)
        finally:
            updater.config = config
        found = []
        for camera, pixels in rays:
            matches = [
                index for index in range(len(dataset))
                if torch.allclose(dataset.cameras.camera_to_worlds[index], camera.camera_to_worlds[0].cpu())
                and torch.allclose(dataset.cameras.times[index], camera.times[0].cpu())
            ]  # fmt: skip
            assert len(matches) == 1
            index = matches[0]
            assert int(frame_ids[index]) == int(frame_ids[5]) and int(camera_ids[index]) != int(camera_ids[5])
            _, image = updater.view(dataset, index)
            change = updater.change(index, image, config.motion_frames)
            moving = moving_pixels(change, config.patch_size, config.motion_threshold)
            rows, cols = pixels.long().unbind(-1)
            assert len(pixels) == 40 and not bool(moving[rows, cols].any()) and bool(moving.any())
            found.append(index)
        assert len(set(found)) == expected
    updater.config = dataclasses.replace(config, motion_threshold=0.0)
    try:
        assert updater.static_rays(loss_map, 40) == []
    finally:
        updater.config = config


def test_the_updates_render_their_views_as_training_sees_the_scene(loop_run):
    """With ``min_views`` 2 the model's renders keep the density where 2 training cameras see; the updates' loss maps
    and guard take all space, as training does: seen from a camera that looks away from the scene, a render of a
    training view is empty but a loss map and the views' PSNR are what they were."""
    _, trainer, updater = loop_run
    model, outputs = trainer.pipeline.model, trainer.pipeline.datamanager.train_dataparser_outputs
    before = updater.loss_map(0)
    views = [updater.view(trainer.pipeline.datamanager.train_dataset, 0)]
    psnr = updater.psnr(views)
    away = copy.deepcopy(outputs.cameras[0:1])
    away.camera_to_worlds[:, :, :3] *= torch.tensor([-1.0, 1.0, -1.0])  # turned round about its y axis
    model.config.render.min_views = 2
    model.see_from(away)
    try:
        assert float(model.render_view(before.camera)["accumulation"].max()) == 0.0
        after = updater.loss_map(0)
        assert torch.equal(after.rgb_loss, before.rgb_loss) and torch.equal(after.surface, before.surface)
        assert updater.psnr(views) == psnr
        model.see_from(outputs.cameras)
        assert float(model.render_view(before.camera)["accumulation"].mean()) > 0.5
    finally:
        model.config.render.min_views = 0
        model.see_from(outputs.cameras)


def test_a_resumed_run_goes_on_with_the_updates_where_they_were(loop_run):
    root, first, _ = loop_run
    checkpoints = root / "runs" / "loop" / "gear-nerf-small" / "first" / "nerfstudio_models"
    # From step 100 (after the update at 60) to step 279: the updates at 120 and 180 are the 2nd and 3rd.
    # What is checked is the schedule, not the fit: 256 rays, 10 Eq 11 steps, and no guard (with so few rays it may
    # undo update 2, which rightly ends the updates; the guard has its own test below).
    middle = copy.deepcopy(
        loop_config(root, "middle", LOOP_ITERATIONS - 101, load_dir=checkpoints, guard_tolerance=math.inf, max_steps=10)
    )
    middle.load_step = 100
    middle.pipeline.datamanager.train_num_rays_per_batch = 256
    trainer, updater = train(middle)
    assert updater.planned == [120, 180]
    assert int(updater.state.num_updates) == 3 and bool(updater.state.finished)
    # From the finished run's last checkpoint: a short resumed run is no error and updates nothing.
    _, updater = train(loop_config(root, "after", 10, load_dir=checkpoints))
    assert bool(updater.state.finished) and int(updater.state.num_updates) == 3


def test_a_run_that_would_get_no_update_stops_before_training(tmp_path):
    root = tmp_path
    write_synthetic_scene(root / "scene", SyntheticSpec(dataset="n3d", width=24, height=18, frames=3, cameras=4))
    config = loop_config(root, "short", 130)  # updates every 60 iterations while 80 remain: none
    with pytest.raises(NoGearUpdates, match="--max-num-iterations"):
        train(config)


REAL_SIZES = {
    # training cameras, frames, width, height (the datasets' usual training sizes; SOURCES.md for panoptic)
    "technicolor": (15, 50, 2048, 1088),
    "n3d": (20, 300, 1352, 1014),
    "immersive": (45, 50, 1280, 960),
    "panoptic": (15, 20, 320, 180),
    "test scene": (4, 4, 40, 30),
}


@pytest.mark.parametrize("preset", [gear_nerf, gear_nerf_small], ids=lambda p: p.config.method_name)
@pytest.mark.parametrize("dataset", REAL_SIZES)
def test_every_preset_plans_several_updates_at_every_dataset_size(preset, dataset):
    """The schedule counts iterations, not passes over the data: the same steps at every size, several of them
    within the preset's own iterations, and at the datasets' real sizes well before a single pass."""
    config = preset.config
    updates = config.pipeline.gear_updates
    steps = planned_updates(updates, 0, config.max_num_iterations - 1)
    assert len(steps) >= 3 and config.max_num_iterations - 1 - steps[-1] >= updates.epochs_after_updates * updates.iterations_per_epoch
    count, frames, width, height = REAL_SIZES[dataset]
    cameras = Cameras(
        camera_to_worlds=torch.eye(4)[:3].expand(count * frames, 3, 4), fx=500.0, fy=500.0, cx=width / 2, cy=height / 2,
        width=width, height=height,
    )
    plan = describe_plan(updates, steps, cameras, config.pipeline.datamanager.train_num_rays_per_batch)
    assert f"{count * frames * width * height / 1e6:.4g} M training pixels" in plan
    assert ", ".join(map(str, steps)) in plan


def test_the_guard_reviews_each_update_and_undoes_one_after_which_its_views_are_worse(loop_run):
    """The loop run's updates were each reviewed L epochs later (with no bar, so kept). An update held to a bar it
    cannot meet (its views must gain 1000 dB by its review) is undone there: the gear assignment is back to what it
    was just before the update, and no further update runs; the held-out view is measured at both ends."""
    _, trainer, updater = loop_run
    pipeline, model = trainer.pipeline, trainer.pipeline.model
    assert int(updater.state.num_undone) == 0 and int(updater.state.review_update) == 0
    state = GearUpdateState(model.gear_assignment(), 4)
    strict = GearUpdater(
        dataclasses.replace(updater.config, guard_tolerance=-1000.0, variance_threshold=0.0), model, pipeline.datamanager, pipeline.sam_backend,
        updater.optimizer, state, rays_per_batch=1024, first_step=0, last_step=LOOP_ITERATIONS - 1,
    )  # fmt: skip
    before = model.gear_assignment()
    stats = strict.update(60)
    assert np.isfinite([stats["views_psnr"], stats["held_out_psnr"]]).all()
    assert int(state.num_updates) == 1 and int(state.review_update) == 1 and int(state.review_step) == 120
    changed = model.gear_assignment()
    assert not all(torch.equal(changed[key], before[key]) for key in before)
    strict(119)  # not yet due
    assert int(state.review_update) == 1
    strict(120)  # due: reviewed and undone; the update due at the same step no longer runs
    assert int(state.num_undone) == 1 and bool(state.finished) and int(state.num_updates) == 1
    assert all(torch.equal(value, before[key]) for key, value in model.gear_assignment().items())
