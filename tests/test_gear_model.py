"""GearNeRFModel: forward, losses, backward, parameter groups and evaluation on the CPU."""

import pytest
import yaml
import torch

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.model_components.scene_colliders import AABBBoxCollider, NearFarCollider

from gear_nerfstudio.errors import InputError
from gear_nerfstudio.model.gear_model import GearNeRFModelConfig
from gear_nerfstudio.model.losses import LossWeights
from gear_nerfstudio.model.metrics import lpips_weights_path, near_layer_warning
from gear_nerfstudio.model.rendering import FullImageRenders
from gear_nerfstudio.model.sampling import ProposalConfig

OUTPUT_KEYS = {"rgb", "depth", "accumulation", "sam", "gear_level", "gear", "num_samples"}
METADATA = {"near": 0.5, "far": 4.5, "num_frames": 6, "unbounded": False}


def make_model(metadata=METADATA, **overrides):
    torch.manual_seed(0)
    config = GearNeRFModelConfig(
        feature_dim=8,
        resolutions=(8, 16),
        gear_resolution=8,
        hidden_dim=16,
        hidden_dim_color=16,
        sam_dim=32,
        sam_head_dim=8,
        num_samples=12,
        **overrides,
    )
    return config.setup(
        scene_box=SceneBox(torch.tensor([[-1.0, -1, -1], [1, 1, 1]])), num_train_data=4, metadata=metadata
    )


def make_rays(num_rays: int = 48, seed: int = 0) -> RayBundle:
    generator = torch.Generator().manual_seed(seed)
    origins = torch.tensor([0.0, 0.0, 2.5]).expand(num_rays, 3)
    targets = torch.rand(num_rays, 3, generator=generator) * 1.6 - 0.8
    return RayBundle(
        origins=origins.clone(),
        directions=torch.nn.functional.normalize(targets - origins, dim=-1),
        pixel_area=torch.full((num_rays, 1), 1e-4),
        camera_indices=torch.zeros(num_rays, 1, dtype=torch.long),
        times=torch.rand(num_rays, 1, generator=generator),
    )


def make_batch(num_rays: int = 48, sam_dim: int = 32, with_sam: bool = True):
    batch = {"image": torch.rand(num_rays, 3)}
    if with_sam:
        batch["sam_features"] = torch.randn(num_rays, sam_dim)
    return batch


def force_gears_in_upper_half(model, gear: int) -> None:
    """g = gear - 0.5 (level ``gear``) where y > 0.43 and exactly 1 (level 1) where y < 0.14 (8 plane rows)."""
    gear_function = model.field.gear_function
    with torch.no_grad():
        space, time = gear_function.space_planes.planes[0], gear_function.time_planes.planes[0]
        space.zero_()
        time.zero_()
        resolution = space.shape[-1]
        space[0, 0, resolution // 2 + 1 :, :] = gear - 1.5  # h'_1(x, y), rows = y
        time[0, 0] = 1.0  # k'_1(z, t)


@pytest.mark.parametrize("base_sampler", ["uniform", "proposal"])
def test_forward_loss_backward(base_sampler):
    """With the proposal sampler the distortion loss is on (it is computed only at a weight above 0)."""
    distortion = 0.5 if base_sampler == "proposal" else 0.0
    model = make_model(
        base_sampler=base_sampler,
        proposal=ProposalConfig(num_samples=(16,), resolutions=(8,)),
        losses=LossWeights(distortion=distortion),
    )
    model.train()
    rays, batch = make_rays(), make_batch()
    outputs = model(rays)
    assert OUTPUT_KEYS <= outputs.keys()
    shapes = {key: tuple(outputs[key].shape) for key in OUTPUT_KEYS}
    assert shapes == {
        "rgb": (48, 3),
        "depth": (48, 1),
        "accumulation": (48, 1),
        "sam": (48, 32),
        "gear_level": (48, 1),
        "gear": (48, 3),
        "num_samples": (48, 1),
    }
    for key in OUTPUT_KEYS:
        assert torch.isfinite(outputs[key]).all(), key
    assert (outputs["num_samples"] == 12).all() and (outputs["gear_level"] == 1).all()
    assert ((outputs["accumulation"] > 0) & (outputs["accumulation"] <= 1 + 1e-5)).all()

    metrics = model.get_metrics_dict(outputs, batch)
    assert torch.isfinite(metrics["psnr"]) and metrics["samples_per_ray"] == 12
    losses = model.get_loss_dict(outputs, batch, metrics)
    expected = {"rgb_loss", "sam_loss", "plane_tv", "l1_time_planes", "time_smoothness"}
    if base_sampler == "proposal":
        expected |= {"interlevel_loss", "distortion_loss", "plane_tv_proposal"}
    assert expected <= losses.keys()
    total = sum(losses.values())
    assert torch.isfinite(total)
    total.backward()
    groups = model.get_param_groups()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in groups["fields"])
    assert all(p.grad is None for p in groups["gear_field"])
    if base_sampler == "proposal":
        assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in groups["proposal_networks"])
    assert torch.isclose(losses["rgb_loss"], torch.mean((outputs["rgb"] - batch["image"]) ** 2))


