"""Stability at the extremes: no NaN or inf reaches a loss, a weight, a gradient or an output.

Volume-rendering weights w_i = T_i (1 - exp(-sigma_i delta_i)) (Eq 1) must stay in [0, 1] and sum to at
most 1 for huge and tiny densities, near and far bounds, zero-length and huge segments, times 0 and 1,
one frame, one camera, N_gear = 1 and 6, gear values at every integer (Eq 5), all-black and all-white
images and mixed precision.
"""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.model_components.renderers import RGBRenderer
from nerfstudio.model_components.ray_samplers import UniformSampler

from gear_nerfstudio.data_parsers.google_immersive import GoogleImmersiveDataParserConfig
from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from gear_nerfstudio.data_parsers.technicolor import TechnicolorDataParserConfig
from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.data.datamanager import GearDataManagerConfig
from gear_nerfstudio.fields.gear_field import GearField, temporal_resolutions
from gear_nerfstudio.fields.gear_function import gear_level
from gear_nerfstudio.fields.proposal_field import ProposalDensityField
from gear_nerfstudio.model.gear_model import GearNeRFModelConfig
from gear_nerfstudio.model.sampling import ProposalConfig
from gear_nerfstudio.model.split_sampler import split_ray_samples
from gear_nerfstudio.pipeline import GearPipelineConfig
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene
from tests.test_gear_field import evaluate
from tests.test_gear_model import OUTPUT_KEYS, force_gears_in_upper_half, make_batch, make_model, make_rays

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
MODEL_RUNS = settings(max_examples=4, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
"""Each example builds a model and runs a training step (about a second on a loaded 2-core machine);
the extremes that matter most are pinned with ``@example``."""
TENSOR_RUNS = settings(max_examples=40, deadline=None, derandomize=True)
ONE_FRAME_TWO_CAMERAS = SyntheticSpec(dataset="n3d", width=16, height=12, frames=1, cameras=2)

raw_densities = st.sampled_from([-1e6, -100.0, -20.0, 0.0, 20.0, 88.0, 100.0, 200.0, 1e6]) | st.floats(-150, 150)
"""Raw density outputs of F_theta: exp(raw - 1) underflows to 0 below -100 and overflows float32 above 89."""


def capture_weights(model) -> dict:
    """Record the weights the model hands to its accumulation renderer (the real Eq 1 weights)."""
    seen = {}
    model.renderer.accumulation.register_forward_hook(
        lambda module, args, kwargs, output: seen.update(weights=kwargs["weights"].detach()), with_kwargs=True
    )
    return seen


def assert_valid_weights(weights: torch.Tensor) -> None:
    """Eq 1: every weight in [0, 1], their sum along each ray at most 1."""
    assert torch.isfinite(weights).all()
    assert weights.min() >= 0.0 and weights.max() <= 1.0
    assert weights.sum(dim=-2).max() <= 1.0 + 1e-5


def assert_finite_step(model, rays, batch) -> dict:
    """Forward, losses, backward: every output, loss and gradient finite, weights valid."""
    seen = capture_weights(model)
    outputs = model(rays)
    for key in OUTPUT_KEYS:
        assert torch.isfinite(outputs[key]).all(), key
    assert_valid_weights(seen["weights"])
    assert (outputs["accumulation"] >= 0).all() and (outputs["accumulation"] <= 1 + 1e-5).all()
    losses = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
    for key, value in losses.items():
        assert torch.isfinite(value).all(), key
    model.zero_grad()
    sum(losses.values()).backward()
    for name, parameter in model.named_parameters():
        assert parameter.grad is None or torch.isfinite(parameter.grad).all(), name
    return outputs


def set_raw_density(model_or_field, raw: float) -> None:
    """Make the density MLP output ``raw`` everywhere (last layer: zero weights, bias ``raw``)."""
    field = getattr(model_or_field, "field", model_or_field)
    with torch.no_grad():
        layer = field.density_net.layers[-1]
        layer.weight[0].zero_()
        layer.bias[0] = raw


def bundle(origins, directions, nears, fars, times) -> RayBundle:
    num_rays = origins.shape[0]
    return RayBundle(
        origins=origins,
        directions=torch.nn.functional.normalize(directions, dim=-1),
        pixel_area=torch.full((num_rays, 1), 1e-4),
        camera_indices=torch.zeros(num_rays, 1, dtype=torch.long),
        nears=nears,
        fars=fars,
        times=times,
    )


# ---------------------------------------------------------------- densities


@MODEL_RUNS
@given(raw=raw_densities)
@example(raw=200.0)
@example(raw=-1e6)
def test_field_density_is_finite_and_non_negative_for_any_raw_output(raw):
    """The density of Eq 1 is finite, so 0 * sigma = 0 on zero-length segments (no 0 * inf = NaN)."""
    field = GearField(AABB, num_frames=3, feature_dim=8, resolutions=(8,), gear_resolution=8, hidden_dim=16)
    set_raw_density(field, raw)
    positions = torch.rand(20, 3) * 2.4 - 1.2
    outputs = evaluate(field, positions, torch.randn(20, 3), torch.rand(20, 1))
    density = outputs["density"]
    assert torch.isfinite(density).all() and (density >= 0).all()
    assert all(torch.isfinite(v.float()).all() for v in outputs.values())
    proposal = ProposalDensityField(AABB, resolution=8, time_resolution=2)
    with torch.no_grad():
        proposal.decoder.weight.zero_()
        proposal.decoder.bias.fill_(raw)
    density = proposal.density_fn(positions[None], torch.rand(1, 1))
    assert torch.isfinite(density).all() and (density >= 0).all()


@MODEL_RUNS
@given(raw=raw_densities, zero_length=st.booleans(), proposal=st.booleans())
@example(raw=200.0, zero_length=True, proposal=False)
@example(raw=1e6, zero_length=False, proposal=True)
@example(raw=-1e6, zero_length=False, proposal=False)
def test_model_is_finite_for_huge_and_tiny_densities(raw, zero_length, proposal):
    """Huge and tiny densities, with ordinary bounds or with every segment of zero length (near = far)."""
    near, far = (2.5, 2.5) if zero_length else (0.5, 4.5)
    model = make_model(
        metadata={"near": near, "far": far, "num_frames": 4},
        base_sampler="proposal" if proposal else "uniform",
        proposal=ProposalConfig(num_samples=(8,), resolutions=(8,)),
    )
    force_gears_in_upper_half(model, 4)
    set_raw_density(model, raw)
    model.train()
    outputs = assert_finite_step(model, make_rays(16), make_batch(16))
    if raw >= 100.0 and not zero_length:
        assert torch.allclose(outputs["accumulation"], torch.ones_like(outputs["accumulation"]), atol=1e-6)
    if raw <= -100.0:
        assert (outputs["accumulation"] == 0).all() and (outputs["gear_level"] == 1).all()


def test_infinite_density_on_a_zero_length_segment_leaves_the_rest_of_the_ray_unchanged():
    """Eq 1: a segment with delta = 0 contributes alpha = 0 whatever sigma is; it must not blank the ray."""
    field = GearField(AABB, num_frames=1, feature_dim=8, resolutions=(8,), gear_resolution=8, hidden_dim=16)
    set_raw_density(field, 500.0)  # exp(499) is inf in float32
    density = evaluate(field, torch.zeros(1, 3), torch.randn(1, 3), None)["density"]
    rays = bundle(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]), None, None, None)
    starts = torch.tensor([[0.1], [0.2], [0.2], [0.3]])
    ends = torch.tensor([[0.2], [0.2], [0.3], [0.4]])  # the second segment has zero length
    samples = rays.get_ray_samples(bin_starts=starts[None], bin_ends=ends[None])
    densities = torch.cat([torch.zeros(1, 1), density, torch.ones(2, 1)])[None]
    weights = samples.get_weights(densities)
    assert_valid_weights(weights.detach())
    assert weights[0, 1, 0] == 0
    assert weights[0, 2, 0].item() == pytest.approx(1.0 - math.exp(-0.1), rel=1e-5)
    weights[0, 2:].sum().backward()
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in field.parameters())


