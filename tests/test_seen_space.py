"""Renders take the density only where enough training cameras see a point (fields/seen_space.py)."""

from __future__ import annotations

import math

import pytest
import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.field_components.spatial_distortions import SceneContraction
from nerfstudio.utils.eval_utils import eval_setup

from gear_nerfstudio.fields.planes import normalize_positions
from gear_nerfstudio.fields.seen_space import SeenSpace, distinct_cameras, views_seeing, world_positions
from gear_nerfstudio.model.rendering import FullImageRenders
from gear_nerfstudio.model.sampling import ProposalConfig
from tests.test_gear_model import make_model

SIZE = 64


def facing_cameras(wide_focal: float = 50.0, narrow_focal: float = 200.0, copies: int = 1) -> Cameras:
    """Camera A at z = 3 looking down -z (half field of view 32.6 degrees) and camera B at z = -3 looking up +z
    (half field of view 9.1 degrees), each repeated ``copies`` times at different times (a rig over frames)."""
    looking_down = torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]])
    looking_up = torch.tensor([[-1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, -1, -3]])
    poses = torch.stack([looking_down, looking_up]).repeat(copies, 1, 1)
    focal = torch.tensor([wide_focal, narrow_focal]).repeat(copies)[:, None]
    return Cameras(
        camera_to_worlds=poses, fx=focal, fy=focal, cx=SIZE / 2, cy=SIZE / 2, width=SIZE, height=SIZE,
        times=torch.arange(2 * copies, dtype=torch.float32)[:, None] / (2 * copies),
    )  # fmt: skip


# The origin is seen by both; (0.8, 0, 0) by A only (15 degrees off both axes); (0, 0, 3.5) by B only (behind A);
# (2.5, 0, 0) by neither (40 degrees off both axes).
POINTS = torch.tensor([[0.0, 0, 0], [0.8, 0, 0], [0, 0, 3.5], [2.5, 0, 0]])


def test_views_seeing_counts_the_cameras_in_front_of_which_a_point_projects_inside_the_image():
    assert views_seeing(facing_cameras(), POINTS).tolist() == [2, 1, 1, 0]
    assert views_seeing(facing_cameras(), POINTS.reshape(2, 2, 3)).shape == (2, 2)


def test_distinct_cameras_leave_out_a_rigs_repeats_over_frames():
    cameras = distinct_cameras(facing_cameras(copies=3))
    assert len(cameras) == 2
    assert views_seeing(cameras, POINTS).tolist() == [2, 1, 1, 0]


@pytest.mark.parametrize("contraction", [None, SceneContraction(order=float("inf"))], ids=["box", "contracted"])
def test_the_grid_inverts_the_plane_coordinates_and_agrees_with_the_cameras(contraction):
    """`world_positions` undoes `normalize_positions`; the grid's answer is the exact count's except in the cells
    that a frustum's side cuts (a share of about 1 / GRID per side)."""
    aabb = torch.tensor([[-1.5, -1.0, -1.0], [1.5, 1.0, 1.0]])
    points = torch.randn(20000, 3, generator=torch.Generator().manual_seed(0)) * (1.0 if contraction else 0.6)
    x, inside = normalize_positions(points, aabb, contraction)
    assert torch.allclose(world_positions(x[inside], aabb, contraction), points[inside], atol=1e-4, rtol=1e-4)
    cameras = facing_cameras()
    seen = SeenSpace(cameras, 2, aabb, contraction)
    exact = views_seeing(cameras, points[inside]) >= 2
    assert 0.1 < float(exact.float().mean()) < 0.9  # contracted: 60 % of the points lie outside the box
    assert float((seen(x[inside]) == exact).float().mean()) > 0.97


@pytest.mark.parametrize("base_sampler", ["uniform", "proposal"])
def test_evaluation_renders_take_density_only_where_min_views_training_cameras_see(base_sampler):
    """The untrained field has density everywhere in its box; after ``see_from`` an evaluation-mode render has none
    at the point that one camera sees, and training, ``all_space`` and ``min_views`` 0 see all space."""
    points, times = POINTS[:2], torch.zeros(2, 1)
    for min_views, seen_by_one in ((2, False), (1, True), (0, True)):
        model = make_model(
            base_sampler=base_sampler,
            proposal=ProposalConfig(num_samples=(16,), resolutions=(8,)),
            render=FullImageRenders(min_views=min_views),
        )
        model.see_from(facing_cameras(copies=2))
        fields = [model.field.density_fn, *(net.density_fn for net in model.proposal_networks)]
        assert len(fields) == (2 if base_sampler == "proposal" else 1)
        for density_fn in fields:
            model.train()
            assert bool((density_fn(points, times) > 0).all())
            model.eval()
            density = density_fn(points, times)[:, 0].detach()
            assert float(density[0]) > 0 and (float(density[1]) > 0) == seen_by_one
            with model.all_space():
                assert bool((density_fn(points, times) > 0).all())
            assert (float(density_fn(points, times)[1, 0]) > 0) == seen_by_one  # set back after all_space


def test_a_rig_of_fewer_cameras_than_min_views_renders_what_all_of_them_see():
    one_camera = facing_cameras()[0:1]
    seen = SeenSpace(one_camera, 2, torch.tensor([[-1.0, -1, -1], [1, 1, 1]]))
    assert seen.min_views == 1
    assert seen(POINTS[:2]).tolist() == [True, True]  # camera A sees both


def test_a_loaded_run_renders_with_the_space_its_training_cameras_see(tiny_run, tmp_path):
    """The pipeline that ns-eval, ns-render, the viewer and ns-gear-track load gives the model its training cameras
    (5 cameras, cam00 held out): the rig's 4 other cameras, once each over the 3 frames; by default (0) none."""
    _, _, first, _ = tiny_run
    _, pipeline, _, _ = eval_setup(first / "config.yml", test_mode="test")
    assert pipeline.model.config.render.min_views == 0 and pipeline.model.field.seen_space is None
    config = tmp_path / "config.yml"  # the run's config with `min_views: 2` under `render:`, as a user would set it
    text = (first / "config.yml").read_text()
    assert text.count("min_views: 0") == 1
    config.write_text(text.replace("min_views: 0", "min_views: 2"))
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    model = pipeline.model
    seen = model.field.seen_space
    assert seen is not None and seen.min_views == model.config.render.min_views == 2
    assert all(net.seen_space is seen for net in model.proposal_networks)
    assert len(seen.cameras) == 4
    outputs = pipeline.datamanager.train_dataparser_outputs
    assert len(outputs.cameras) == 4 * 3
    training_centres = outputs.cameras.camera_to_worlds[:, :, 3]
    assert all(
        any(math.isclose(float((centre - other).norm()), 0.0, abs_tol=1e-6) for other in training_centres)
        for centre in seen.cameras.camera_to_worlds[:, :, 3]
    )