def test_sam_loss_only_with_sam_features():
    model = make_model()
    model.train()
    outputs = model(make_rays())
    assert "sam_loss" not in model.get_loss_dict(outputs, make_batch(with_sam=False))
    batch = make_batch()
    loss = model.get_loss_dict(outputs, batch)["sam_loss"]
    assert torch.isclose(loss, torch.mean((outputs["sam"] - batch["sam_features"]) ** 2))


def test_param_groups_separate_the_gear_function():
    model = make_model()
    groups = model.get_param_groups()
    fields, gear = {id(p) for p in groups["fields"]}, {id(p) for p in groups["gear_field"]}
    assert gear == {id(p) for p in model.field.gear_function.parameters()}
    assert not fields & gear
    assert fields | gear == {id(p) for p in model.field.parameters()}
    assert "proposal_networks" not in groups


def test_gear_values_and_levels_api():
    model = make_model()
    positions = torch.rand(5, 7, 3) * 2 - 1
    times = torch.rand(5, 7, 1)
    g = model.gear_values(positions, times)
    assert g.shape == (5, 7) and torch.equal(g, torch.ones(5, 7))
    g.sum().backward()
    assert all(p.grad is not None for p in model.field.gear_function.parameters())
    assert torch.equal(model.gear_levels(positions, times), torch.ones(5, 7, dtype=torch.long))
    force_gears_in_upper_half(model, 3)
    levels = model.gear_levels(positions, times[:, :1])
    upper, lower = positions[..., 1] > 0.45, positions[..., 1] < 0.1
    assert upper.any() and lower.any()
    assert (levels[upper] == 3).all() and (levels[lower] == 1).all()


def test_upshifted_region_gets_more_samples_and_a_higher_gear_image():
    model = make_model()
    force_gears_in_upper_half(model, 4)
    model.train()
    rays = make_rays(64)
    outputs = model(rays)
    samples = outputs["num_samples"][:, 0]
    assert samples.min() >= 12 and samples.max() <= 12 * 8 and samples.max() > 12
    upper = rays.directions[:, 1] > 0.2
    assert samples[upper].float().mean() > samples[~upper].float().mean()
    assert outputs["gear_level"][upper].mean() > outputs["gear_level"][~upper].mean()
    losses = model.get_loss_dict(outputs, make_batch(64))
    sum(losses.values()).backward()
    for triple in (model.field.time_planes[0], model.field.time_planes[3]):
        assert all(plane.grad is not None and plane.grad.abs().sum() > 0 for plane in triple.planes)


def test_metadata_drives_collider_frames_and_contraction():
    model = make_model()
    assert isinstance(model.collider, NearFarCollider)
    assert (model.collider.near_plane, model.collider.far_plane) == (0.5, 4.5)
    assert model.field.time_resolutions == [1, 3, 4, 6]
    assert model.field.spatial_distortion is None

    model = make_model(metadata={**METADATA, "unbounded": True}, near_plane=0.1)
    assert isinstance(model.field.spatial_distortion, SceneContraction)
    assert model.collider.near_plane == 0.1

    model = make_model(metadata={})
    assert isinstance(model.collider, AABBBoxCollider)
    assert model.field.time_resolutions == [1, 1, 1, 1]