# ---------------------------------------------------------------- bounds and segments


@MODEL_RUNS
@given(
    near=st.sampled_from([0.0, 1e-8, 1e-3, 0.5, 2.5]) | st.floats(0.0, 5.0),
    span=st.sampled_from([0.0, 1e-7, 1e-3, 1.0, 1e3, 1e6, 1e30]) | st.floats(0.0, 100.0),
    unbounded=st.booleans(),
)
@example(near=2.5, span=0.0, unbounded=False)
@example(near=0.0, span=1e30, unbounded=True)
@example(near=1e-8, span=1e-7, unbounded=False)
def test_model_is_finite_for_very_near_and_very_far_bounds(near, span, unbounded):
    """Bounds from 0 to 1e30 in front of the camera, zero-length rays (span 0) included, train and eval."""
    model = make_model(metadata={"near": near, "far": near + span, "num_frames": 4, "unbounded": unbounded})
    force_gears_in_upper_half(model, 3)
    model.train()
    assert_finite_step(model, make_rays(12), make_batch(12))
    model.eval()
    seen = capture_weights(model)
    with torch.no_grad():
        outputs = model(make_rays(12, seed=1))
    assert all(torch.isfinite(outputs[key]).all() for key in OUTPUT_KEYS)
    assert_valid_weights(seen["weights"])


