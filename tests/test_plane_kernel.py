"""The fused Warp plane kernel against the torch path (grid_sample): features f (Eq 3, 7) and their gradients with
respect to the planes, B, the positions and the times, on the CPU."""

import copy

import pytest
import torch

from gear_nerfstudio.fields.gear_field import GearField, sample_points
from gear_nerfstudio.fields.gear_function import GearFunction
from gear_nerfstudio.fields.plane_kernel import pack_planes
from gear_nerfstudio.fields.proposal_field import ProposalDensityField
from gear_nerfstudio.model.sampling import ProposalConfig
from tests.test_gear_model import make_model, make_rays

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def random_field(resolutions, num_frames=6, time_resolutions=None, feature_dim=4) -> GearField:
    """A field of 3 gears whose planes and B are random (the initial space-time planes are constant)."""
    torch.manual_seed(0)
    field = GearField(
        AABB, num_frames=num_frames, num_gears=3, feature_dim=feature_dim, resolutions=resolutions,
        gear_resolution=4, time_resolutions=time_resolutions,
    )
    with torch.no_grad():
        for plane in [*field.space_planes.planes, *(p for triple in field.time_planes for p in triple.planes)]:
            plane.uniform_(-1.0, 1.0)
        field.basis.weight.normal_()
    return field


def samples(n: int = 400, seed: int = 1):
    """Positions (some outside [-1, 1], some on the planes' borders and on cell edges), times (some on the first and
    last frame) and gear levels."""
    generator = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=generator) * 2.4 - 1.2
    x[:20, 0], x[20:40, 1], x[40:60, 2] = 1.0, -1.0, 0.0
    x[60:70] = torch.tensor([-1.0, 1.0, -1.0])
    t = torch.rand(n, 1, generator=generator)
    t[:30], t[30:60] = 0.0, 1.0
    levels = torch.randint(1, 4, (n,), generator=generator)
    return x, t, levels


def features_and_grads(field: GearField, kind: str, x, t, levels):
    """f at (x, t) with the given plane lookups, and the gradients of a fixed random projection of f."""
    field.plane_kernel = kind
    x, t = x.clone().requires_grad_(), t.clone().requires_grad_()
    features = field.gear_features(x, t, levels)
    weights = torch.randn(features.shape, generator=torch.Generator().manual_seed(2))
    (features * weights).sum().backward()
    grads = {name: p.grad.clone() for name, p in field.named_parameters() if p.grad is not None}
    field.zero_grad(set_to_none=True)
    return features.detach(), x.grad, t.grad, grads


def assert_close(actual, expected, what):
    """Equal up to float32 rounding: 1e-5 of the largest magnitude."""
    scale = expected.abs().max().clamp(min=1.0)
    error = (actual - expected).abs().max() / scale
    assert error < 1e-5, f"{what}: relative error {error:.2e}"


@pytest.mark.parametrize(
    "resolutions, time_resolutions", [((8, 16), None), ((5,), None), ((6, 12, 7), (1, 1, 1)), ((8,), (1, 3, 6))]
)
@pytest.mark.parametrize("training", [False, True])
def test_kernel_matches_torch(resolutions, time_resolutions, training):
    """Same f and gradients; in training the stacked planes hold the gears in use only (``gear_features``)."""
    field = random_field(resolutions, time_resolutions=time_resolutions)
    field.train(training)
    x, t, levels = samples()
    if training:
        levels = levels.clamp(max=2)  # gear 3 unused: not in the stack
    reference = copy.deepcopy(field)
    expected = features_and_grads(reference, "torch", x, t, levels)
    actual = features_and_grads(field, "warp", x, t, levels)
    assert_close(actual[0], expected[0], "features")
    assert_close(actual[1], expected[1], "d/dx")
    assert_close(actual[2], expected[2], "d/dt")
    assert actual[3].keys() == expected[3].keys()
    for name in expected[3]:
        assert_close(actual[3][name], expected[3][name], f"d/d{name}")
    if training:
        assert torch.equal(field.used_columns, reference.used_columns)


def test_density_and_outputs_match():
    """The whole field (density, colour, SAM embedding) is the same with either lookup."""
    field = random_field((8, 16))
    field.eval()
    x, t, _ = samples(200)
    points = sample_points(x * 0.9, t, torch.nn.functional.normalize(torch.randn(200, 3), dim=-1))
    outputs = {}
    for kind in ("torch", "warp"):
        field.plane_kernel = kind
        density, embedding = field.get_density(points)
        outputs[kind] = (density, field.get_outputs(points, embedding))
    assert_close(outputs["warp"][0], outputs["torch"][0], "density")
    for name, value in outputs["torch"][1].items():
        assert_close(outputs["warp"][1][name], value, name.value)


def random_planes(module: torch.nn.Module) -> None:
    """Every plane of ``module`` random in [-1, 1]."""
    with torch.no_grad():
        for name, plane in module.named_parameters():
            if "planes" in name:
                plane.uniform_(-1.0, 1.0)