@pytest.mark.parametrize("base_sampler", ["uniform", "proposal"])
def test_split_samples_are_the_base_samples_in_use_split_inside_their_own_intervals(base_sampler):
    """Sec 4.4 on either base sampler: each base sample at gear p becomes 2^(p-1) samples that tile its own
    interval (the proposal sampler's intervals differ in length along a ray)."""
    model = make_model(base_sampler=base_sampler, proposal=ProposalConfig(num_samples=(16,), resolutions=(8,)))
    force_gears_in_upper_half(model, 3)
    model.train()
    rays = model.collider(make_rays(64))
    samples = model.sampler(rays, model.field.gear_levels)
    base, levels, split = samples.base, samples.levels, samples.split
    assert torch.equal(levels, model.field.gear_levels(base.frustums.get_positions(), base.times))  # at midpoints
    assert (levels == 1).any() and (levels == 3).any()
    assert torch.equal(split.num_samples_per_ray, (2 ** (levels - 1)).sum(dim=1))
    parent_starts = base.frustums.starts[..., 0].gather(1, split.parent)
    parent_ends = base.frustums.ends[..., 0].gather(1, split.parent)
    starts, ends = split.ray_samples.frustums.starts[..., 0], split.ray_samples.frustums.ends[..., 0]
    inside = (starts >= parent_starts) & (ends <= parent_ends) & (starts <= ends)
    assert bool(inside[split.valid].all())
    lengths = torch.zeros_like(base.frustums.starts[..., 0]).scatter_add(1, split.parent, (ends - starts) * split.valid)
    assert torch.allclose(lengths, base.frustums.ends[..., 0] - base.frustums.starts[..., 0], atol=1e-6)


def test_evaluation_renders_start_at_the_near_plane():
    """nerfstudio's NearFarCollider starts rays at 0 outside training by default; a held-out rig camera would then
    render the space behind its own near plane, which no training ray constrains (on a dome: the wall the camera
    sits in, an opaque dark layer). Evaluation renders must start where training samples did."""
    model = make_model()
    for mode in (model.train, model.eval):
        mode()
        samples = model.sampler(model.collider(make_rays(16)), model.field.gear_levels).base
        assert float(samples.frustums.starts.min()) >= METADATA["near"] - 1e-6


def test_camera_appearance_codes_for_trained_held_out_and_unknown_cameras():
    """Training cameras' rays get their own codes; the held-out camera and rays without a rig camera get the mean
    code of the trained cameras; the code changes the colour, not the density."""
    metadata = {**METADATA, "camera_names": ["cam00", "cam01", "cam02"], "camera_ids": torch.tensor([1, 1, 2, 2])}
    model = make_model(metadata=metadata, appearance_dim=4)
    appearance = model.field.appearance
    with torch.no_grad():
        appearance.codes.weight.copy_(torch.tensor([[9.0] * 4, [1.0] * 4, [3.0] * 4]))
    assert appearance.trained.tolist() == [False, True, True]
    codes = appearance({"rig_camera": torch.tensor([[0], [1], [2]])}, 3)
    assert codes[:, 0].tolist() == [2.0, 1.0, 3.0]  # cam00 was never trained: the mean of cam01 and cam02
    assert appearance({}, 2)[:, 0].tolist() == [2.0, 2.0]
    model.eval()
    rays = make_rays(8)
    outputs = {}
    for camera in (1, 2):
        rays.metadata = {"rig_camera": torch.full((8, 1), camera)}
        with torch.no_grad():
            outputs[camera] = model(rays)
    assert torch.equal(outputs[1]["depth"], outputs[2]["depth"])
    assert not torch.allclose(outputs[1]["rgb"], outputs[2]["rgb"])