segment_lengths = st.sampled_from([0.0, 1e-30, 1e-7, 1.0, 1e6, 1e30]) | st.floats(0.0, 1e3)


@TENSOR_RUNS
@given(
    lengths=st.lists(segment_lengths, min_size=1, max_size=6),
    densities=st.lists(st.sampled_from([0.0, 1e-30, 1.0, 1e30, 3e38]) | st.floats(0.0, 1e6), min_size=6, max_size=6),
    levels=st.lists(st.integers(1, 6), min_size=6, max_size=6),
    start=st.sampled_from([0.0, 1e-6, 1e3]),
)
@example(lengths=[1.0, 0.0, 1e30], densities=[1e30, 3e38, 1.0, 0.0, 0.0, 0.0], levels=[6, 6, 6, 1, 1, 1], start=0.0)
def test_split_segments_of_any_length_give_valid_weights(lengths, densities, levels, start):
    """Zero-length and huge base segments, split up to 2^5 times (N_gear = 6), with finite densities."""
    n = len(lengths)
    edges = torch.tensor([start] + [start + sum(lengths[: i + 1]) for i in range(n)], dtype=torch.float32)
    rays = bundle(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]), None, None, None)
    base = rays.get_ray_samples(bin_starts=edges[None, :-1, None], bin_ends=edges[None, 1:, None])
    split = split_ray_samples(base, torch.tensor([levels[:n]]))
    samples = split.ray_samples
    assert (samples.deltas >= 0).all()
    assert split.num_samples_per_ray.item() == sum(2 ** (p - 1) for p in levels[:n])
    per_sample = torch.tensor(densities[:n])[split.parent][..., None]
    weights = samples.get_weights(torch.where(split.valid[..., None], per_sample, 0.0))
    assert_valid_weights(weights)
    assert (weights[~split.valid] == 0).all()
    rgb = RGBRenderer(background_color="last_sample")(torch.rand(*samples.shape, 3), weights)
    assert torch.isfinite(rgb).all() and (rgb >= 0).all() and (rgb <= 1 + 1e-5).all()


