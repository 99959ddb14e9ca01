"""Free-viewpoint tracking (Sec 4.5): `ns-gear-track` and its core functions on a model trained with the
real `ns-train` on a tiny synthetic N3D scene with ground-truth object masks."""

from __future__ import annotations

import json
import math
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from PIL import Image

from gear_nerfstudio.tracking.cli import TrackCommand
from tests.conftest import command as run
from gear_nerfstudio.tracking.metrics import MaskScore, accuracy, iou, summarise
from gear_nerfstudio.sam.builtin_backend import BuiltinSamBackend
from gear_nerfstudio.sam.interface import Embedding
from gear_nerfstudio.tools.synthetic.scene import SyntheticScene
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, rig_for
from gear_nerfstudio.tracking.click import HIT_ACCUMULATION, TrackingError, click_point, project_prompt
from gear_nerfstudio.tracking.propagation import (
    centred_box,
    locate_object,
    mask_box,
    object_features,
    propagation_chains,
    render_embedding,
    segment,
    track,
)

FAST_SPHERE = 3
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
    assert summary["times"] == [0.0, 0.5, 1.0]
    assert summary["ground_truth_object"] == FAST_SPHERE
    assert summary["click"]["prompts"][0]["pixel"] == [x, y]

    truth = np.load(scene / "ground_truth" / "cam00.npz")["object_ids"] == FAST_SPHERE
    by_time = {record["time"]: record for record in summary["masks"]}
    assert sorted(by_time) == [0.0, 0.5, 1.0]
    assert "points" in by_time[0.5]["prompt"]  # the projected click at the clicked time
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

    import av

    with av.open(str(out / "overlay" / "cam00.mp4")) as container:
        assert sum(1 for _ in container.decode(video=0)) == 3


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
    mask = segment(backend, embedding, np.array([[12.0, 9.0]]), np.array([1]))
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


def test_locate_object_finds_the_inside_of_the_object_feature_region():
    # 16x12 image on an 8-cell grid: cells are 2x2 pixels; 6 rows x 8 columns are valid.
    features = np.zeros((4, 8, 8), dtype=np.float32)
    features[0, :6, :8] = 1.0  # background
    features[:, 1:4, 5:8] = 0.0
    features[1, 1:4, 5:8] = 1.0  # the object: 3x3 cells, centre cell (2, 6)
    features[1, 1, 5] = 0.9  # its closest-to-mean cell is not its centre
    embedding = Embedding(features=features, image_size=(12, 16))
    mask = np.zeros((12, 16), dtype=bool)
    mask[2:8, 10:16] = True
    found = object_features(embedding, mask)
    assert found is not None
    assert locate_object(embedding, found) == (13.0, 5.0)  # centre of cell (row 2, col 6)
    assert object_features(embedding, np.zeros_like(mask)) is None
    assert object_features(embedding, np.ones_like(mask)) is None
    background_only = Embedding(features=np.where(features[1:2] > 0, 0.0, features), image_size=(12, 16))
    background_only.features[0, :6, :8] = 1.0
    assert locate_object(background_only, found) is None


def test_centred_box_keeps_a_box_that_holds_the_point_and_moves_others_inside_the_image():
    box = np.array([2.0, 2.0, 6.0, 5.0])
    assert centred_box(box, (3.0, 4.0), (12, 16)).tolist() == [2.0, 2.0, 6.0, 5.0]
    assert centred_box(box, (10.0, 8.0), (12, 16)).tolist() == [8.0, 6.5, 12.0, 9.5]
    assert centred_box(box, (15.5, 11.5), (12, 16)).tolist() == [12.0, 9.0, 16.0, 12.0]


def test_embedding_propagation_follows_a_fast_object_that_a_box_loses():
    """On the encoder features of ground-truth frames (no NeRF): the fast sphere moves further than its
    own size per frame, so the paper's box propagation loses it; the embedding propagation finds it again.
    The slow sphere stays in its box, so both propagations give the same masks."""
    backend = BuiltinSamBackend()
    spec = SyntheticSpec(dataset="n3d", width=64, height=48, frames=6, cameras=1)
    scene, camera = SyntheticScene(), rig_for(spec)[0]
    renders = [scene.render(camera, frame) for frame in range(spec.frames)]
    embeddings = {frame / 5: backend.encode(render.rgb) for frame, render in enumerate(renders)}
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
    assert results[FAST_SPHERE, "embedding"] > 0.45
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
