"""Bad input: each case stops with a DatasetError that names the file and the problem."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.tools.synthetic.writers import write_video
from tests.test_dataparsers import parse


@pytest.fixture()
def copy_of(scene_dirs, tmp_path):
    def make(name: str) -> dict:
        target = tmp_path / name
        shutil.copytree(scene_dirs[name], target)
        return {name: target}

    return make


def expect_error(dirs, name, cache_dir, *fragments, split="train", **options):
    with pytest.raises(DatasetError) as info:
        parse(name, dirs, cache_dir, split, **options)
    message = str(info.value)
    for fragment in fragments:
        assert fragment in message, message
    assert not list(cache_dir.rglob("*.tmp")) if cache_dir.exists() else True
    return message


def test_empty_folders(tmp_path, cache_dir):
    for name, pattern in (("technicolor", "_undist_"), ("n3d", "camXX.mp4"), ("immersive", "camera_XXXX.mp4")):
        empty = tmp_path / f"empty-{name}"
        empty.mkdir()
        if name == "immersive":
            (empty / "models.json").write_text(json.dumps([{"name": "camera_0001"}]))
        with pytest.raises(DatasetError) as info:
            parse(name, {name: empty}, cache_dir)
        assert str(empty) in str(info.value)
    with pytest.raises(DatasetError, match="does not exist"):
        parse("n3d", {"n3d": tmp_path / "nowhere"}, cache_dir)


def test_technicolor_camera_file_problems(copy_of, cache_dir):
    dirs = copy_of("technicolor")
    cameras = dirs["technicolor"] / "cameras_parameters.txt"
    original = cameras.read_text()

    cameras.unlink()
    expect_error(dirs, "technicolor", cache_dir, "cameras_parameters.txt", "missing")

    cameras.write_bytes(b"\xff\xfe\x00garbage")
    expect_error(dirs, "technicolor", cache_dir, "cameras_parameters.txt", "cannot read")

    lines = original.splitlines()
    cameras.write_text("\n".join(lines[:3] + [" ".join(lines[3].split()[:11])] + lines[4:]) + "\n")
    expect_error(dirs, "technicolor", cache_dir, "cameras_parameters.txt", "line 4 has 11 columns")

    cameras.write_text("\n".join(lines[:-1]) + "\n")
    expect_error(dirs, "technicolor", cache_dir, "cameras_parameters.txt", "15 camera rows", "16 cameras")


def test_technicolor_broken_and_missing_frames(copy_of, cache_dir):
    dirs = copy_of("technicolor")
    broken = dirs["technicolor"] / "Synthetic_undist_00002_03.png"
    broken.write_bytes(broken.read_bytes()[:60])
    expect_error(dirs, "technicolor", cache_dir, str(broken), "cannot read the image")

    broken.unlink()
    expect_error(dirs, "technicolor", cache_dir, "camera 03 has no frame(s) [2]")


def test_frame_window_past_the_end(scene_dirs, cache_dir):
    expect_error(scene_dirs, "technicolor", cache_dir, "runs past the end", "last frame present: 4", frame_start=3, frame_count=5)
    expect_error(scene_dirs, "n3d", cache_dir, "frame_start 9 is outside", frame_start=9)
    expect_error(scene_dirs, "immersive", cache_dir, "runs past the end", frame_count=10)


def test_n3d_poses_problems(copy_of, cache_dir):
    dirs = copy_of("n3d")
    poses_path = dirs["n3d"] / "poses_bounds.npy"
    poses = np.load(poses_path)

    np.save(poses_path, poses[:-1])
    expect_error(dirs, "n3d", cache_dir, "poses_bounds.npy", "4 pose rows", "5 videos")

    np.save(poses_path, poses[:, :15])
    expect_error(dirs, "n3d", cache_dir, "poses_bounds.npy", "expected (N, 17)")

    poses_path.write_bytes(b"not a numpy file")
    expect_error(dirs, "n3d", cache_dir, "poses_bounds.npy", "cannot read")

    poses_path.unlink()
    expect_error(dirs, "n3d", cache_dir, "poses_bounds.npy", "missing")


def test_videos_of_different_lengths(copy_of, cache_dir):
    dirs = copy_of("n3d")
    video = dirs["n3d"] / "cam02.mp4"
    write_video(video, [np.zeros((30, 40, 3), np.uint8)] * 3, fps=30)
    message = expect_error(dirs, "n3d", cache_dir, "different lengths")
    assert "'cam02.mp4': 3" in message and "'cam01.mp4': 4" in message


def test_broken_videos(copy_of, cache_dir):
    dirs = copy_of("immersive")
    video = dirs["immersive"] / "camera_0003.mp4"
    video.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(200))
    expect_error(dirs, "immersive", cache_dir, str(video), "cannot read the video")

    dirs = copy_of("n3d")
    video = dirs["n3d"] / "cam00.mp4"
    data = video.read_bytes()
    video.write_bytes(data[: len(data) // 2])
    expect_error(dirs, "n3d", cache_dir, str(video), split="test")


def test_immersive_models_problems(copy_of, cache_dir):
    dirs = copy_of("immersive")
    models_path = dirs["immersive"] / "models.json"
    models = json.loads(models_path.read_text())

    models_path.write_text("[{not json")
    expect_error(dirs, "immersive", cache_dir, "models.json", "cannot read")

    broken = [dict(m) for m in models]
    del broken[2]["focal_length"]
    models_path.write_text(json.dumps(broken))
    expect_error(dirs, "immersive", cache_dir, "models.json", "camera_0003", "focal_length")

    broken = [dict(m) for m in models]
    broken[0]["projection_type"] = "equirectangular"
    models_path.write_text(json.dumps(broken))
    expect_error(dirs, "immersive", cache_dir, "models.json", "equirectangular")

    models_path.unlink()
    expect_error(dirs, "immersive", cache_dir, "models.json", "missing")


def test_unknown_held_out_camera(scene_dirs, cache_dir):
    expect_error(scene_dirs, "n3d", cache_dir, "held-out camera 'cam42' not found", held_out_camera="cam42")