def test_slightly_negative_base_segments_do_not_give_negative_weights():
    """near = far: nerfstudio's stratified sampler returns segments of about -5e-7; Eq 1 needs delta >= 0."""
    sampler = UniformSampler(num_samples=16)
    sampler.train()
    torch.manual_seed(0)
    ones = torch.ones(256, 1)
    rays = bundle(torch.zeros(256, 3), torch.randn(256, 3), 2.5 * ones, 2.5 * ones, None)
    base = sampler(rays)
    assert (base.deltas < 0).any(), "the sampler no longer produces negative segments; update this case"
    split = split_ray_samples(base, torch.randint(1, 4, base.shape))
    assert (split.ray_samples.deltas >= 0).all()
    weights = split.ray_samples.get_weights(torch.full((*split.ray_samples.shape, 1), 1e8))
    assert_valid_weights(weights)


# ---------------------------------------------------------------- times, frames, cameras, gears


@pytest.mark.parametrize("num_frames", [1, 2, 50])
def test_times_exactly_zero_and_one(num_frames):
    """t = 0 and t = 1 sit exactly on the first and last plane rows; outputs finite at both ends."""
    model = make_model(metadata={"near": 0.5, "far": 4.5, "num_frames": num_frames})
    force_gears_in_upper_half(model, 4)
    model.train()
    for t in (0.0, 1.0):
        rays = make_rays(16)
        rays.times = torch.full_like(rays.times, t)
        assert_finite_step(model, rays, make_batch(16))
    field = model.field
    with torch.no_grad():
        for triple in field.time_planes:
            for plane in triple.planes:
                rows = torch.arange(plane.shape[-2], dtype=plane.dtype)
                plane.copy_(rows[None, None, :, None].expand_as(plane))  # row index everywhere
    x = torch.zeros(2, 3)
    t = torch.tensor([[0.0], [1.0]])
    for gear, t_res in enumerate(field.time_resolutions, start=1):
        values = field.time_planes[gear - 1](torch.stack([torch.cat([x[:, :1], t * 2 - 1], -1)] * 3))
        assert values[0, 0, :].tolist() == [0.0, float(t_res - 1)]


def test_one_frame_field_and_model():
    """num_frames = 1: every gear's space-time planes have one row, time smoothness is 0, any t works."""
    assert temporal_resolutions(4, 1) == [1, 1, 1, 1] and temporal_resolutions(1, 1) == [1]
    assert temporal_resolutions(6, 0) == [1] * 6
    model = make_model(metadata={"near": 0.5, "far": 4.5, "num_frames": 1}, base_sampler="proposal",
                       proposal=ProposalConfig(num_samples=(8,), resolutions=(8,)))
    force_gears_in_upper_half(model, 4)
    model.train()
    assert model.field.time_resolutions == [1, 1, 1, 1]
    rays = make_rays(16)
    rays.times = torch.zeros_like(rays.times)
    assert_finite_step(model, rays, make_batch(16))
    assert model.field.regularisers()["time_smoothness"] == 0
    model.eval()
    with torch.no_grad():
        first = model(rays)
        rays.times = torch.ones_like(rays.times)
        later = model(rays)
    assert torch.equal(later["num_samples"], first["num_samples"])  # one row: nothing depends on t
    assert torch.equal(later["rgb"], first["rgb"])


