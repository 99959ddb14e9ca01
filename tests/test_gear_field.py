"""GearField: gear projection (Eq 5), masks (Eq 6), serial feature volumes (Eq 3, 7), gear function (Eq 4)."""

import math

import pytest
import torch

from nerfstudio.field_components.field_heads import FieldHeadNames

from gear_nerfstudio.fields.gear_field import GearField, GearFieldHeadNames, sample_points, temporal_resolutions
from gear_nerfstudio.fields.gear_function import gear_level

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def reference_level(g: float, num_gears: int) -> int:
    """Eq 5 written out case by case."""
    if math.isnan(g) or g < 1:
        return 1
    if g >= num_gears:
        return num_gears
    return math.ceil(g)


def small_field(num_frames: int = 50, num_gears: int = 4, **kwargs) -> GearField:
    torch.manual_seed(0)
    return GearField(
        AABB,
        num_frames=num_frames,
        num_gears=num_gears,
        feature_dim=8,
        resolutions=(8, 16),
        gear_resolution=8,
        **kwargs,
    )


def evaluate(field: GearField, positions, directions, times):
    """The field's outputs at points through nerfstudio's Field interface, by output name."""
    outputs = field(sample_points(positions, times, directions))
    return {name.value: value for name, value in outputs.items()}


def random_inputs(n: int = 500, seed: int = 1):
    generator = torch.Generator().manual_seed(seed)
    positions = torch.rand(n, 3, generator=generator) * 2.4 - 1.2
    times = torch.rand(n, 1, generator=generator)
    return positions, times


def set_gear_ramp(field: GearField, low: float, high: float) -> None:
    """Make g(x, t) = 1 + ramp(x) with ramp linear from ``low`` at x = -1 to ``high`` at x = +1."""
    gear_function = field.gear_function
    with torch.no_grad():
        space, time = gear_function.space_planes.planes[0], gear_function.time_planes.planes[0]
        space.zero_()
        time.zero_()
        space[2, 0] = 1.0  # h'_3(y, z), channel 0
        time[2, 0] = torch.linspace(low, high, time.shape[-1])  # k'_3(x, t), channel 0, along x


@pytest.mark.parametrize("num_gears", [1, 2, 4])
def test_gear_level_at_and_around_every_integer(num_gears):
    values, expected = [], []
    for k in range(0, num_gears + 2):
        for g in (k - 1e-6, float(k), k + 1e-6):
            values.append(g)
            expected.append(reference_level(g, num_gears))
    levels = gear_level(torch.tensor(values, dtype=torch.float64), num_gears)
    assert levels.dtype == torch.long
    assert levels.tolist() == expected


def test_gear_level_spot_values_and_non_finite():
    g = torch.tensor([1.0, 1.0 + 1e-6, 2.0, 2.0 + 1e-6, 4.0 - 1e-6, 4.0, 7.5, 0.3, -3.0, -math.inf, math.inf, math.nan])
    assert gear_level(g, 4).tolist() == [1, 2, 2, 3, 4, 4, 4, 1, 1, 1, 4, 1]


def test_gear_masks_partition_samples():
    g = torch.cat([torch.randn(1000) * 3 + 2, torch.tensor([math.inf, -math.inf, math.nan])])
    levels = gear_level(g, 4)
    masks = levels[:, None] == torch.arange(1, 5)  # Eq 6
    assert torch.equal(masks.sum(dim=1), torch.ones(len(g), dtype=torch.long))
    assert set(levels.tolist()) == {1, 2, 3, 4}


@pytest.mark.parametrize(
    "num_gears, num_frames, fraction, expected",
    [(4, 30, 0.25, [8, 15, 23, 30]), (4, 300, 0.25, [75, 150, 225, 300]), (4, 30, 1.0, [30] * 4), (4, 1, 0.5, [1] * 4)],
)
def test_gear_1_rows_as_a_fraction_of_the_frames(num_gears, num_frames, fraction, expected):
    assert temporal_resolutions(num_gears, num_frames, fraction) == expected


@pytest.mark.parametrize(
    "num_gears, num_frames, expected",
    [
        (4, 50, [1, 17, 34, 50]),
        (4, 100, [1, 34, 67, 100]),
        (2, 50, [1, 50]),
        (1, 50, [50]),
        (4, 1, [1, 1, 1, 1]),
        (1, 1, [1]),
    ],
)
def test_temporal_resolutions(num_gears, num_frames, expected):
    assert temporal_resolutions(num_gears, num_frames) == expected
    field = small_field(num_frames=num_frames, num_gears=num_gears)
    for gear_planes, t_res in zip(field.time_planes, expected):
        assert [plane.shape[-2] for plane in gear_planes.planes] == [t_res, t_res]
        assert [plane.shape[-1] for plane in gear_planes.planes] == [8, 16]


