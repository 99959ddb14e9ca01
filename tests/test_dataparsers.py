"""The three parsers against the generator's own cameras, frames and times, and on real N3D data."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from gear_nerfstudio.data_parsers.google_immersive import GoogleImmersiveDataParserConfig
from gear_nerfstudio.data_parsers.multiview import surrounds_scene
from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from gear_nerfstudio.data_parsers.technicolor import TechnicolorDataParserConfig
from gear_nerfstudio.projection import project
from gear_nerfstudio.tools.synthetic.scene import SyntheticScene
from gear_nerfstudio.tools.synthetic.writers import rig_for
from tests.conftest import SHARED_REAL, SPECS

PARSERS = {
    "technicolor": (TechnicolorDataParserConfig, {"near": 1.0, "far": 8.0}),
    "n3d": (Neural3DVideoDataParserConfig, {}),
    "immersive": (GoogleImmersiveDataParserConfig, {"near": 0.3, "far": 10.0}),
}
HELD_OUT = {"technicolor": "10", "n3d": "cam00", "immersive": "camera_0001"}


def parse(name, scene_dirs, cache_dir, split="train", **options):
    config_class, defaults = PARSERS[name]
    config = config_class(data=scene_dirs[name], cache_dir=cache_dir, **{**defaults, **options})
    return config.setup().get_dataparser_outputs(split)


def visible_points(name):
    """World points on visible surfaces at frame 0, from the generator's rays and ground-truth depth."""
    scene = SyntheticScene(SPECS[name].motion)
    points = []
    for camera in rig_for(SPECS[name])[:3]:
        render = scene.render(camera, 0)
        jj, ii = np.mgrid[0 : camera.height : 3, 0 : camera.width : 3]
        uv = np.stack([ii.ravel() + 0.5, jj.ravel() + 0.5], axis=-1)
        depth = render.depth[jj.ravel(), ii.ravel()]
        origins, dirs = camera.rays(uv)
        keep = np.isfinite(depth) & (depth < 20)
        points.append(origins[keep] + depth[keep, None] * dirs[keep])
    return np.concatenate(points)


def to_scene(points: np.ndarray, outputs) -> torch.Tensor:
    """Dataset world coordinates -> the parser's normalised scene."""
    transform = outputs.dataparser_transform.double()
    world = torch.from_numpy(points) @ transform[:, :3].T + transform[:, 3]
    return (world * outputs.dataparser_scale).float()