def test_one_frame_one_training_camera_trains_and_evaluates(tmp_path):
    """A two-camera, one-frame capture: the held-out camera for eval leaves one training camera.

    nerfstudio users expect this to train (few-view setups are legitimate); the real datamanager,
    SAM feature cache, model and losses run, and evaluation gives finite PSNR and SSIM.
    """
    scene = write_synthetic_scene(tmp_path / "scene", ONE_FRAME_TWO_CAMERAS)
    parser = Neural3DVideoDataParserConfig(data=scene, cache_dir=tmp_path / "cache")
    train = parser.setup().get_dataparser_outputs("train")
    assert len(train.image_filenames) == 1 and train.metadata["num_frames"] == 1
    assert train.cameras.times.tolist() == [[0.0]]
    config = GearPipelineConfig(
        datamanager=GearDataManagerConfig(
            dataparser=parser, train_num_rays_per_batch=32, eval_num_rays_per_batch=32, sam_cache_dir=tmp_path / "sam"
        ),
        model=GearNeRFModelConfig(
            feature_dim=8, resolutions=(8,), gear_resolution=8, hidden_dim=16, hidden_dim_color=16, sam_head_dim=8,
            num_samples=8,
        ),
    )
    pipeline = config.setup(device="cpu", test_mode="val")
    assert pipeline.model.field.time_resolutions == [1, 1, 1, 1]
    pipeline.train()
    _, losses, metrics = pipeline.get_train_loss_dict(step=0)
    assert {"rgb_loss", "sam_loss"} <= losses.keys()
    assert all(torch.isfinite(v) for v in [*losses.values(), *metrics.values()])
    sum(losses.values()).backward()
    assert all(torch.isfinite(p.grad).all() for p in pipeline.model.parameters() if p.grad is not None)
    pipeline.eval()
    image_metrics, _ = pipeline.get_eval_image_metrics_and_images(step=0)
    assert math.isfinite(image_metrics["psnr"]) and math.isfinite(image_metrics["ssim"])


def test_only_the_held_out_camera_is_a_clear_error(tmp_path):
    """With a single camera there is nothing to train on once it is held out: a DatasetError says so."""
    scene = write_synthetic_scene(tmp_path / "scene", ONE_FRAME_TWO_CAMERAS)
    parser = Neural3DVideoDataParserConfig(data=scene, cache_dir=tmp_path / "cache", exclude_cameras=("cam01",))
    with pytest.raises(DatasetError, match="only the held-out camera 'cam00'"):
        parser.setup().get_dataparser_outputs("train")


@pytest.mark.parametrize(
    "spec, config_class, options",
    [
        (SyntheticSpec(dataset="technicolor", width=16, height=12, frames=1, rows=1, cols=2),
         TechnicolorDataParserConfig, {"held_out_camera": "01", "near": 1.0, "far": 8.0}),
        (ONE_FRAME_TWO_CAMERAS, Neural3DVideoDataParserConfig, {}),
        (SyntheticSpec(dataset="immersive", width=16, height=12, frames=1, cameras=2),
         GoogleImmersiveDataParserConfig, {"near": 0.3, "far": 10.0}),
    ],
    ids=["technicolor", "n3d", "immersive"],
)
def test_one_frame_two_camera_scene_parses_in_every_format(tmp_path, spec, config_class, options):
    """Times are 0 when T = 1 (not 0 / 0); one image per split; near < far, both finite."""
    scene = write_synthetic_scene(tmp_path / "scene", spec)
    parser = config_class(data=scene, cache_dir=tmp_path / "cache", **options).setup()
    for split in ("train", "test"):
        outputs = parser.get_dataparser_outputs(split)
        assert len(outputs.image_filenames) == 1
        assert outputs.cameras.times.tolist() == [[0.0]]
        assert outputs.metadata["num_frames"] == 1
        assert 0.0 < outputs.metadata["near"] < outputs.metadata["far"] < math.inf
        assert torch.isfinite(outputs.cameras.camera_to_worlds).all()


