"""Bad input: each case stops with a DatasetError that names the file and the problem."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.tools.synthetic.writers import write_video
from tests.conftest import IMPORT_WARNING, command
from tests.test_dataparsers import parse

pytestmark = pytest.mark.cost(30)


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


DRIVER = """
import contextlib, io, json, sys
from nerfstudio.scripts import train

results = {}
for name, argv in json.loads(sys.argv[1]).items():
    output = io.StringIO()
    with contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
        sys.argv = ["ns-train", *argv]
        try:
            train.entrypoint()
            status = 0
        except SystemExit as exit:
            status = exit.code
        except BaseException as error:  # what reaches the top of ns-train goes to sys.excepthook
            sys.excepthook(type(error), error, error.__traceback__)
            status = 1
    results[name] = {"status": status, "output": output.getvalue()}
print(json.dumps(results))
"""


def bad_inputs(copy_of) -> dict:
    """One scene folder per kind of bad input of the tests above: name -> (parser, folder, options, fragment)."""
    cases = {}

    def case(name, dataset, parser, fragment, damage=None, options=()):
        folder = copy_of(dataset)[dataset] if damage else None
        if damage:
            target = folder.with_name(name)
            folder.rename(target)
            damage(target)
            folder = target
        cases[name] = (parser, folder, list(options), fragment)
        return folder

    case("camera-file-missing", "technicolor", "technicolor-data", "cameras_parameters.txt: the camera file is missing",
         lambda d: (d / "cameras_parameters.txt").unlink(), ["--near", "1", "--far", "8"])
    case("broken-png", "technicolor", "technicolor-data", "Synthetic_undist_00002_03.png",
         lambda d: (d / "Synthetic_undist_00002_03.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(50)),
         ["--near", "1", "--far", "8"])
    case("window-past-end", "n3d", "neural-3d-video-data", "frame_start 9 is outside", lambda d: None,
         ["--frame-start", "9"])
    case("poses-shape", "n3d", "neural-3d-video-data", "expected (N, 17)",
         lambda d: np.save(d / "poses_bounds.npy", np.load(d / "poses_bounds.npy")[:, :15]))
    case("video-lengths", "n3d", "neural-3d-video-data", "different lengths",
         lambda d: write_video(d / "cam02.mp4", [np.zeros((30, 40, 3), np.uint8)] * 3, fps=30))
    case("broken-video", "immersive", "google-immersive-data", "camera_0003.mp4: cannot read the video",
         lambda d: (d / "camera_0003.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(200)),
         ["--near", "0.3", "--far", "10"])
    case("models-json", "immersive", "google-immersive-data", "models.json: cannot read",
         lambda d: (d / "models.json").write_text("[{not json"), ["--near", "0.3", "--far", "10"])
    case("held-out-camera", "n3d", "neural-3d-video-data", "held-out camera 'cam42' not found", lambda d: None,
         ["--held-out-camera", "cam42"])
    case("wrong-parser", "n3d", "technicolor-data", "use `ns-train gear-nerf neural-3d-video-data", lambda d: None)
    return cases


def test_every_bad_input_stops_ns_train_in_one_line_and_writes_nothing(copy_of, tmp_path):
    """ns-train's own entry point on each bad input: at most 3 lines of output (no traceback, no printed config),
    the file and problem named, exit status 1, and no run folder. Also too few iterations for a gear update."""
    cases = {}
    for name, (parser, folder, options, fragment) in bad_inputs(copy_of).items():
        argv = ["gear-nerf-small", "--output-dir", str(tmp_path / "runs" / name), "--machine.device-type", "cpu",
                "--vis", "tensorboard", parser, "--data", str(folder), "--cache-dir", str(tmp_path / "cache"), *options]
        cases[name] = (argv, fragment)
    n3d = copy_of("n3d")["n3d"]
    cases["no-gear-update"] = (
        ["gear-nerf-small", "--output-dir", str(tmp_path / "runs" / "no-gear-update"), "--max-num-iterations", "10",
         "neural-3d-video-data", "--data", str(n3d), "--cache-dir", str(tmp_path / "cache")],
        "none would run in steps 0..9",
    )
    result = subprocess.run(
        [sys.executable, "-c", DRIVER, json.dumps({name: argv for name, (argv, _) in cases.items()})],
        capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    outcomes = json.loads(result.stdout.splitlines()[-1])
    for name, (_, fragment) in cases.items():
        lines = [line for line in outcomes[name]["output"].splitlines() if line.strip()]
        assert outcomes[name]["status"] == 1, (name, lines)
        assert len(lines) <= 3 and lines[-1].startswith("error: ") and fragment in lines[-1], (name, lines)
        assert not (tmp_path / "runs" / name).exists(), name


def test_ns_train_reports_a_wrong_parser_in_one_line(scene_dirs, tmp_path):
    """The real ns-train, with the default (Technicolor) parser on an N3D folder: one line, the right parser."""
    result = command("ns-train", "gear-nerf-small", "--output-dir", str(tmp_path / "runs"), "--data",
                     str(scene_dirs["n3d"]), cwd=tmp_path)
    errors = [line for line in result.stderr.splitlines() if not IMPORT_WARNING.search(line)]
    assert result.returncode == 1, result.stderr
    assert errors == [
        f"error: {scene_dirs['n3d']}: no Technicolor frames named <Scene>_undist_<frame:05d>_<cam:02d>.png (the folder "
        f"looks like neural-3d-video-data's layout: use `ns-train gear-nerf neural-3d-video-data --data "
        f"{scene_dirs['n3d']}`)"
    ], result.stderr
    assert not (tmp_path / "runs").exists()
