"""Free-viewpoint tracking (Sec 4.5): `ns-gear-track` and its core functions on a model trained with the
real `ns-train` on a tiny synthetic N3D scene with ground-truth object masks."""

from __future__ import annotations

import copy
import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from PIL import Image
from scipy import ndimage

from gear_nerfstudio.tracking import agreement, cli, propagation
from gear_nerfstudio.tracking.cli import TrackCommand
from tests.conftest import command as run
from gear_nerfstudio.tracking.metrics import MaskScore, accuracy, iou, summarise
from gear_nerfstudio.sam.builtin_backend import BuiltinSamBackend
from gear_nerfstudio.sam.interface import Embedding, cell_centres
from gear_nerfstudio.tools.synthetic.scene import RigCamera, SyntheticScene
from gear_nerfstudio.sam.occlusion import in_front_share
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, rig_for
from gear_nerfstudio.tracking.click import (
    HIT_ACCUMULATION,
    IN_FRONT,
    ClickHit,
    TrackingError,
    border_share,
    check_click,
    click_point,
    project_prompt,
    view_share,
)
from gear_nerfstudio.tracking.propagation import (
    ObjectAppearance,
    mask_box,
    object_region,
    propagation_chains,
    region_prompt,
    render_embedding,
    segment,
    track,
)

pytestmark = pytest.mark.cost(60)

SLOW_SPHERE, FAST_SPHERE = 2, 3
CLICK_CAMERA = "cam01"
CLICK_FRAME = 1  # of 3: time 0.5
FAINT = 0.01
"""Accumulation threshold for clicks on this briefly trained model, whose density is still faint
(about 0.1 on the spheres); rays through empty space accumulate exactly 0."""


@pytest.fixture(scope="module")
def trained(tiny_run):
    """The session's tiny gear-nerf-small run (20 iterations, gear updates at steps 3, 6 and 9)."""
    root, scene, first, _ = tiny_run
    return root, scene, first / "config.yml"


@pytest.fixture(scope="module")
def loaded(trained):
    from nerfstudio.utils.eval_utils import eval_setup

    config, pipeline, _, _ = eval_setup(trained[2], test_mode="test")
    return config, pipeline


def object_pixel(scene: Path, camera: str, frame: int, object_id: int):
    """Centre (x, y) of the object's ground-truth pixel with the most object pixels around it."""
    ids = np.load(scene / "ground_truth" / f"{camera}.npz")["object_ids"][frame] == object_id
    padded = np.pad(ids, 1).astype(int)
    neighbours = sum(np.roll(np.roll(padded, dy, 0), dx, 1) for dy in (-1, 0, 1) for dx in (-1, 0, 1))[1:-1, 1:-1]
    row, col = np.unravel_index(int(np.argmax(np.where(ids, neighbours, -1))), ids.shape)
    return col + 0.5, row + 0.5


def dataset_camera(pipeline, name: str) -> Cameras:
    for dataset in (pipeline.datamanager.train_dataset, pipeline.datamanager.eval_dataset):
        names = [dataset.metadata["camera_names"][i] for i in dataset.metadata["camera_ids"].tolist()]
        if name in names:
            index = names.index(name)
            return dataset.cameras[index : index + 1]
    raise KeyError(name)


def look_along(centre, forward) -> torch.Tensor:
    """Camera-to-world (3, 4), OpenGL axes, of a camera at `centre` looking along `forward`."""
    forward = torch.as_tensor(forward, dtype=torch.float32)
    forward = forward / torch.linalg.norm(forward)
    hint = torch.tensor([0.0, 0.0, 1.0]) if abs(float(forward[2])) < 0.9 else torch.tensor([1.0, 0.0, 0.0])
    right = torch.linalg.cross(forward, hint)
    right = right / torch.linalg.norm(right)
    up = torch.linalg.cross(right, forward)
    return torch.stack([right, up, -forward, torch.as_tensor(centre, dtype=torch.float32)], dim=1)


def write_path(path: Path, poses, height: int, width: int, fov: float, times=None) -> Path:
    """A camera path in the ns-render / viewer format."""
    frames = []
    for index, pose in enumerate(poses):
        c2w = np.eye(4)
        c2w[:3] = pose.numpy()
        frame = {"camera_to_world": c2w.ravel().tolist(), "fov": fov, "aspect": width / height}
        if times is not None:
            frame["render_time"] = times[index]
        frames.append(frame)
    data = {"render_height": height, "render_width": width, "camera_type": "perspective", "camera_path": frames}
    path.write_text(json.dumps(data))
    return path


def warning_lines(stderr: str):
    """The command's warning lines, without their prefix."""
    prefix = "ns-gear-track: warning: "
    return [line[len(prefix) :] for line in stderr.splitlines() if line.startswith(prefix)]