def test_gear_function_starts_at_exactly_one_with_gradients_to_both_planes():
    field = small_field()
    positions, times = random_inputs()
    g = field.gear_values(positions, times)
    assert torch.equal(g, torch.ones_like(g))
    assert torch.equal(field.gear_levels(positions, times), torch.ones(len(positions), dtype=torch.long))
    g.sum().backward()
    for plane in (field.gear_function.space_planes.planes[0], field.gear_function.time_planes.planes[0]):
        assert plane.grad is not None and plane.grad.abs().sum() > 0


def test_the_radiance_field_starts_the_same_whatever_the_gear_functions_channels():
    """The gear function draws its initial values from a fork of the random stream: at one seed, fields with 8 and 32
    gear channels share every other parameter's start."""
    fields = [small_field(gear_feature_dim=channels) for channels in (8, 32)]
    starts = [field.state_dict() for field in fields]
    others = [name for name in starts[0] if not name.startswith("gear_function.")]
    assert len(others) > 10 and all(torch.equal(starts[0][name], starts[1][name]) for name in others)
    planes = [field.gear_function.space_planes.planes[0] for field in fields]
    assert (planes[0].shape[1], planes[1].shape[1]) == (8, 32)


def test_every_gear_starts_as_the_static_field():
    field = small_field()
    positions, times = random_inputs()
    x = positions.clamp(-1, 1)
    features = [field.gear_feature(x, times, gear) for gear in range(1, 5)]
    for other in features[1:]:
        assert torch.allclose(other, features[0], atol=1e-6)
    other_times = torch.rand_like(times)
    assert torch.allclose(field.gear_feature(x, other_times, 4), features[0], atol=1e-6)


def test_grouped_features_match_dense_sum_over_gears():
    field = small_field()
    with torch.no_grad():
        for triple in field.time_planes:
            for plane in triple.planes:
                plane.uniform_(0.5, 1.5)
    field.used_columns[:] = True  # every gear trained everywhere: nothing to inherit
    positions, times = random_inputs()
    x = positions.clamp(-1, 1)
    levels = torch.randint(1, 5, (len(x),))
    grouped = field.gear_features(x, times, levels)
    dense = sum((levels == gear)[:, None] * field.gear_feature(x, times, gear) for gear in range(1, 5))  # Eq 7
    # the stacked planes are ~110 rows tall: float32 rounding of the time coordinate moves a lookup by ~1e-5 rows
    assert torch.allclose(grouped, dense, atol=1e-5)
    assert not torch.allclose(field.gear_feature(x, times, 2), field.gear_feature(x, times, 4), atol=1e-3)


def test_gradients_reach_only_gears_with_samples():
    field = small_field()
    positions, times = random_inputs()
    x = positions.clamp(-1, 1)
    levels = torch.randint(1, 5, (len(x),))
    levels[levels == 2] = 3
    field.gear_features(x, times, levels).square().sum().backward()
    for gear, triple in enumerate(field.time_planes, start=1):
        for plane in triple.planes:
            if gear == 2:
                assert plane.grad is None or plane.grad.abs().sum() == 0
            else:
                assert plane.grad is not None and plane.grad.abs().sum() > 0
    assert all(plane.grad.abs().sum() > 0 for plane in field.space_planes.planes)
    assert field.basis.weight.grad.abs().sum() > 0


@pytest.mark.parametrize("plane_kernel", ["torch", "warp"])
def test_a_training_chunk_without_samples_before_any_gear_is_used(plane_kernel):
    """A batch whose rays all miss the scene box, at the first step: no sample, no gear in use yet."""
    if plane_kernel == "warp":
        pytest.importorskip("warp")
    field = small_field(plane_kernel=plane_kernel)
    field.train()
    empty = torch.zeros(0, 3)
    assert field.gear_features(empty, torch.zeros(0, 1), torch.zeros(0, dtype=torch.long)).shape == (0, 8)
    outputs = evaluate(field, empty, empty, torch.zeros(0, 1))
    assert outputs["density"].shape == (0, 1) and outputs["rgb"].shape == (0, 3)
    assert not field.used_gears.any()