@pytest.mark.parametrize("num_gears", [1, 6])
def test_one_and_six_gears(num_gears):
    """N_gear = 1 (plain K-Planes, no splitting) and N_gear = 6 (up to 2^5 sub-samples per sample)."""
    model = make_model(num_gears=num_gears)
    force_gears_in_upper_half(model, num_gears)
    model.train()
    outputs = assert_finite_step(model, make_rays(24), make_batch(24))
    assert model.field.time_resolutions == temporal_resolutions(num_gears, 6)
    assert outputs["gear_level"].min() >= 1 and outputs["gear_level"].max() <= num_gears + 1e-5
    assert ((outputs["gear"] >= 0) & (outputs["gear"] <= 1)).all()
    samples = outputs["num_samples"]
    assert samples.min() >= 12 and samples.max() <= 12 * 2 ** (num_gears - 1)
    if num_gears == 1:
        assert (samples == 12).all()
    else:
        assert samples.max() >= 11 + 2 ** (num_gears - 1)  # some base sample at the top gear


gear_values = st.builds(
    lambda k, offset: k + offset,
    st.integers(-1, 8),
    st.sampled_from([0.0, -1e-6, 1e-6, -0.5, 0.5, -1e-3, 1e-3]),
) | st.sampled_from([math.inf, -math.inf, math.nan])


@TENSOR_RUNS
@given(g=gear_values, num_gears=st.integers(1, 6))
def test_gear_values_at_and_around_every_integer_split_as_eq5_says(g, num_gears):
    """Eq 5 at, just below and just above every integer; a base sample at level p gives 2^(p-1) samples."""
    p = int(gear_level(torch.tensor([g]), num_gears))
    expected = 1 if (math.isnan(g) or g < 1) else (num_gears if g >= num_gears else math.ceil(g))
    assert p == expected
    rays = bundle(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]), None, None, None)
    base = rays.get_ray_samples(bin_starts=torch.tensor([[[0.5]]]), bin_ends=torch.tensor([[[1.5]]]))
    split = split_ray_samples(base, torch.tensor([[p]]))
    assert split.num_samples_per_ray.item() == 2 ** (p - 1)
    weights = split.ray_samples.get_weights(torch.full((1, 2 ** (p - 1), 1), 2.0))
    assert weights.sum().item() == pytest.approx(1.0 - math.exp(-2.0), rel=1e-5)


@MODEL_RUNS
@given(g=gear_values.filter(math.isfinite), num_gears=st.sampled_from([1, 4, 6]))
@example(g=3.0, num_gears=4)
@example(g=5.0 + 1e-3, num_gears=6)
def test_model_with_a_constant_gear_value(g, num_gears):
    """g(x, t) = g everywhere (the offset 1 of Eq 4 plus a constant): every ray gets n 2^(p-1) samples."""
    model = make_model(num_gears=num_gears)
    with torch.no_grad():
        space, time = model.field.gear_function.space_planes.planes[0], model.field.gear_function.time_planes.planes[0]
        space.zero_()
        time.zero_()
        space[0, 0] = g - 1.0
        time[0, 0] = 1.0
    model.eval()
    p = int(gear_level(torch.tensor([g], dtype=torch.float32), num_gears))
    seen = capture_weights(model)
    with torch.no_grad():
        outputs = model(make_rays(8))
    assert all(torch.isfinite(outputs[key]).all() for key in OUTPUT_KEYS)
    assert_valid_weights(seen["weights"])
    assert (outputs["num_samples"] == 12 * 2 ** (p - 1)).all()