def deepest_pixel(mask: np.ndarray):
    """Centre (x, y) of the mask's pixel furthest from its edge and from the image's border."""
    distance = ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]
    row, col = np.unravel_index(int(np.argmax(distance)), mask.shape)
    return col + 0.5, row + 0.5


class PerfectRender:
    """What a perfectly trained model would render, in place of `render_embedding` and `view_depth`: the
    synthetic scene itself, seen from any camera of the model's world frame, with the SAM backend's encoder
    features of that image and its true depth."""

    def __init__(self, scene: Path, pipeline):
        outputs = pipeline.datamanager.train_dataparser_outputs
        transform = outputs.dataparser_transform.double().numpy()
        self.rotation, self.shift, self.scale = transform[:, :3], transform[:, 3], float(outputs.dataparser_scale)
        spec = json.loads((scene / "ground_truth" / "scene.json").read_text())["spec"]
        self.frames, self.scene = spec["frames"], SyntheticScene(motion=spec["motion"])

    def rig_camera(self, camera: Cameras) -> RigCamera:
        """The scene's own camera (OpenCV axes, world-to-camera) of a camera in the model's world frame."""
        c2w = camera.camera_to_worlds.reshape(3, 4).double().numpy()
        rotation = self.rotation.T @ c2w[:, :3]  # OpenGL camera-to-world in the scene's world
        centre = self.rotation.T @ (c2w[:, 3] / self.scale - self.shift)

        def value(tensor) -> float:
            return float(tensor.reshape(-1)[0])

        return RigCamera(
            name="view", rotation=np.stack([rotation[:, 0], -rotation[:, 1], -rotation[:, 2]]), centre=centre,
            fx=value(camera.fx), fy=value(camera.fy), cx=value(camera.cx), cy=value(camera.cy),
            width=int(value(camera.width)), height=int(value(camera.height)),
        )

    def render(self, camera: Cameras, time: float):
        return self.scene.render(self.rig_camera(camera), round(time * (self.frames - 1)))

    def embedding(self, model, camera: Cameras, time: float, backend) -> Embedding:
        """The encoder's features of the image, with the true depth as the depth cue (as `render_embedding`)."""
        render = self.render(camera, time)
        return with_true_depth(backend.encode(render.rgb), render.depth)

    def depth(self, model, camera: Cameras, time: float, pixels: torch.Tensor) -> np.ndarray:
        depth = self.render(camera, time).depth
        rows = np.clip(pixels[..., 1].numpy().astype(int), 0, depth.shape[0] - 1)
        cols = np.clip(pixels[..., 0].numpy().astype(int), 0, depth.shape[1] - 1)
        return depth[rows, cols]


def assert_failed_cleanly(result: subprocess.CompletedProcess, parent: Path, *phrases: str) -> None:
    assert result.returncode == 2, result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    for phrase in phrases:
        assert phrase in result.stderr, result.stderr[-3000:]
    assert list(parent.iterdir()) == [], "a failed run left files behind"


# --- the command ------------------------------------------------------------------------------------