def test_forward_uses_the_gear_function_and_reaches_every_gear():
    field = small_field()
    set_gear_ramp(field, 0.0, 4.0)  # g = 1 + 2 (x + 1), from 1 to 5
    positions, times = random_inputs(2000)
    positions = positions.clamp(-1, 1)
    expected = gear_level(1.0 + 2.0 * (positions[:, 0] + 1.0), 4)
    levels = field.gear_levels(positions, times)
    away_from_boundaries = ((1.0 + 2.0 * (positions[:, 0] + 1.0)) % 1.0 - 0.5).abs() < 0.45
    assert torch.equal(levels[away_from_boundaries], expected[away_from_boundaries])
    assert set(levels.tolist()) == {1, 2, 3, 4}

    directions = torch.nn.functional.normalize(torch.randn_like(positions), dim=-1)
    outputs = evaluate(field, positions, directions, times)
    assert torch.equal(outputs["gear_level"], levels)
    (outputs["density"].sum() + outputs["rgb"].sum() + outputs["sam"].sum()).backward()
    for triple in field.time_planes:
        assert all(plane.grad is not None and plane.grad.abs().sum() > 0 for plane in triple.planes)
    assert all(p.grad is None for p in field.gear_function.parameters())


def test_outputs_shapes_range_and_density_outside_box():
    field = small_field(sam_dim=64, sam_head_dim=None)
    positions, times = random_inputs()
    directions = torch.nn.functional.normalize(torch.randn_like(positions), dim=-1)
    outputs = evaluate(field, positions, directions, times)
    assert outputs["density"].shape == (len(positions), 1)
    assert outputs["rgb"].shape == (len(positions), 3)
    assert outputs["sam"].shape == (len(positions), 64)
    assert all(torch.isfinite(v.float()).all() for v in outputs.values())
    assert ((outputs["rgb"] >= 0) & (outputs["rgb"] <= 1)).all()
    outside = (positions.abs() > 1).any(dim=-1)
    assert outside.any() and (~outside).any()
    assert (outputs["density"][outside] == 0).all()
    assert (outputs["density"][~outside] > 0).all()
    no_times = evaluate(field, positions, directions, None)
    assert torch.allclose(no_times["density"], evaluate(field, positions, directions, torch.zeros_like(times))["density"])


@pytest.mark.parametrize("initial_density", [0.05, 2.0, 20.0])
def test_the_field_starts_from_its_initial_density(initial_density):
    """``initial_density`` sets the density of the untrained field (the density MLP's output bias), within the spread
    that the random planes and weights give, where PyTorch's initialisation starts near exp(-1)."""
    positions, times = random_inputs()
    inside = (positions.abs() <= 1).all(dim=-1)
    default = small_field().density_fn(positions, times)[inside].median()
    chosen = small_field(initial_density=initial_density).density_fn(positions, times)[inside]
    assert abs(math.log(default) + 1.0) < 0.5
    assert abs(math.log(chosen.median()) - math.log(initial_density)) < 0.5
    assert chosen.min() > 0.5 * initial_density and chosen.max() < 2.0 * initial_density
    with pytest.raises(ValueError, match="initial_density must be > 0, got 0"):
        small_field(initial_density=0.0)


def test_density_fn_and_head_names_follow_nerfstudio_fields():
    """nerfstudio code that takes a Field (density_fn for samplers, FieldHeadNames outputs) gets the same density
    from density_fn as from the full forward pass, and the SAM embedding and gear level under their own names."""
    field = small_field(num_frames=6)
    positions, times = random_inputs(64)
    directions = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    outputs = field(sample_points(positions, times, directions))
    names = {FieldHeadNames.RGB, FieldHeadNames.DENSITY, GearFieldHeadNames.SAM, GearFieldHeadNames.GEAR_LEVEL}
    assert names <= set(outputs)
    torch.testing.assert_close(field.density_fn(positions, times), outputs[FieldHeadNames.DENSITY])
    levels = outputs[GearFieldHeadNames.GEAR_LEVEL].reshape(-1)
    assert torch.equal(levels, field.gear_levels(positions, times).reshape(-1).to(levels.dtype))


def test_unbounded_scene_is_contracted():
    from nerfstudio.field_components.spatial_distortions import SceneContraction

    field = small_field(spatial_distortion=SceneContraction(order=float("inf")))
    positions = torch.tensor([[100.0, -50.0, 3.0], [0.2, 0.1, -0.3]])
    outputs = evaluate(field, positions, torch.tensor([[0.0, 0.0, 1.0]] * 2), torch.zeros(2, 1))
    assert (outputs["density"] > 0).all() and torch.isfinite(outputs["density"]).all()