# ---------------------------------------------------------------- images and metrics


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_all_black_and_all_white_images(value):
    """Constant images: training losses finite; PSNR of a perfect prediction finite (MSE clamped), SSIM 1."""
    model = make_model()
    model.train()
    rays = make_rays(16)
    batch = {"image": torch.full((16, 3), value), "sam_features": torch.zeros(16, 32)}
    outputs = assert_finite_step(model, rays, batch)
    perfect = {**{k: v.detach() for k, v in outputs.items()}, "rgb": batch["image"].clone()}
    metrics = model.get_metrics_dict(perfect, batch)
    assert torch.isfinite(metrics["psnr"]) and metrics["psnr"] >= 90.0
    assert torch.isfinite(model.get_metrics_dict(outputs, batch)["psnr"])

    model.eval()
    height, width = 12, 12
    with torch.no_grad():
        flat = model(make_rays(height * width))
    image_outputs = {key: value_.reshape(height, width, -1) for key, value_ in flat.items()}
    image = torch.full((height, width, 3), value)
    metrics, images = model.get_image_metrics_and_images(image_outputs, {"image": image})
    assert all(math.isfinite(v) for v in metrics.values()), metrics
    metrics, _ = model.get_image_metrics_and_images({**image_outputs, "rgb": image.clone()}, {"image": image})
    assert math.isfinite(metrics["psnr"]) and metrics["psnr"] >= 90.0
    assert metrics["ssim"] == pytest.approx(1.0, abs=1e-4)
    opposite = torch.full((height, width, 3), 1.0 - value)
    metrics, _ = model.get_image_metrics_and_images({**image_outputs, "rgb": opposite}, {"image": image})
    assert metrics["psnr"] == pytest.approx(0.0, abs=1e-5) and math.isfinite(metrics["ssim"])
    assert all(torch.isfinite(v).all() for v in images.values())


# ---------------------------------------------------------------- mixed precision


@pytest.mark.parametrize("base_sampler", ["uniform", "proposal"])
def test_bfloat16_autocast_on_the_cpu(base_sampler):
    """torch.autocast(cpu, bfloat16): outputs, losses and gradients finite, weights valid, same splits."""
    model = make_model(base_sampler=base_sampler, proposal=ProposalConfig(num_samples=(8,), resolutions=(8,)))
    force_gears_in_upper_half(model, 4)
    model.eval()
    with torch.no_grad():
        reference = model(make_rays(16))
    model.train()
    rays, batch = make_rays(16), make_batch(16)
    seen = capture_weights(model)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        outputs = model(rays)
        losses = model.get_loss_dict(outputs, batch)
    for key in OUTPUT_KEYS:
        assert torch.isfinite(outputs[key]).all(), key
    assert_valid_weights(seen["weights"].float())
    assert all(torch.isfinite(v) for v in losses.values())
    sum(losses.values()).backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    model.eval()
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = model(make_rays(16))
    assert torch.equal(mixed["num_samples"], reference["num_samples"])
    assert torch.allclose(mixed["rgb"], reference["rgb"], atol=3e-2)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="float16 autocast needs a CUDA device")
def test_float16_autocast_on_cuda():
    """nerfstudio's --mixed-precision on a GPU (float16): huge densities and all outputs stay finite."""
    model = make_model().cuda()
    force_gears_in_upper_half(model, 4)
    set_raw_density(model, 200.0)
    model.train()
    rays = make_rays(64).to("cuda")
    batch = {k: v.cuda() for k, v in make_batch(64).items()}
    seen = capture_weights(model)
    with torch.autocast("cuda", dtype=torch.float16):
        outputs = model(rays)
        losses = model.get_loss_dict(outputs, batch)
    assert all(torch.isfinite(outputs[key]).all() for key in OUTPUT_KEYS)
    assert_valid_weights(seen["weights"].float())
    sum(losses.values()).backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_unbounded_contraction_of_points_at_huge_distances():
    """SceneContraction maps points up to 1e30 (and beyond the box) into the planes; finite outputs."""
    field = GearField(
        AABB, num_frames=2, feature_dim=8, resolutions=(8,), gear_resolution=8, hidden_dim=16,
        spatial_distortion=SceneContraction(order=float("inf")),
    )
    positions = torch.tensor([[1e30, -1e30, 0.0], [1e-30, 0.0, 0.0], [3e38, 0.0, -3e38], [5.0, 5.0, 5.0]])
    outputs = evaluate(field, positions, torch.randn(4, 3), torch.tensor([[0.0], [1.0], [0.5], [1.0]]))
    assert all(torch.isfinite(v.float()).all() for v in outputs.values())
    assert torch.isfinite(field.gear_values(positions, torch.zeros(4, 1))).all()