def test_near_layer_report_compares_with_the_training_rays_depth():
    """A training batch sets the reference depth; an opaque evaluation view that ends much closer than it is
    reported (metric ``near_layer``, and named in the warning line), one that ends as far is not."""
    model = make_model()
    model.train()
    rays, batch = make_rays(), make_batch()
    outputs = model(rays)
    model.get_metrics_dict(outputs, batch)
    reference = float(model.training_depth)
    assert reference == pytest.approx(float(outputs["depth"].median()))
    size = (16, 16)  # SSIM's window is 11 pixels
    for depth, expected in ((0.1 * reference, 1.0), (reference, 0.0)):
        view = {
            "rgb": torch.rand(*size, 3), "accumulation": torch.ones(*size, 1), "depth": torch.full((*size, 1), depth),
            "gear": torch.zeros(*size, 3),
        }  # fmt: skip
        metrics, _ = model.get_image_metrics_and_images(view, {"image": torch.rand(*size, 3)})
        assert metrics["near_layer"] == expected and metrics["accumulation"] == 1.0
        warning = near_layer_warning([("cam00 frame 3", metrics), ("cam00 frame 4", {**metrics, "near_layer": 0.0})], reference)
        assert (warning is not None) == (expected == 1.0)
        assert warning is None or warning.endswith("in 1 of 2 evaluation views: cam00 frame 3 (100 %)"), warning


def test_time_resolutions_override_sets_rows_of_each_gear():
    model = make_model(num_gears=1, time_resolutions=(3,))
    assert model.field.time_resolutions == [3]
    assert [tuple(plane.shape[-2:]) for plane in model.field.time_planes[0].planes][0][0] == 3
    with pytest.raises(ValueError, match="one per gear"):
        make_model(num_gears=4, time_resolutions=(3,))
    with pytest.raises(ValueError, match="one per gear"):
        make_model(num_gears=1, time_resolutions=(0,))


def test_gear1_row_fraction_gives_gear_1_rows_in_time_growing_to_every_frame():
    assert make_model(gear1_row_fraction=0.0).field.time_resolutions == [1, 3, 4, 6]
    model = make_model(gear1_row_fraction=0.5)
    assert model.field.time_resolutions == [3, 4, 5, 6]
    assert [plane.shape[-2] for plane in model.field.time_planes[0].planes] == [3, 3]
    assert make_model(gear1_row_fraction=1.0).field.time_resolutions == [6, 6, 6, 6]
    assert make_model(gear1_row_fraction=0.5, time_resolutions=(1, 2, 3, 4)).field.time_resolutions == [1, 2, 3, 4]
    with pytest.raises(ValueError, match="gear1_row_fraction"):
        make_model(gear1_row_fraction=1.5)


def test_eval_image_metrics():
    model = make_model()
    model.eval()
    height, width = 16, 16
    with torch.no_grad():
        flat = model(make_rays(height * width))
    outputs = {key: value.reshape(height, width, -1) for key, value in flat.items()}
    batch = {"image": torch.rand(height, width, 3)}
    metrics, images = model.get_image_metrics_and_images(outputs, batch)
    assert {"psnr", "ssim"} <= metrics.keys()
    assert ("lpips" in metrics) == lpips_weights_path().is_file()
    assert all(isinstance(v, float) for v in metrics.values())
    assert images["img"].shape == (height, 2 * width, 3)
    assert {"accumulation", "depth", "gear"} <= images.keys()


