"""Motion-aware spatial sampling (Sec 4.4): split samples tile their segments and render consistently."""

import pytest
import torch

from nerfstudio.cameras.rays import RayBundle
from nerfstudio.model_components.ray_samplers import UniformSampler
from nerfstudio.model_components.renderers import AccumulationRenderer, DepthRenderer, RGBRenderer

from gear_nerfstudio.model.split_sampler import split_ray_samples


def ray_bundle(num_rays: int = 6, seed: int = 0) -> RayBundle:
    generator = torch.Generator().manual_seed(seed)
    directions = torch.nn.functional.normalize(torch.randn(num_rays, 3, generator=generator), dim=-1)
    return RayBundle(
        origins=torch.randn(num_rays, 3, generator=generator),
        directions=directions,
        pixel_area=torch.full((num_rays, 1), 1e-3),
        camera_indices=torch.arange(num_rays)[:, None],
        nears=torch.full((num_rays, 1), 0.5),
        fars=torch.full((num_rays, 1), 3.0) + torch.rand(num_rays, 1, generator=generator),
        times=torch.rand(num_rays, 1, generator=generator),
    )


def base_samples(num_samples: int = 8, stratified: bool = True, num_rays: int = 6):
    sampler = UniformSampler(num_samples=num_samples)
    sampler.train(stratified)
    return sampler(ray_bundle(num_rays))


def random_levels(shape, seed: int = 3) -> torch.Tensor:
    return torch.randint(1, 5, shape, generator=torch.Generator().manual_seed(seed))


def render(samples, density: float, color: torch.Tensor, background="black"):
    densities = torch.full((*samples.shape, 1), density)
    if samples.deltas.shape != densities.shape:
        raise AssertionError("samples must be padded (num_rays, num_samples)")
    weights = samples.get_weights(densities)
    rgb = RGBRenderer(background_color=background)(color.expand(*samples.shape, 3), weights)
    return weights, rgb, AccumulationRenderer()(weights)


def test_sub_samples_tile_each_segment_exactly_and_equally():
    base = base_samples()
    levels = random_levels(base.shape)
    split = split_ray_samples(base, levels)
    starts, ends = split.ray_samples.frustums.starts[..., 0], split.ray_samples.frustums.ends[..., 0]
    base_starts, base_ends = base.frustums.starts[..., 0], base.frustums.ends[..., 0]
    assert torch.equal(split.num_samples_per_ray, (2 ** (levels - 1)).sum(dim=1))
    for r in range(base.shape[0]):
        slot = 0
        for i in range(base.shape[1]):
            count = 2 ** (int(levels[r, i]) - 1)
            sub_starts, sub_ends = starts[r, slot : slot + count], ends[r, slot : slot + count]
            assert sub_starts[0] == base_starts[r, i] and sub_ends[-1] == base_ends[r, i]
            assert torch.equal(sub_starts[1:], sub_ends[:-1])
            expected_length = (base_ends[r, i] - base_starts[r, i]) / count
            # boundaries are rounded at the magnitude of the ray distance, so lengths carry that absolute error
            rounding = 4 * torch.finfo(ends.dtype).eps * float(base_ends[r, i].abs())
            assert torch.allclose(sub_ends - sub_starts, expected_length.expand(count), rtol=0, atol=rounding)
            assert torch.isclose((sub_ends - sub_starts).sum(), base_ends[r, i] - base_starts[r, i], atol=1e-6)
            assert (split.parent[r, slot : slot + count] == i).all()
            slot += count
        assert slot == split.num_samples_per_ray[r]
        assert split.valid[r, :slot].all() and not split.valid[r, slot:].any()
        assert (starts[r, slot:] == base_ends[r, -1]).all() and (ends[r, slot:] == base_ends[r, -1]).all()
    assert torch.equal(split.ray_samples.deltas[..., 0], ends - starts)


def test_split_samples_keep_ray_attributes():
    base = base_samples()
    split = split_ray_samples(base, random_levels(base.shape))
    samples = split.ray_samples
    assert samples.shape == split.valid.shape
    assert torch.equal(samples.times[..., 0], base.times[:, :1, 0].expand(samples.shape))
    assert torch.equal(samples.camera_indices[..., 0], base.camera_indices[:, :1, 0].expand(samples.shape))
    assert torch.equal(samples.frustums.directions, base.frustums.directions[:, :1].expand(*samples.shape, 3))
    positions = samples.frustums.get_positions()
    along = ((positions - samples.frustums.origins) * samples.frustums.directions).sum(-1)
    assert torch.allclose(along, (samples.frustums.starts + samples.frustums.ends)[..., 0] / 2, atol=1e-5)


@pytest.mark.parametrize("background", ["black", "white", "last_sample"])
def test_splitting_does_not_change_a_constant_field(background):
    base = base_samples(num_samples=10)
    split = split_ray_samples(base, random_levels(base.shape))
    color = torch.tensor([0.2, 0.5, 0.9])
    weights_base, rgb_base, acc_base = render(base, 1.3, color, background)
    weights_split, rgb_split, acc_split = render(split.ray_samples, 1.3, color, background)
    assert torch.allclose(rgb_split, rgb_base, atol=1e-6)
    assert torch.allclose(acc_split, acc_base, atol=1e-6)
    assert 0.5 < acc_base.min() and acc_base.max() < 1.0
    assert torch.allclose(split.to_base(weights_split), weights_base, atol=1e-6)
    assert (weights_split[~split.valid] == 0).all()