def test_one_click_tracks_to_the_held_out_view_at_every_time(trained):
    root, scene, config = trained
    x, y = object_pixel(scene, CLICK_CAMERA, CLICK_FRAME, FAST_SPHERE)
    out = root / "ok" / "ball"
    result = run(
        "ns-gear-track", "--load-config", str(config), "--output-dir", str(out), "--click-camera", CLICK_CAMERA,
        "--click-time", "0.5", "--positive", str(x), str(y), "--min-accumulation", str(FAINT), cwd=root,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert sorted(p.name for p in out.parent.iterdir()) == ["ball"]  # no staging folder left
    summary = json.loads((out / "tracking.json").read_text())
    assert summary["targets"] == ["cam00"]  # default: the held-out camera
    assert summary["min_views"] == 4  # rendered where 4 training cameras see (the run renders all space)
    assert summary["times"] == [0.0, 0.5, 1.0]
    assert summary["ground_truth_object"] == FAST_SPHERE
    assert summary["click"]["prompts"][0]["pixel"] == [x, y]

    truth = np.load(scene / "ground_truth" / "cam00.npz")["object_ids"] == FAST_SPHERE
    by_time = {record["time"]: record for record in summary["masks"]}
    assert sorted(by_time) == [0.0, 0.5, 1.0]
    assert "points" in by_time[0.5]["prompt"]  # the projected click at the clicked time
    assert by_time[0.5]["prompt"]["refined_pixels"] >= 0  # multi-view agreement ran (on by default)
    (px, py), = by_time[0.5]["prompt"]["points"]
    assert 0 <= px < 24 and 0 <= py < 18
    for time in (0.0, 1.0):  # boxes of the clicked time's mask prompt its neighbours
        assert by_time[time]["prompt"]["from_time"] == 0.5
    ious, accs = {}, {}
    for time, record in by_time.items():
        mask = np.asarray(Image.open(out / record["mask"])) > 127
        assert mask.shape == (18, 24)
        gt = truth[round(time * 2)]
        union = np.logical_or(mask, gt).sum()
        ious[time] = np.logical_and(mask, gt).sum() / union if union else 1.0
        accs[time] = (mask == gt).mean()
        assert record["iou"] == pytest.approx(ious[time]) and record["accuracy"] == pytest.approx(accs[time])
    metrics = summary["metrics"]
    assert metrics["mIoU"] == pytest.approx(ious[0.5]) and metrics["accuracy"] == pytest.approx(accs[0.5])
    assert metrics["t-mIoU"] == pytest.approx((ious[0.0] + ious[1.0]) / 2)
    assert metrics["t-accuracy"] == pytest.approx((accs[0.0] + accs[1.0]) / 2)
    assert "mIoU" in result.stdout
    for record in summary["masks"]:
        assert record["share"] == pytest.approx(record["area"] / (18 * 24))
    assert summary["masks_covering_most_of_view"] == sum(record["share"] > 0.5 for record in summary["masks"])
    assert warning_lines(result.stderr) == summary["warnings"]  # one line each, on stderr and in tracking.json
    assert {"mask_share", "mask_border_share", "mask_in_front_share", "background"} <= set(summary["click"])
    assert summary["click"]["prompts"][0]["accumulation"] >= FAINT

    import av

    with av.open(str(out / "overlay" / "cam00.mp4")) as container:
        assert sum(1 for _ in container.decode(video=0)) == 3


def test_background_click_is_warned_on_stderr_and_in_tracking_json(trained, tmp_path):
    """A click on the wall, as far from every object as the image allows: the command says that the click
    seems to have hit the background, on one line, and records it in tracking.json."""
    root, scene, config = trained
    x, y = deepest_pixel(np.load(scene / "ground_truth" / f"{CLICK_CAMERA}.npz")["object_ids"][CLICK_FRAME] == 0)
    out = tmp_path / "wall"
    result = run(
        "ns-gear-track", "--load-config", str(config), "--output-dir", str(out), "--click-camera", CLICK_CAMERA,
        "--click-time", "0.5", "--positive", str(x), str(y), "--min-accumulation", str(FAINT), "--times", "0.5",
        "--no-video", cwd=root,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    summary = json.loads((out / "tracking.json").read_text())
    warnings = warning_lines(result.stderr)
    assert warnings == summary["warnings"]
    background = [w for w in warnings if w.startswith("the click seems to have hit the background: ")]
    assert len(background) == 1, warnings
    assert "the scene's ground truth shows no object at the clicked pixel" in background[0]
    assert summary["click"]["background"] is True and summary["ground_truth_object"] == 0
    large = [w for w in warnings if "tracked masks cover more than half of their view" in w]
    assert len(large) == (summary["masks_covering_most_of_view"] > 0)


@pytest.fixture()
def perfect_model(trained, loaded, monkeypatch):
    """`ns-gear-track`'s own code on the loaded tiny run, with the renders of a perfectly trained model
    (`PerfectRender`): the 20-iteration run renders the same SAM feature everywhere, so there every mask is
    the whole image."""
    config, pipeline = loaded
    perfect = PerfectRender(trained[1], pipeline)
    import nerfstudio.utils.eval_utils as eval_utils

    monkeypatch.setattr(eval_utils, "eval_setup", lambda *args, **kwargs: (config, pipeline, Path("ckpt"), 0))
    monkeypatch.setattr(cli, "render_embedding", perfect.embedding)
    monkeypatch.setattr(cli, "view_depth", perfect.depth)
    monkeypatch.setattr(propagation, "render_embedding", perfect.embedding)
    monkeypatch.setattr(agreement, "render_embedding", perfect.embedding)
    yield perfect
    # `ns-gear-track`'s load set the shared model's seen space to its --min-views: back to the run's own.
    pipeline.model.see_from(pipeline.datamanager.train_dataparser_outputs.cameras)


@pytest.mark.parametrize("target", ["static", "slow", "fast", "wall", "floor"])
def test_sphere_clicks_are_not_warned_and_wall_and_floor_clicks_are(
    trained, loaded, perfect_model, target, tmp_path, capsys
):
    """On what a perfect model renders (64 x 48, cam01's pose, time 0.5), a click deep inside any of the three
    spheres gives no warning; a click on the wall or the floor says that it seems to have hit the background,
    because its mask is not in front of what surrounds it."""
    camera = dataset_camera(loaded[1], CLICK_CAMERA)
    fov = math.degrees(2 * math.atan(float(camera.height) / 2 / float(camera.fy)))
    path = write_path(tmp_path / "view.json", [camera.camera_to_worlds.reshape(3, 4)], 48, 64, fov, times=[0.5])
    ids = perfect_model.render(cli.load_camera_path(path), 0.5).object_ids
    pixel = {
        "static": deepest_pixel(ids == 1),
        "slow": deepest_pixel(ids == 2),
        "fast": deepest_pixel(ids == FAST_SPHERE),
        "wall": deepest_pixel(ids[:24] == 0),  # the upper half of the view is wall
        "floor": (32.5, 46.5),  # the bottom rows are floor
    }[target]
    assert (ids[int(pixel[1]), int(pixel[0])] == 0) == (target in ("wall", "floor"))
    out = tmp_path / "out"
    TrackCommand(
        trained[2], out, click_camera_path=path, positive=[pixel], min_accumulation=FAINT, video=False, times=[0.5]
    ).main()
    summary = json.loads((out / "tracking.json").read_text())
    warnings = warning_lines(capsys.readouterr().err)
    assert warnings == summary["warnings"]
    front = summary["click"]["mask_in_front_share"]
    if target in ("wall", "floor"):
        assert summary["click"]["background"] is True and front < IN_FRONT
        assert warnings == [
            f"the click seems to have hit the background: the mask at the clicked view view.json#0 (time 0.5) is in "
            f"front of its surroundings along {100 * front:.0f}% of its edge (an object's along most of it)"
        ]
    else:
        assert summary["click"]["background"] is False and front > IN_FRONT
        assert warnings == [] and summary["masks_covering_most_of_view"] == 0


def test_multi_view_agreement_gives_back_the_part_of_an_object_that_a_mask_left_out(trained, loaded, monkeypatch):
    """Multi-view agreement (`agreement.agreed_mask`) on what a perfect model renders (`PerfectRender`, its depth in
    the model's units), every camera at 3 times its resolution: the fast sphere's true mask at the held-out cam00 at
    time 0.5 with its lower half taken out (as the decoder leaves out a person's legs), lifted with the depth into
    the 4 training cameras, where the sphere's point prompts the decoder: the lower half comes back, and little else."""
    _, pipeline = loaded
    perfect = PerfectRender(trained[1], pipeline)

    def rendered(model, camera, time, backend):
        embedding = perfect.embedding(model, camera, time, backend)
        return Embedding(embedding.features, embedding.image_size, embedding.depth * perfect.scale)

    monkeypatch.setattr(agreement, "render_embedding", rendered)
    backend = pipeline.sam_backend

    def larger(name: str) -> Cameras:
        camera = copy.deepcopy(dataset_camera(pipeline, name))
        camera.rescale_output_resolution(3.0)
        return camera

    target = larger("cam00")
    truth = perfect.render(target, 0.5).object_ids == FAST_SPHERE
    x, y = deepest_pixel(truth)
    embedding = rendered(pipeline.model, target, 0.5, backend)
    scale = backend.grid_size / max(embedding.image_size)
    point = agreement.cell_points(target, embedding)[int(y * scale), int(x * scale)]  # the sphere's surface
    upper = truth & (np.arange(truth.shape[0])[:, None] < y)
    views = {name: larger(name) for name in ("cam01", "cam02", "cam03", "cam04")}
    seen = agreement.object_views(pipeline.model, backend, views, [point], np.ones(1), 0.5)
    agreed = agreement.agreed_mask(target, embedding, upper, list(seen.values()))
    assert (agreed >= upper).all()  # cells are only added
    assert iou(upper, truth) < 0.6 and iou(agreed, truth) > 0.8, (iou(upper, truth), iou(agreed, truth))
    assert (agreed & ~truth).sum() < 0.2 * truth.sum()

    # What every view's mask takes in apart from the object (here the slow sphere) would be agreed too; it stays out,
    # as only agreed cells that join the mask are added.
    slow = perfect.render(target, 0.5).object_ids == SLOW_SPHERE
    assert slow.any() and not ndimage.binary_dilation(truth, iterations=3)[slow].any()  # apart in the target
    for name, view in seen.items():
        view.mask |= perfect.render(views[name], 0.5).object_ids == SLOW_SPHERE
    assert np.array_equal(agreement.agreed_mask(target, embedding, upper, list(seen.values())), agreed)


def test_tracking_renders_only_what_min_views_training_cameras_see_whatever_the_run_renders(trained):
    """`ns-gear-track` loads the run with its renders keeping the density where --min-views (4 by default) training
    cameras see, though the run itself, like every run by default, renders all space; 0 renders all space."""
    for arguments, expected in (({}, 4), ({"min_views": 2}, 2), ({"min_views": 0}, None)):
        _, pipeline, _, _ = cli.TrackCommand(load_config=trained[2], **arguments).load()
        seen = pipeline.model.field.seen_space
        assert pipeline.model.config.render.min_views == 0
        assert seen is None if expected is None else seen.min_views == expected, (arguments, seen)
        assert all(network.seen_space is seen for network in pipeline.model.proposal_networks)


def test_time_outside_0_1_is_refused_before_loading(trained, tmp_path):
    root, _, config = trained
    result = run(
        "ns-gear-track", "--load-config", str(config), "--output-dir", str(tmp_path / "out"), "--click-camera",
        CLICK_CAMERA, "--click-time", "1.5", "--positive", "3", "3", cwd=root,
    )
    assert_failed_cleanly(result, tmp_path, "--click-time 1.5 is outside [0, 1]")


def test_click_on_empty_space_says_it_hits_nothing(trained, loaded, tmp_path):
    """A camera-path frame outside the scene box looking away from it: its rays meet no density."""
    root, _, config = trained
    away = look_along((0.0, 0.0, 3.0), (0.0, 0.0, 1.0))  # above the scene box [-1, 1]^3, looking up
    path = write_path(root / "away.json", [away], 18, 24, 50.0, times=[0.5])
    out_parent = tmp_path / "outputs"
    out_parent.mkdir()
    result = run(
        "ns-gear-track", "--load-config", str(config), "--output-dir", str(out_parent / "out"),
        "--click-camera-path", str(path), "--positive", "12", "9", cwd=root,
    )
    assert_failed_cleanly(result, out_parent, "positive click on away.json#0", "hits nothing")


def test_unknown_cameras_and_bad_times_are_named(trained, tmp_path):
    _, scene, config = trained
    with pytest.raises(TrackingError, match=r"unknown click camera 'cam99'.*cam00"):
        TrackCommand(config, tmp_path / "a", click_camera="cam99", click_time=0.5, positive=[(3.0, 3.0)]).main()
    x, y = object_pixel(scene, CLICK_CAMERA, CLICK_FRAME, FAST_SPHERE)
    with pytest.raises(TrackingError, match=r"unknown target camera 'cam42'"):
        TrackCommand(
            config, tmp_path / "b", click_camera=CLICK_CAMERA, click_time=0.5, positive=[(x, y)],
            target_cameras=["cam42"],
        ).main()
    with pytest.raises(TrackingError, match=r"--times value -0.2 is outside \[0, 1\]"):
        TrackCommand(config, tmp_path / "c", click_camera=CLICK_CAMERA, positive=[(x, y)], times=[-0.2]).main()
    assert list(tmp_path.iterdir()) == []


def test_point_behind_or_outside_a_target_view_is_reported_per_view(trained, loaded, tmp_path):
    root, scene, config = trained
    x, y = object_pixel(scene, CLICK_CAMERA, CLICK_FRAME, FAST_SPHERE)
    point = click_point(loaded[1].model, dataset_camera(loaded[1], CLICK_CAMERA), (x, y), 0.5, FAINT)
    centre = dataset_camera(loaded[1], "cam00").camera_to_worlds[0, :, 3]
    towards = (point - centre) / torch.linalg.norm(point - centre)
    aside = torch.linalg.cross(towards, torch.tensor([0.0, 0.0, 1.0]))
    poses = [
        look_along(centre, towards),  # the point at the image centre: fine
        look_along(centre, -towards),  # the point behind
        look_along(centre, towards + math.tan(math.radians(60.0)) * aside / torch.linalg.norm(aside)),  # 60 deg aside
    ]
    path = write_path(root / "targets.json", poses, 18, 24, 30.0)
    with pytest.raises(TrackingError) as error:
        TrackCommand(
            config, tmp_path / "out", click_camera=CLICK_CAMERA, click_time=0.5, positive=[(x, y)],
            target_camera_path=path, min_accumulation=FAINT,
        ).main()
    message = str(error.value)
    assert "targets_0000" not in message
    assert "target view targets_0001: the clicked point" in message and "is behind the camera" in message
    assert "target view targets_0002: the clicked point" in message and "outside the 24x18 image" in message
    assert list(tmp_path.iterdir()) == []


# --- core functions ---------------------------------------------------------------------------------


def test_in_front_share_tells_an_object_from_a_piece_of_wall_or_floor():
    rows, cols = np.mgrid[0:24, 0:32]
    floor = 1.0 / (0.05 + 0.02 * rows)  # a plane seen at a grazing angle: inverse depth linear in the row
    piece = (rows >= 8) & (rows < 16) & (cols >= 10) & (cols < 20)
    assert in_front_share(piece, floor) == 0.0  # a piece of a plane goes on into its surroundings
    box = np.where(piece, 0.5 * floor, floor)  # an object in front of it
    assert in_front_share(piece, box) == 1.0
    # Masks a cell or two too large still see the jump, except where their corners stick out past the object's.
    assert in_front_share(ndimage.binary_dilation(piece, iterations=1), box) > 0.8
    assert in_front_share(ndimage.binary_dilation(piece, iterations=2), box) > IN_FRONT
    assert in_front_share(ndimage.binary_erosion(piece, iterations=2), box) == 1.0  # or too small
    beside = (rows >= 8) & (rows < 16) & (cols >= 20) & (cols < 26)  # the plane next to the object
    assert in_front_share(beside, box) < 0.05
    assert in_front_share(np.zeros_like(piece), box) is None and in_front_share(np.ones_like(piece), box) is None


def test_check_click_says_when_a_mask_covers_most_of_the_view_or_a_ray_ends_at_the_far_bound():
    mask = np.zeros((20, 30), dtype=bool)
    mask[5:15, 10:18] = True
    depth = np.where(mask, 2.0, 4.0)
    near = ClickHit(point=torch.zeros(3), depth=2.0, near=1.0, far=5.0, accumulation=0.9)
    numbers, warnings = check_click("cam01", 0.5, mask, mask, depth, [(12.0, 8.0)], [1], [near])
    assert warnings == [] and numbers["background"] is False
    assert numbers["mask_share"] == view_share(mask) == pytest.approx(80 / 600)
    assert numbers["mask_in_front_share"] == 1.0

    large = np.ones_like(mask)
    large[:, 25:] = False  # 83 % of the image, but not its right-hand side
    assert border_share(large) == pytest.approx((2 * 25 + 18) / (2 * 30 + 2 * 18))
    _, warnings = check_click("cam01", 0.5, large, large, depth, [(12.0, 8.0)], [1], [near])
    assert warnings[0].startswith("the mask at the clicked view cam01 (time 0.5) covers 83% of the image (more than")
    assert "touches 71% of the image border" in warnings[1]

    far = ClickHit(point=torch.zeros(3), depth=4.9, near=1.0, far=5.0, accumulation=0.9)
    _, warnings = check_click("cam01", 0.5, mask, mask, depth, [(12.0, 8.0), (3.0, 3.0)], [1, 0], [near, far])
    assert warnings == []  # a negative click may end anywhere
    _, warnings = check_click("cam01", 0.5, mask, mask, depth, [(12.0, 8.0)], [1], [far])
    assert warnings == [
        "the click seems to have hit the background: the ray of the click at (x=12, y=8) ends at its far bound "
        "(depth 4.9, 98% of the way from near 1 to far 5)"
    ]


def test_click_point_lies_on_the_clicked_ray_and_projects_back(trained, loaded):
    _, scene, _ = trained
    model = loaded[1].model
    camera = dataset_camera(loaded[1], CLICK_CAMERA)
    x, y = object_pixel(scene, CLICK_CAMERA, CLICK_FRAME, FAST_SPHERE)
    point = click_point(model, camera, (x, y), 0.5, FAINT)
    assert point.shape == (3,)
    assert project_prompt(camera, point) == pytest.approx((x, y), abs=1e-3)
    centre = camera.camera_to_worlds[0, :, 3]
    near, far = model.collider.near_plane, model.collider.far_plane
    assert near <= float(torch.linalg.norm(point - centre)) <= far


def test_click_point_refuses_bad_times_pixels_and_empty_space(loaded):
    model = loaded[1].model
    camera = dataset_camera(loaded[1], CLICK_CAMERA)
    with pytest.raises(TrackingError, match=r"click time 1.2 is outside \[0, 1\]"):
        click_point(model, camera, (3.0, 3.0), 1.2)
    with pytest.raises(TrackingError, match=r"click pixel \(x=30, y=3\) is outside the 24x18 image"):
        click_point(model, camera, (30.0, 3.0), 0.5)
    away = Cameras(camera_to_worlds=look_along((0.0, 0.0, 3.0), (0.0, 0.0, 1.0))[None], fx=20.0, fy=20.0, cx=12.0, cy=9.0)
    with pytest.raises(TrackingError, match=f"hits nothing: the ray's accumulated density is 0.000 < {FAINT}"):
        click_point(model, away, (12.0, 9.0), 0.5, FAINT)
    with pytest.raises(TrackingError, match=f"hits nothing: .* < {HIT_ACCUMULATION}"):
        click_point(model, away, (3.0, 3.0), 0.0)


def test_project_prompt_inverts_fisheye_and_pinhole_rays():
    """A point on the ray of a pixel projects to that pixel, for nerfstudio's own ray generation."""
    c2w = look_along((0.3, -0.2, 1.0), (0.2, 1.0, -0.3))
    for camera_type, distortion in ((CameraType.PERSPECTIVE, None), (CameraType.FISHEYE, [0.05, -0.01, 0, 0, 0, 0])):
        camera = Cameras(
            camera_to_worlds=c2w[None], fx=30.0, fy=30.0, cx=24.0, cy=18.0, width=48, height=36,
            camera_type=camera_type,
            distortion_params=None if distortion is None else torch.tensor([distortion], dtype=torch.float32),
        )
        for pixel in ((3.5, 4.25), (40.0, 30.0), (24.5, 18.5)):  # nerfstudio gives NaN at (cx, cy)
            ray = camera.generate_rays(camera_indices=0, coords=torch.tensor([[pixel[1], pixel[0]]]))
            point = ray.origins[0] + 2.5 * ray.directions[0]
            assert project_prompt(camera, point) == pytest.approx(pixel, abs=1e-3)
        with pytest.raises(TrackingError, match="is behind the camera"):
            project_prompt(camera, ray.origins[0] - 2.5 * ray.directions[0])
        ray = camera.generate_rays(camera_indices=0, coords=torch.tensor([[18.0, 70.0]]))  # x = 70 > 48
        with pytest.raises(TrackingError, match=r"projects to pixel \(x=70.0, y=18.0\), outside the 48x36 image"):
            project_prompt(camera, ray.origins[0] + 2.5 * ray.directions[0])


def test_render_embedding_fills_the_valid_grid_and_decodes(loaded):
    model, backend = loaded[1].model, loaded[1].sam_backend
    camera = dataset_camera(loaded[1], "cam00")
    embedding = render_embedding(model, camera, 0.5, backend)
    assert embedding.features.shape == (backend.embedding_dim, backend.grid_size, backend.grid_size)
    assert embedding.image_size == (18, 24)
    rows = math.ceil(18 * backend.grid_size / 24)  # the image's longest side spans the whole grid
    assert np.abs(embedding.features[:, :rows]).sum(axis=0).min() > 0
    assert not embedding.features[:, rows:].any()  # SAM's padding stays zero
    assert embedding.depth.shape == (backend.grid_size, backend.grid_size)  # the depth cue, at the same cells
    assert embedding.depth[:rows].min() > 0 and not embedding.depth[rows:].any()
    mask = segment(backend, embedding, np.array([[12.5, 9.5]]), np.array([1]))  # the centre of pixel (9, 12)
    assert mask.shape == (18, 24) and mask.dtype == bool and mask[9, 12]
    box = np.array([4.0, 3.0, 14.0, 11.0])
    boxed = segment(backend, embedding, np.zeros((0, 2)), np.zeros(0), box)
    assert boxed.shape == (18, 24) and not boxed[:, 17:].any() and not boxed[15:].any()  # within a cell of the box


def test_box_and_propagation_order():
    mask = np.zeros((6, 8), dtype=bool)
    mask[2:4, 3:7] = True
    assert mask_box(mask).tolist() == [3, 2, 7, 4]
    assert mask_box(np.zeros((6, 8), dtype=bool)) is None
    # Click at 0.5 of 5 frames; every frame between the click and a requested time is visited in order.
    assert propagation_chains(0.5, [0.0, 1.0], 5) == ([0.75, 1.0], [0.25, 0.0])
    assert propagation_chains(0.0, [0.6], 3) == ([0.5, 0.6], [])


def test_object_appearance_keeps_every_part_of_a_two_coloured_object():
    """A two-coloured object (3x3 cells, its left column another colour) on a one-colour background: at
    another time every one of its cells is an object cell, although its mean feature matches neither part;
    the region overlapping a box's mask wins over a better-matching region elsewhere, and the re-prompt's
    points lie in that region and its box is the region's."""
    # 16x12 image on an 8-cell grid: cells are 2x2 pixels; 6 rows x 8 columns are valid.
    features = np.zeros((4, 8, 8), dtype=np.float32)
    features[0, :6, :8] = 1.0  # background
    features[:, 1:4, 5:8] = 0.0
    features[1, 1:4, 6:8] = 1.0  # the object's main colour
    features[2, 1:4, 5] = 1.0  # its second colour (left column)
    embedding = Embedding(features=features, image_size=(12, 16))
    mask = np.zeros((12, 16), dtype=bool)
    mask[2:8, 10:16] = True
    appearance = ObjectAppearance.of(embedding, mask)
    assert appearance is not None and len(appearance.object) == 9
    assert ObjectAppearance.of(embedding, np.zeros_like(mask)) is None
    assert ObjectAppearance.of(embedding, np.ones_like(mask)) is None

    later = np.zeros_like(features)
    later[0, :6, :8] = 1.0
    later[:, 2:5, 0:3] = 0.0  # the object moved to rows 2-4, columns 0-2
    later[1, 2:5, 1:3] = 1.0
    later[2, 2:5, 0] = 1.0
    later[:, 0, 6] = 0.0  # a one-cell copy of its main colour elsewhere
    later[1, 0, 6] = 1.0
    moved = Embedding(features=later, image_size=(12, 16))
    cells, distance = appearance.cells(moved)
    expected = np.zeros((6, 8), dtype=bool)
    expected[2:5, 0:3] = True
    expected[0, 6] = True
    np.testing.assert_array_equal(cells, expected)
    near = np.zeros((6, 8), dtype=bool)
    near[2, 2] = True  # the box's mask touches the moved object
    region = object_region(cells, distance, near)
    np.testing.assert_array_equal(region, expected & (np.arange(8) < 3)[None])
    points, box = region_prompt(region, moved)
    assert box.tolist() == [0.0, 4.0, 6.0, 10.0]
    assert points[0].tolist() == [3.0, 7.0]  # the deepest cell (3, 1) first
    assert all(region[int(y // 2), int(x // 2)] for x, y in points)
    assert object_region(np.zeros_like(cells), distance, near) is None


def with_true_depth(embedding: Embedding, depth: np.ndarray) -> Embedding:
    """The embedding with a depth map (H, W) at its cells' centres as the depth cue, as `render_embedding` gives it."""
    centres = cell_centres(embedding.image_size, embedding.grid_size).numpy().astype(int)
    cells = np.zeros((embedding.grid_size, embedding.grid_size), dtype=np.float32)
    cells[: centres.shape[0], : centres.shape[1]] = depth[centres[..., 1], centres[..., 0]]
    return Embedding(embedding.features, embedding.image_size, cells)


@pytest.mark.parametrize("depth_cue", [False, True])
def test_embedding_propagation_follows_a_fast_object_that_a_box_loses(depth_cue):
    """On the encoder features of ground-truth frames (no NeRF), with or without the true depth as the depth cue:
    the fast sphere moves further than its own size per frame, so the paper's box propagation loses it; the
    embedding propagation finds all of it again (t-mIoU 0.45 before the object's appearance kept its parts, 0.78
    now; 0.93 with the depth cue). The slow sphere stays in its box, so both propagations give the same masks."""
    backend = BuiltinSamBackend()
    spec = SyntheticSpec(dataset="n3d", width=64, height=48, frames=6, cameras=1)
    scene, camera = SyntheticScene(), rig_for(spec)[0]
    renders = [scene.render(camera, frame) for frame in range(spec.frames)]
    embeddings = {frame / 5: backend.encode(render.rgb) for frame, render in enumerate(renders)}
    if depth_cue:
        embeddings = {t: with_true_depth(e, renders[round(t * 5)].depth) for t, e in embeddings.items()}
    times = sorted(embeddings)
    results = {}
    for object_id in (2, FAST_SPHERE):
        ids = renders[0].object_ids == object_id
        rows, cols = np.nonzero(ids)
        click = np.array([[cols.mean() + 0.5, rows.mean() + 0.5]])
        for propagation in ("box", "embedding"):
            masks = track(backend, embeddings.__getitem__, click, np.array([1]), 0.0, times, 6, propagation)
            assert [m.time for m in masks] == times
            scores = [iou(m.mask, renders[round(m.time * 5)].object_ids == object_id) for m in masks[1:]]
            results[object_id, propagation] = float(np.mean(scores))
            located = [m for m in masks[1:] if "points" in m.prompt]
            if propagation == "box" or object_id == 2:
                assert not located
            else:
                assert located and all(m.prompt["from_time"] < m.time for m in located)
    assert results[FAST_SPHERE, "box"] < 0.2
    assert results[FAST_SPHERE, "embedding"] > (0.85 if depth_cue else 0.7), results
    assert results[2, "box"] > 0.7 and results[2, "embedding"] == results[2, "box"]
    with pytest.raises(TrackingError, match="unknown propagation"):
        track(backend, embeddings.__getitem__, click, np.array([1]), 0.0, times, 6, "flow")


def test_metrics_match_torchmetrics():
    from torchmetrics.classification import BinaryAccuracy, BinaryJaccardIndex

    rng = np.random.default_rng(0)
    scores = []
    for index in range(4):
        predicted, truth = rng.random((18, 24)) < 0.3, rng.random((18, 24)) < 0.4
        expected_iou = float(BinaryJaccardIndex()(torch.from_numpy(predicted).int(), torch.from_numpy(truth).int()))
        expected_acc = float(BinaryAccuracy()(torch.from_numpy(predicted).int(), torch.from_numpy(truth).int()))
        assert iou(predicted, truth) == pytest.approx(expected_iou)
        assert accuracy(predicted, truth) == pytest.approx(expected_acc)
        scores.append(MaskScore("cam00", index / 3, index == 1, expected_iou, expected_acc))
    empty = np.zeros((4, 4), dtype=bool)
    assert iou(empty, empty) == 1.0 and accuracy(empty, empty) == 1.0
    summary = summarise(scores)
    assert summary["mIoU"] == pytest.approx(scores[1].iou) and summary["masks_at_clicked_time"] == 1
    others = [s for i, s in enumerate(scores) if i != 1]
    assert summary["t-mIoU"] == pytest.approx(np.mean([s.iou for s in others]))
    assert summary["t-accuracy"] == pytest.approx(np.mean([s.accuracy for s in others]))