@pytest.mark.parametrize("name", ["technicolor", "n3d", "immersive"])
@pytest.mark.parametrize("downscale", [1, 2])
def test_parsed_cameras_project_like_the_generator(name, downscale, scene_dirs, cache_dir):
    points = visible_points(name)
    generator = {camera.name: camera for camera in rig_for(SPECS[name])}
    checked = 0
    for split in ("train", "test"):
        outputs = parse(name, scene_dirs, cache_dir, split, downscale_factor=downscale)
        first = torch.nonzero(outputs.metadata["frame_ids"] == 0).ravel()
        cameras = outputs.cameras[first]
        scene_points = to_scene(points, outputs)
        uv, in_front = project(cameras, scene_points)
        for k, index in enumerate(first.tolist()):
            camera = generator[outputs.metadata["camera_names"][outputs.metadata["camera_ids"][index]]]
            width, height = int(cameras.width[k]), int(cameras.height[k])
            assert (width, height) == (camera.width // downscale, camera.height // downscale)
            expected, expected_front = camera.project(points)
            expected = expected * np.array([width / camera.width, height / camera.height])
            inside = expected_front & (expected[:, 0] >= 0) & (expected[:, 0] <= width)
            inside &= (expected[:, 1] >= 0) & (expected[:, 1] <= height)
            assert inside.sum() > 20
            assert bool(in_front[k][torch.from_numpy(inside)].all())
            error = np.abs(uv[k].numpy()[inside] - expected[inside]).max()
            assert error < 0.5, f"{name} {camera.name}: projection differs by {error:.3f} px"

            # nerfstudio's own rays through the generator's pixels must pass through the points.
            coords = torch.from_numpy(expected[inside][:, ::-1].copy()).float()  # (row, col)
            rays = cameras.generate_rays(camera_indices=k, coords=coords)
            offset = scene_points[torch.from_numpy(inside)] - rays.origins
            along = (offset * rays.directions).sum(-1)
            across = torch.linalg.norm(offset - along[:, None] * rays.directions, dim=-1)
            angle_px = (across / along) * float(cameras.fx[k])
            assert float(angle_px.max()) < 0.5, f"{name} {camera.name}: ray misses by {float(angle_px.max()):.3f} px"
            checked += 1
    assert checked == len(generator)


@pytest.mark.parametrize("name", ["technicolor", "n3d", "immersive"])
def test_splits_times_and_frames(name, scene_dirs, cache_dir):
    spec = SPECS[name]
    train = parse(name, scene_dirs, cache_dir, "train")
    test = parse(name, scene_dirs, cache_dir, "test")
    val = parse(name, scene_dirs, cache_dir, "val")
    n_cameras = len(rig_for(spec))
    T = spec.frames
    assert len(train.image_filenames) == (n_cameras - 1) * T
    assert len(test.image_filenames) == len(val.image_filenames) == T
    assert set(test.metadata["camera_ids"].tolist()) == {test.metadata["camera_names"].index(HELD_OUT[name])}
    assert HELD_OUT[name] not in {train.metadata["camera_names"][i] for i in train.metadata["camera_ids"].tolist()}
    assert torch.allclose(test.cameras.times.ravel(), torch.linspace(0, 1, T))
    assert test.metadata["num_frames"] == T
    assert torch.equal(test.metadata["frame_ids"], torch.arange(T))

    # The frame at time t of the held-out camera is the generator's frame t (no off-by-one in decoding).
    camera = {c.name: c for c in rig_for(spec)}[HELD_OUT[name]]
    scene = SyntheticScene(spec.motion)
    for frame in range(T):
        loaded = np.asarray(Image.open(test.image_filenames[frame]).convert("RGB"), dtype=np.float32)
        errors = [np.abs(loaded - scene.render(camera, f).rgb).mean() for f in range(T)]
        assert int(np.argmin(errors)) == frame and errors[frame] < 4.0


def test_frame_window_selects_frames_and_rescales_times(scene_dirs, cache_dir):
    spec = SPECS["technicolor"]  # its files are numbered from 1, as in some real scenes
    default = parse("technicolor", scene_dirs, cache_dir, "test")
    assert default.metadata["frame_numbers"] == list(range(1, 1 + spec.frames))
    window = parse("technicolor", scene_dirs, cache_dir, "test", frame_start=2, frame_count=2)
    assert window.metadata["frame_numbers"] == [2, 3]
    assert [p.name for p in window.image_filenames] == ["Synthetic_undist_00002_10.png", "Synthetic_undist_00003_10.png"]
    assert window.cameras.times.ravel().tolist() == [0.0, 1.0]
    single = parse("n3d", scene_dirs, cache_dir, "train", frame_start=3, frame_count=1)
    assert single.cameras.times.ravel().tolist() == [0.0] * (SPECS["n3d"].cameras - 1)


@pytest.mark.parametrize("name", ["technicolor", "n3d", "immersive"])
def test_scene_fits_the_box_and_bounds_are_ordered(name, scene_dirs, cache_dir):
    outputs = parse(name, scene_dirs, cache_dir, "train")
    centres = outputs.cameras.camera_to_worlds[:, :, 3]
    assert float(centres.abs().max()) <= 1.0
    assert 0 < outputs.metadata["near"] < outputs.metadata["far"]
    assert outputs.metadata["unbounded"] == (name == "immersive")
    # Orientation 'up': the mean camera up vector (column 1 of camera-to-world) is +z.
    up = outputs.cameras.camera_to_worlds[:, :, 1].mean(0)
    assert float(up[2]) > 0.95 * float(torch.linalg.norm(up))


@pytest.mark.skipif(not (SHARED_REAL / "n3d_flame_steak_frame0").is_dir(), reason="shared real data not present")
def test_real_n3d_frame_parses(tmp_path):
    config = Neural3DVideoDataParserConfig(data=SHARED_REAL / "n3d_flame_steak_frame0", cache_dir=tmp_path)
    parser = config.setup()
    train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    assert len(train.image_filenames) == 20 and len(test.image_filenames) == 1
    assert test.metadata["camera_names"][int(test.metadata["camera_ids"][0])] == "cam00"
    assert train.cameras.times.ravel().tolist() == [0.0] * 20
    raw = np.load(SHARED_REAL / "n3d_flame_steak_frame0" / "poses_bounds.npy")
    calib_h, calib_w, focal = raw[0, 4], raw[0, 9], raw[0, 14]
    width, height = Image.open(test.image_filenames[0]).size
    assert (int(test.cameras.width[0]), int(test.cameras.height[0])) == (width, height) == (672, 504)
    assert float(test.cameras.fx[0]) == pytest.approx(focal * width / calib_w, rel=1e-5)
    assert float(test.cameras.fy[0]) == pytest.approx(focal * height / calib_h, rel=1e-5)
    assert float(test.cameras.cx[0]) == width / 2 and float(test.cameras.cy[0]) == height / 2
    # A forward-facing rig: every camera looks roughly the same way as the mean view direction.
    forward = -train.cameras.camera_to_worlds[:, :, 2]
    mean = forward.mean(0) / torch.linalg.norm(forward.mean(0))
    assert float((forward @ mean).min()) > 0.8


def ring_rig(count: int = 12, radius: float = 3.0, height: float = 2.0) -> np.ndarray:
    """Camera-to-world poses (OpenGL axes) on a ring, each looking at a point on the floor in the middle."""
    poses = []
    for angle in np.linspace(0, 2 * np.pi, count, endpoint=False):
        centre = np.array([radius * np.cos(angle), radius * np.sin(angle), height])
        back = centre - np.zeros(3)
        back /= np.linalg.norm(back)
        right = np.cross([0.0, 0.0, 1.0], back)
        right /= np.linalg.norm(right)
        poses.append(np.stack([right, np.cross(back, right), back, centre], axis=-1))
    return np.array(poses)


def test_a_rig_that_surrounds_its_scene_is_told_from_forward_facing_rigs(scene_dirs, cache_dir):
    assert surrounds_scene(ring_rig())
    for name in ("technicolor", "n3d"):
        config_class, defaults = PARSERS[name]
        rig = config_class(data=scene_dirs[name], cache_dir=cache_dir, **defaults).setup().read_rig()
        assert not surrounds_scene(rig.camera_to_worlds)


@pytest.mark.skipif(not (SHARED_REAL / "panoptic_basketball").is_dir(), reason="shared real data not present")
def test_a_dome_capture_fits_the_box_of_its_cameras(tmp_path):
    """The real dome capture: its frusta reach 7 units past every camera, its scene lies inside the rig."""
    def outputs(scene_box):
        config = TechnicolorDataParserConfig(
            data=SHARED_REAL / "panoptic_basketball", near=0.3, far=7.0, cache_dir=tmp_path, scene_box=scene_box
        )
        return config.setup().get_dataparser_outputs("train")

    auto, frusta = outputs("auto"), outputs("frusta")
    centres = auto.cameras.camera_to_worlds[:, :, 3]
    assert 0.85 < float(centres.abs().max()) <= 1.0  # the cameras fill the box
    assert auto.dataparser_scale > 2 * frusta.dataparser_scale  # twice the plane resolution on the scene
    assert auto.dataparser_scale == outputs("rig").dataparser_scale