def values_and_grads(module, kind: str, function, x, t):
    """``function(x, t)`` without gradients, then with them: its values, and the gradients of a fixed random
    projection with respect to x, t and the module's parameters."""
    for part in module.modules():
        if hasattr(part, "plane_kernel"):
            part.plane_kernel = kind
    with torch.no_grad():
        without = function(x, t)
    xk, tk = x.clone().requires_grad_(), t.clone().requires_grad_()
    values = function(xk, tk)
    (values * torch.randn(values.shape, generator=torch.Generator().manual_seed(2))).sum().backward()
    grads = [p.grad.clone() for p in module.parameters() if p.grad is not None]
    module.zero_grad(set_to_none=True)
    return [without, values.detach(), xk.grad, tk.grad, *grads]


@pytest.mark.parametrize("time_resolution", [1, 5])
def test_proposal_field_matches_torch(time_resolution):
    """The proposal networks' planes (one gear, one resolution, no frame rows): the same densities without gradients
    (the weighted-sum kernel) and with them (the products kernel), and the same gradients."""
    torch.manual_seed(0)
    field = ProposalDensityField(AABB, resolution=6, time_resolution=time_resolution, feature_dim=4)
    random_planes(field)
    x, t, _ = samples()
    results = {kind: values_and_grads(field, kind, field.density_fn, x * 0.9, t) for kind in ("torch", "warp")}
    assert len(results["warp"]) == len(results["torch"]) == 8  # values twice, x, t, two planes, the decoder's two
    names = ["densities without gradients", "densities", "d/dx", "d/dt", "d/dh", "d/dk", "d/dW", "d/db"]
    for what, actual, expected in zip(names, results["warp"], results["torch"]):
        assert_close(actual, expected, what)


@pytest.mark.parametrize("time_resolution", [1, 5])
def test_gear_function_matches_torch(time_resolution):
    """The gear function g (Eq 4) with the kernel: the same values without gradients (the weighted-sum kernel) and
    with them, and the same gradients."""
    torch.manual_seed(0)
    function = GearFunction(feature_dim=4, resolution=5, time_resolution=time_resolution)
    random_planes(function)
    x, t, _ = samples()
    results = {kind: values_and_grads(function, kind, function, x, t) for kind in ("torch", "warp")}
    assert len(results["warp"]) == 6  # values twice, x, t, the two planes
    for what, actual, expected in zip(["g without gradients", "g", "d/dx", "d/dt", "d/dh'", "d/dk'"],
                                      results["warp"], results["torch"]):
        assert_close(actual, expected, what)


def test_packed_planes_follow_the_parameters():
    """A render packs the planes once (the second call without gradients reuses them) and packs them again after an
    in-place change of a plane, such as an optimizer step or a checkpoint load."""
    field = random_field((4, 8))
    field.eval()
    field.plane_kernel = "warp"
    x, t, levels = samples(50)
    with torch.no_grad():
        before = field.gear_features(x, t, levels)
        packed = field.packed_planes[1]
        field.gear_features(x, t, levels)
        assert field.packed_planes[1] is packed
        field.time_planes[1].planes[0].mul_(2.0)
        after = field.gear_features(x, t, levels)
    field.plane_kernel = "torch"
    with torch.no_grad():
        expected = field.gear_features(x, t, levels)
    assert not torch.allclose(after, before)
    assert_close(after, expected, "features after the change")
    field.plane_kernel = "warp"
    field.gear_features(x, t, levels)  # with gradients: packed anew, the kept copy dropped
    assert field.packed_planes is None


def test_model_renders_the_same():
    """The model with the kernel (radiance field and proposal networks) renders what it renders with torch."""
    outputs = {}
    for kind in ("torch", "warp"):
        model = make_model(base_sampler="proposal", proposal=ProposalConfig(num_samples=(16,), resolutions=(8,)),
                           plane_kernel=kind)
        model.eval()
        with torch.no_grad():
            outputs[kind] = model(make_rays())
    for name in ("rgb", "depth", "accumulation", "sam"):
        assert_close(outputs["warp"][name], outputs["torch"][name], name)


def test_no_samples():
    field = random_field((4,))
    field.eval()
    features, x_grad, t_grad, grads = features_and_grads(field, "warp", torch.zeros(0, 3), torch.zeros(0, 1),
                                                         torch.ones(0, dtype=torch.long))
    assert features.shape == (0, 4) and x_grad.shape == (0, 3) and t_grad.shape == (0, 1)
    assert all(not grad.any() for grad in grads.values())


def test_plane_products_needs_matching_planes():
    with pytest.raises(ValueError, match="one space-time plane per spatial plane"):
        pack_planes([torch.zeros(3, 2, 4, 4)], [])


def test_unknown_kernel_is_refused():
    with pytest.raises(ValueError, match="plane_kernel must be"):
        GearField(AABB, num_frames=2, num_gears=1, resolutions=(4,), plane_kernel="cuda")