def test_huge_densities_with_padding_stay_finite():
    model = make_model()
    force_gears_in_upper_half(model, 4)
    with torch.no_grad():
        model.field.density_net.layers[-1].bias[0] = 200.0  # exp(199) overflows float32; density_activation caps it
    model.train()
    outputs = model(make_rays(64))
    assert (outputs["num_samples"] > 12).any()
    for key in OUTPUT_KEYS:
        assert torch.isfinite(outputs[key]).all(), key
    losses = model.get_loss_dict(outputs, make_batch(64))
    sum(losses.values()).backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_full_image_render_path_gives_the_forward_pass_outputs_asked_for():
    """`get_outputs_for_camera_ray_bundle` (image_render: chunks, outputs on demand, colour only for samples of
    weight >= 1e-5) against the forward pass of the same rays at one time, with split samples (gears 1 and 4)."""
    model = make_model()
    force_gears_in_upper_half(model, 4)
    with torch.no_grad():
        for plane in model.field.space_planes.planes:
            plane.uniform_(0.0, 1.5)  # a mix of empty and opaque space
    model.eval()
    rays = make_rays(300)
    rays.times = torch.full_like(rays.times, 0.4)
    with torch.no_grad():
        forward = model(rays)
    model.config.render.chunk_samples = 500  # several chunks
    rendered = model.get_outputs_for_camera_ray_bundle(rays)
    assert set(rendered) == {"rgb", "depth", "accumulation", "gear"}
    with model.rendering("sam", "gear_level", "num_samples"):
        asked = model.get_outputs_for_camera_ray_bundle(rays)
    assert set(asked) == {"rgb", "depth", "accumulation", "gear", "sam", "gear_level", "num_samples"}
    assert forward["num_samples"].max() > 12 and torch.equal(asked["num_samples"], forward["num_samples"])
    assert 0.05 < float(forward["accumulation"].mean()) < 0.95
    for name in ("accumulation", "gear_level", "gear"):
        assert torch.allclose(asked[name], forward[name], atol=1e-5), name
    # a ray that accumulates less than half has no median: nerfstudio gives its last slot, a real sample or the
    # padding at the far end depending on the longest ray of its chunk; near 0.5 the last bit of a weight decides
    settled = forward["accumulation"] > 0.5 + 1e-3
    assert torch.allclose(asked["depth"][settled], forward["depth"][settled], atol=1e-5)
    for name in ("rgb", "sam"):  # the samples below the weight 1e-5 left out: at most 96 of them per ray
        assert torch.allclose(asked[name], forward[name], atol=1e-3), (name, (asked[name] - forward[name]).abs().max())
    assert torch.equal(rendered["rgb"], asked["rgb"])


@pytest.mark.parametrize("base_sampler", ["uniform", "proposal"])
def test_render_sample_counts_apply_to_full_image_renders_only(base_sampler):
    """``render.num_samples`` (and ``render.num_proposal_samples``) set n in full-image renders; training samples
    and the forward pass keep the model's counts; a count per proposal iteration is checked at setup."""
    proposal = base_sampler == "proposal"
    model = make_model(
        base_sampler=base_sampler,
        proposal=ProposalConfig(num_samples=(16, 8)),
        render=FullImageRenders(num_samples=5, num_proposal_samples=(8, 4) if proposal else None),
    )
    model.eval()
    rays = make_rays(40)
    with model.rendering("num_samples"):
        rendered = model.get_outputs_for_camera_ray_bundle(rays)
    assert torch.equal(rendered["num_samples"], torch.full((40, 1), 5.0))  # every sample at gear 1: not split
    with torch.no_grad():
        assert torch.equal(model(rays)["num_samples"], torch.full((40, 1), 12.0))
    if proposal:
        assert model.sampler.base.num_proposal_samples_per_ray == (16, 8)
        with pytest.raises(InputError, match="render.num-proposal-samples has 1 values but the model has 2"):
            make_model(
                base_sampler="proposal",
                proposal=ProposalConfig(num_samples=(16, 8)),
                render=FullImageRenders(num_proposal_samples=(8,)),
            )


def test_a_config_file_written_before_the_option_groups_loads():
    """A run's config.yml with the proposal, loss and render options flat (before the groups) loads into them."""
    text = (
        "!!python/object:gear_nerfstudio.model.gear_model.GearNeRFModelConfig\n"
        "num_gears: 2\nnum_proposal_samples: !!python/tuple [8]\nproposal_warmup: 7\nmin_views: 3\n"
        "render_num_samples: 5\ndistortion_loss_mult: 0.5\n"
    )
    config = yaml.load(text, Loader=yaml.Loader)
    assert config.num_gears == 2 and config.num_samples == 64
    assert config.proposal == ProposalConfig(num_samples=(8,), warmup=7)
    assert config.render == FullImageRenders(num_samples=5, min_views=3)
    assert config.losses == LossWeights(distortion=0.5)
    assert not {"num_proposal_samples", "min_views", "distortion_loss_mult"} & set(vars(config))
    assert yaml.load(yaml.dump(config), Loader=yaml.Loader) == config  # and today's files as before