def test_sam_lift_is_affine_in_the_rendered_embedding():
    field = small_field(sam_dim=32, sam_head_dim=4)
    embeddings = torch.randn(5, 7, 4)
    weights = torch.rand(5, 7, 1) * 0.2
    lifted_then_rendered = (weights * field.sam_lift(embeddings)).sum(dim=-2)
    rendered_then_lifted = field.lift_sam((weights * embeddings).sum(dim=-2), weights.sum(dim=-2))
    assert torch.allclose(lifted_then_rendered, rendered_then_lifted, atol=1e-5)


def test_radiance_parameters_exclude_the_gear_function():
    field = small_field()
    radiance = {id(p) for p in field.radiance_parameters()}
    gear = {id(p) for p in field.gear_function.parameters()}
    assert gear and not radiance & gear
    assert radiance | gear == {id(p) for p in field.parameters()}


def test_regularisers_start_at_zero_for_time_planes_and_respond_to_changes():
    field = small_field()
    reg = field.regularisers()
    assert reg["l1_time_planes"] == 0 and reg["time_smoothness"] == 0 and reg["plane_tv"] > 0
    with torch.no_grad():
        field.time_planes[3].planes[0][:, :, 1::2] += 0.5  # zig-zag along t
    unused = field.regularisers()  # gear 4 has had no sample yet: its planes are not regularised
    assert unused["l1_time_planes"] == 0 and unused["time_smoothness"] == 0
    field.used_columns[3] = True
    reg = field.regularisers()
    assert reg["l1_time_planes"] > 0 and reg["time_smoothness"] > 0


def train_step(field: GearField, optimizer: torch.optim.Optimizer, positions, times) -> None:
    optimizer.zero_grad(set_to_none=True)
    directions = torch.nn.functional.normalize(torch.ones_like(positions), dim=-1)
    outputs = evaluate(field, positions, directions, times)
    loss = outputs["density"].mean() + outputs["rgb"].mean() + sum(field.regularisers().values())
    loss.backward()
    optimizer.step()


def test_unused_gears_cost_no_optimizer_step_until_a_region_shifts_up():
    field = small_field()
    field.train()
    optimizer = torch.optim.Adam(field.radiance_parameters(), lr=0.01)
    positions, times = random_inputs(400)
    positions = positions.clamp(-1, 1)
    before = [[plane.detach().clone() for plane in triple.planes] for triple in field.time_planes]
    for _ in range(3):
        train_step(field, optimizer, positions, times)
    assert field.used_gears.tolist() == [True, False, False, False]
    for gear, triple in enumerate(field.time_planes):
        for plane, old in zip(triple.planes, before[gear]):
            assert (plane not in optimizer.state) == (gear > 0)
            assert torch.equal(plane, old) == (gear > 0)
    in_use = field.parameters_in_use()
    unused = sum(plane.numel() for triple in field.time_planes[1:] for plane in triple.planes)
    assert in_use == sum(p.numel() for p in field.parameters()) - unused

    set_gear_ramp(field, 0.0, 4.0)  # a region shifts up: g from 1 to 5 along x
    train_step(field, optimizer, positions, times)
    assert field.used_gears.tolist() == [True, True, True, True]
    assert all(plane in optimizer.state for triple in field.time_planes for plane in triple.planes)
    assert field.parameters_in_use() == sum(p.numel() for p in field.parameters())
    # The record of used gears is part of the checkpoint.
    restored = small_field()
    restored.load_state_dict(field.state_dict())
    assert restored.used_gears.tolist() == [True, True, True, True]


def test_evaluation_does_not_mark_gears_as_used():
    field = small_field()
    set_gear_ramp(field, 0.0, 4.0)
    positions, times = random_inputs(200)
    field.eval()
    with torch.no_grad():
        evaluate(field, positions.clamp(-1, 1), torch.nn.functional.normalize(positions, dim=-1), times)
    assert not bool(field.used_gears.any())


def kplanes_regularisers(space, time):
    """The K-Planes plugin's regularisers written per plane (each a mean), averaged over the planes (planes of
    fewer than 3 rows count with 0 time smoothness)."""
    tv = [((c[:, 1:] - c[:, :-1]) ** 2).mean() + ((c[:, :, 1:] - c[:, :, :-1]) ** 2).mean() for t in space for c in t]
    tv += [((c[:, :, 1:] - c[:, :, :-1]) ** 2).mean() for t in time for c in t]
    l1 = [(1 - c).abs().mean() for t in time for c in t]
    smooth = [((c[:, 2:] - 2 * c[:, 1:-1] + c[:, :-2]) ** 2).mean() if c.shape[1] >= 3 else 0.0 for t in time for c in t]
    return {"plane_tv": sum(tv) / len(tv), "l1_time_planes": sum(l1) / len(l1), "time_smoothness": sum(smooth) / len(l1)}