@pytest.mark.parametrize("level", [1, 2, 3, 4])
def test_uniform_gear_renders_like_a_finer_uniform_sampler(level):
    num_samples = 6
    coarse = base_samples(num_samples=num_samples, stratified=False)
    fine = base_samples(num_samples=num_samples * 2 ** (level - 1), stratified=False)
    split = split_ray_samples(coarse, torch.full(coarse.shape, level))
    assert torch.allclose(split.ray_samples.frustums.starts, fine.frustums.starts, atol=1e-5)
    assert torch.allclose(split.ray_samples.frustums.ends, fine.frustums.ends, atol=1e-5)
    color = torch.tensor([0.7, 0.1, 0.4])
    weights_split, rgb_split, acc_split = render(split.ray_samples, 0.8, color)
    weights_fine, rgb_fine, acc_fine = render(fine, 0.8, color)
    assert torch.allclose(rgb_split, rgb_fine, atol=1e-6) and torch.allclose(acc_split, acc_fine, atol=1e-6)
    for method in ("median", "expected"):
        depth = DepthRenderer(method=method)
        assert torch.allclose(
            depth(weights_split, split.ray_samples), depth(weights_fine, fine), atol=1e-5
        ), f"{method} depth"


def test_mixed_gears_depth_matches_hand_built_fine_samples():
    base = base_samples(num_samples=5)
    levels = random_levels(base.shape, seed=7)
    split = split_ray_samples(base, levels)
    weights, _, _ = render(split.ray_samples, 0.9, torch.ones(3))
    depth = DepthRenderer(method="expected")(weights, split.ray_samples)
    for r in range(base.shape[0]):
        edges = []
        for i in range(base.shape[1]):
            s, e = float(base.frustums.starts[r, i]), float(base.frustums.ends[r, i])
            count = 2 ** (int(levels[r, i]) - 1)
            edges += [(s + (e - s) * j / count, s + (e - s) * (j + 1) / count) for j in range(count)]
        transmittance, expected, total = 1.0, 0.0, 0.0
        for s, e in edges:
            alpha = 1.0 - torch.exp(torch.tensor(-0.9 * (e - s), dtype=torch.float64)).item()
            expected += transmittance * alpha * (s + e) / 2
            total += transmittance * alpha
            transmittance *= 1.0 - alpha
        assert depth[r, 0].item() == pytest.approx(expected / total, rel=1e-5)


def test_pack_unpack_round_trip_and_padding_copies_last_sample():
    base = base_samples()
    split = split_ray_samples(base, random_levels(base.shape))
    values = torch.randn(*split.valid.shape, 2)
    packed = split.pack(values)
    assert packed.shape == (int(split.num_samples_per_ray.sum()), 2)
    unpacked = split.unpack(packed)
    assert torch.equal(unpacked[split.valid], values[split.valid])
    for r in range(split.valid.shape[0]):
        last = int(split.num_samples_per_ray[r]) - 1
        assert (unpacked[r, last + 1 :] == values[r, last]).all()


def test_split_base_three():
    base = base_samples()
    levels = random_levels(base.shape)
    split = split_ray_samples(base, levels, split_base=3)
    assert torch.equal(split.num_samples_per_ray, (3 ** (levels - 1)).sum(dim=1))
    _, rgb_split, _ = render(split.ray_samples, 2.0, torch.ones(3) * 0.3)
    _, rgb_base, _ = render(base, 2.0, torch.ones(3) * 0.3)
    assert torch.allclose(rgb_split, rgb_base, atol=1e-6)


def test_last_sub_sample_ends_exactly_where_float_rounding_would_miss():
    # float32: s + (e - s) != e for these values; the split must still end exactly at e.
    starts = torch.tensor([[0.00025653839111328125, 0.008971214294433594, 0.005011081695556641]])
    ends = torch.tensor([[28.18324089050293, 26.263315200805664, 14.563555717468262]])
    assert (starts + (ends - starts) * (torch.tensor(4.0) / 4) != ends).any()
    bundle = RayBundle(
        origins=torch.zeros(3, 3), directions=torch.tensor([[0.0, 0.0, 1.0]] * 3), pixel_area=torch.ones(3, 1)
    )
    base = bundle.get_ray_samples(bin_starts=starts.T[..., None], bin_ends=ends.T[..., None])
    split = split_ray_samples(base, torch.full((3, 1), 3))
    assert torch.equal(split.ray_samples.frustums.ends[:, -1, 0], ends[0])
    assert torch.equal(split.ray_samples.frustums.starts[:, 0, 0], starts[0])


def test_accumulate_over_packed_samples_equals_padded_weighted_sum():
    base = base_samples()
    split = split_ray_samples(base, random_levels(base.shape))
    weights = torch.rand(*split.valid.shape, 1) * split.valid[..., None]
    values = torch.randn(*split.valid.shape, 5)
    expected = torch.sum(weights * split.unpack(split.pack(values)), dim=-2)
    assert torch.allclose(split.accumulate(weights, split.pack(values)), expected, atol=1e-6)
    assert split.ray_index.shape == (int(split.num_samples_per_ray.sum()),)
    assert torch.equal(torch.bincount(split.ray_index, minlength=split.valid.shape[0]), split.num_samples_per_ray)


def test_packed_order_is_the_row_major_order_of_the_real_slots():
    base = base_samples()
    split = split_ray_samples(base, random_levels(base.shape))
    expected = split.valid.reshape(-1).nonzero()[:, 0]
    assert torch.equal(split.sample_index, expected)
    assert torch.equal(split.ray_index, expected // split.valid.shape[1])