def test_regularisers_of_one_gear_are_those_of_k_planes_and_other_gears_do_not_reweigh_them():
    field = small_field(num_frames=6)
    with torch.no_grad():
        for plane in [*field.space_planes.planes, *field.time_planes[0].planes, *field.time_planes[1].planes]:
            plane.add_(torch.randn_like(plane) * 0.1)
    field.used_columns[0] = True  # gear 1 in use (one time row: no time smoothness)
    alone = field.regularisers()
    reference = kplanes_regularisers(list(field.space_planes.planes), list(field.time_planes[0].planes))
    for name in alone:
        assert torch.isclose(alone[name], torch.as_tensor(reference[name]), rtol=1e-5), name
    # Gear 2 comes into use: its planes add their own terms, gear 1's keep their weight.
    field.used_columns[1] = True
    both = field.regularisers()
    gear_2 = kplanes_regularisers([], list(field.time_planes[1].planes))
    num_planes = {"plane_tv": 12, "l1_time_planes": 6, "time_smoothness": 6}  # of one K-Planes field (2 resolutions)
    for name in both:
        added = gear_2[name] * (len(field.time_planes[1].planes) * 3) / num_planes[name]
        assert torch.isclose(both[name], alone[name] + added, rtol=1e-5), name
    assert both["time_smoothness"] > 0 and both["l1_time_planes"] > alone["l1_time_planes"]


def train_forward(field: GearField, positions, times) -> None:
    directions = torch.nn.functional.normalize(torch.ones_like(positions), dim=-1)
    field.train()
    with torch.enable_grad():
        evaluate(field, positions, directions, times)


@pytest.mark.parametrize("lower", [1, 2])
def test_a_region_that_shifts_up_keeps_its_features(lower):
    """k^(G+1) of the columns a region newly uses starts as k^G resampled in time, so the region's features are
    the same right after the upshift (exactly here: 10 frames give 1, 4, 7, 10 rows, and the nodes of gear 2's
    rows are nodes of gear 3's)."""
    field = small_field(num_frames=10)
    assert field.time_resolutions == [1, 4, 7, 10]
    with torch.no_grad():
        for plane in field.time_planes[lower - 1].planes:
            plane.add_(torch.randn_like(plane) * 0.3)
    field.used_columns[: lower] = True  # the lower gears have been trained everywhere
    positions, times = random_inputs(600)
    positions = positions.clamp(-1, 1)
    moving = positions[:, 0] > 0.5
    before = field.gear_feature(positions[moving], times[moving], lower)
    untouched = [plane.detach().clone() for plane in field.time_planes[lower].planes]

    slope = 1.5 if lower == 1 else 0.5  # g = lower at x = 0.5, in (lower, lower + 1] above, in (lower - 1, lower] below
    set_gear_ramp(field, lower - 1 - 1.5 * slope, lower - 1 + 0.5 * slope)
    levels = field.gear_levels(positions, times)
    assert set(levels[positions[:, 0] > 0.5].tolist()) == {lower + 1} and set(levels[positions[:, 0] < 0.5].tolist()) == {lower}
    train_forward(field, positions, times)
    upshifted = positions[:, 0] > 0.6
    after = field.gear_feature(positions[upshifted], times[upshifted], lower + 1)
    assert torch.allclose(after, before[(positions[moving, 0] > 0.6)], atol=1e-5)
    # Columns that no upshifted sample touched keep their initial values.
    plane, old = field.time_planes[lower].planes[1], untouched[1]  # resolution 16; plane k_3(x, t) is index 2
    x_cells = torch.linspace(-1, 1, 16)
    far = x_cells < 0.4
    assert torch.equal(plane[2][..., far], old[2][..., far]) and not torch.equal(plane[2], old[2])


def test_gears_in_use_follows_every_change_of_used_columns():
    field = small_field()
    field.train()
    set_gear_ramp(field, 0.0, 4.0)
    positions, times = random_inputs(400)
    train_step(field, torch.optim.Adam(field.radiance_parameters(), lr=0.01), positions.clamp(-1, 1), times)
    assert field.gears_in_use() == field.used_gears.tolist() == [True, True, True, True]
    field.used_columns[1:] = False
    assert field.gears_in_use() == [True, False, False, False]
    restored = small_field()
    restored.load_state_dict(field.state_dict())
    assert restored.gears_in_use() == [True, False, False, False]
