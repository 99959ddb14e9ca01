"""`ns-gear-process` through the real command, on real footage: 14 cameras of N3D's flame_steak
(../shared/data/real/n3d_flame_steak_frame0, its calibration stripped; one frame each, made into short videos whose
brightness marks the instant), starting at known instants, with audio tracks the test makes (one noise recording,
each camera's track starting at its own instant, whole and sub-frame). One processed scene is shared by the tests
of this module. The 31-camera Panoptic capture is measured by `python -m benchmarks process-accuracy` (it needs every
camera of the dome and instants spread over the take: about a minute here)."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from gear_nerfstudio.process.accuracy import pose_errors
from tests.conftest import IMPORT_WARNING, SHARED_REAL, command, ns

FLAME = SHARED_REAL / "n3d_flame_steak_frame0"
CAMERAS = tuple(f"cam{i:02d}" for i in range(14))
FPS = 30
OFFSETS = tuple((0.0, 1.0, 0.4, 2.0, 1.6, -0.3, 1.2)[i % 7] for i in range(14))
"""Instant of each camera's frame 0, in frames of cam00's clock: whole and sub-frame (rounded: 0, 1 or 2)."""
LENGTH = 6
"""Frames per input video; the window every camera covers is instants 2-5."""
AUDIO_RATE = 48000
ORDER = ("cam05",) + tuple(name for name in CAMERAS if name != "cam05")
"""Input cameras in output order (cam05 held out)."""


def brightness(instant: int) -> float:
    """What the frames of an instant are multiplied by, so that the output shows which instant each frame is."""
    return 1.0 - 0.1 * instant


pytestmark = [pytest.mark.cost(110), pytest.mark.skipif(not FLAME.is_dir(), reason="shared real data not present")]


def decode(path: Path) -> list:
    """The RGB frames of a video."""
    import av

    with av.open(str(path)) as container:
        return [frame.to_ndarray(format="rgb24") for frame in container.decode(video=0)]


def encode(path: Path, frames: list, fps: int = FPS, audio: np.ndarray = None) -> None:
    """H.264 video, with a mono AAC track when `audio` (float32 at AUDIO_RATE) is given."""
    import av

    with av.open(str(path), mode="w") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.height, stream.width = frames[0].shape[:2]
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": "12"}
        sound = None if audio is None else container.add_stream("aac", rate=AUDIO_RATE, layout="mono")
        for rgb in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")))
        container.mux(stream.encode())
        if sound is not None:
            for start in range(0, len(audio), 1024):
                chunk = av.AudioFrame.from_ndarray(audio[None, start : start + 1024], format="fltp", layout="mono")
                chunk.sample_rate = AUDIO_RATE
                container.mux(sound.encode(chunk))
            container.mux(sound.encode())


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """The 14 videos (offsets and audio as above; frames at the whole-frame offsets, audio at the exact ones), and
    the scene ns-gear-process makes of them with `--sync audio`, cam05 held out: (input folder, output folder,
    the command's result). Without the self-check (its own module)."""
    root = tmp_path_factory.mktemp("process")
    inputs = root / "videos"
    inputs.mkdir()
    noise = np.random.default_rng(0).normal(0, 0.3, AUDIO_RATE).astype(np.float32)
    samples = LENGTH * AUDIO_RATE // FPS
    for name, offset in zip(CAMERAS, OFFSETS):
        frame = decode(FLAME / f"{name}.mp4")[0].astype(np.float32)
        instants = range(int(round(offset)), int(round(offset)) + LENGTH)
        frames = [(frame * brightness(t)).round().astype(np.uint8) for t in instants]
        start = int(round((offset + 1) * AUDIO_RATE / FPS))
        encode(inputs / f"{name}.mp4", frames, audio=noise[start : start + samples])
    output = root / "scene"
    result = ns("ns-gear-process", "--data", str(inputs), "--output-dir", str(output), "--sync", "audio",
                "--held-out", "cam05", "--no-self-check", cwd=root)  # fmt: skip
    return inputs, output, result


def test_audio_sync_finds_whole_and_sub_frame_offsets(rig):
    """Each camera's offset is reported with its confidence, within a tenth of a frame (the issue asks for one)."""
    _, output, result = rig
    found = dict(re.findall(r"(cam\d\d)\.mp4: offset ([-+][\d.]+) frames \(confidence [\d.]+\)", result.stdout))
    assert sorted(found) == sorted(CAMERAS), result.stdout
    for name, offset in zip(CAMERAS, OFFSETS):
        assert abs(float(found[name]) - offset) < 0.1, (name, found[name], offset)
    confidences = [float(c) for c in re.findall(r"confidence ([\d.]+)", result.stdout)]
    assert min(confidences) > 0.5, result.stdout


def test_frames_are_cut_to_the_window_every_camera_covers(rig):
    """Whole-frame offsets 0, 1 or 2 and 6 frames each: instants 2 .. 5 in every output video (the nearest of the
    instants' brightness levels, 0.1 apart; the crop and the codecs move a level by up to 0.03); each camera's first
    frame is 2 - its offset; cam05 is cam00, the others follow in sorted order."""
    _, output, _ = rig
    summary = json.loads((output / "transforms.json").read_text())
    assert summary["num_frames"] == 4
    by_source = {frame["source"]: frame for frame in summary["frames"]}
    for name, offset in zip(CAMERAS, OFFSETS):
        assert by_source[f"{name}.mp4"]["first_source_frame"] == 2 - int(round(offset)), name
    assert [frame["source"] for frame in summary["frames"]] == [f"{name}.mp4" for name in ORDER]
    assert [frame["file_path"] for frame in summary["frames"]] == [f"cam{i:02d}.mp4" for i in range(14)]
    for index, name in enumerate(ORDER):
        source = decode(FLAME / f"{name}.mp4")[0].mean()
        shown = [frame.mean() / source for frame in decode(output / f"cam{index:02d}.mp4")]
        instants = [int(np.argmin([abs(level - brightness(t)) for t in range(LENGTH + 2)])) for level in shown]
        assert instants == [2, 3, 4, 5], (name, shown)


def test_recovered_rig_matches_the_capture_calibration(rig):
    """After a similarity alignment, centres within 2 % of the rig's size and rotations within 1 degree of the
    capture's own calibration; one focal per camera, principal point centred (N3D's file has neither)."""
    _, output, _ = rig
    truth = np.load(FLAME / "poses_bounds.npy")[[CAMERAS.index(name) for name in ORDER]]
    recovered = np.load(output / "poses_bounds.npy")
    errors = pose_errors(recovered, truth)
    assert errors["centre_pct"].max() < 2.0, errors
    assert errors["rotation_deg"].max() < 1.0, errors
    assert (recovered[:, 15] > 0).all() and (recovered[:, 16] > recovered[:, 15]).all()
    focal_ratio = recovered[:, 14] / (truth[:, 14] * 672 / truth[:, 9])  # the file's focal is at 2690 x 2016
    assert np.abs(focal_ratio - 1).max() < 0.05, focal_ratio


def test_the_scene_reads_with_the_n3d_parser_and_comes_with_summary_and_plot(rig, tmp_path):
    _, output, _ = rig
    config = Neural3DVideoDataParserConfig(data=output, cache_dir=tmp_path / "cache", frame_count=2)
    outputs = config.setup().get_dataparser_outputs("train")
    assert outputs.metadata["camera_names"] == [f"cam{i:02d}" for i in range(14)]
    assert len(outputs.image_filenames) == 13 * 2
    summary = json.loads((output / "transforms.json").read_text())
    assert summary["num_points"] > 100 and 0 < summary["reprojection_error_px"] < 2
    assert summary["self_check_frames"] == []
    for frame in summary["frames"]:
        assert frame["cx"] == frame["w"] / 2 and frame["fl_x"] == frame["fl_y"]
        assert frame["reprojection_error_px"] < 2 and frame["observations"] > 20
        assert "self_check" not in frame  # --no-self-check (tests/test_self_check.py runs it)
    assert (output / "rig.png").stat().st_size > 10_000
    assert (output / "sparse_points.ply").is_file() and (output / "colmap" / "sparse" / "cameras.bin").is_file()
    assert sorted(p.name for p in (output / "colmap").iterdir()) == ["sparse"]
    assert not list(output.parent.glob(".scene.tmp-*"))


def expect_one_line_error(result, *fragments) -> None:
    lines = [line for line in (result.stdout + result.stderr).splitlines() if line.strip()]
    lines = [line for line in lines if not IMPORT_WARNING.search(line)]
    assert result.returncode == 1, result.stderr[-3000:]
    assert len(lines) == 1 and lines[0].startswith("error: "), lines
    for fragment in fragments:
        assert fragment in lines[0], lines


def process(data: Path, output: Path, *options: str):
    """Run ns-gear-process; nothing may be left beside the output (no output folder, no temporary one)."""
    result = command("ns-gear-process", "--data", str(data), "--output-dir", str(output), *options, cwd=output.parent)
    assert not output.exists() and not list(output.parent.glob(f".{output.name}.tmp-*"))
    return result


def test_an_existing_output_folder_is_not_touched(rig, tmp_path):
    inputs, _, _ = rig
    output = tmp_path / "scene"
    output.mkdir()
    (output / "keep.txt").write_text("mine")
    result = command("ns-gear-process", "--data", str(inputs), "--output-dir", str(output), cwd=tmp_path)
    expect_one_line_error(result, str(output), "already exists")
    assert [p.name for p in output.iterdir()] == ["keep.txt"]


def test_a_video_that_does_not_decode(rig, tmp_path):
    inputs, _, _ = rig
    data = tmp_path / "videos"
    data.mkdir()
    for name in CAMERAS[:2]:
        shutil.copy(inputs / f"{name}.mp4", data)
    (data / "cam99.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 8)
    expect_one_line_error(process(data, tmp_path / "scene"), str(data / "cam99.mp4"), "does not decode")


def test_frames_of_different_sizes_within_one_camera(tmp_path):
    from PIL import Image

    data = tmp_path / "frames"
    for camera in ("a", "b"):
        (data / camera).mkdir(parents=True)
        for index in range(3):
            size = (40, 30) if (camera, index) != ("b", 2) else (48, 30)
            Image.new("RGB", size, (index * 40, 90, 20)).save(data / camera / f"{index:03d}.png")
    expect_one_line_error(process(data, tmp_path / "scene"), str(data / "b" / "002.png"), "48x30", "camera b")


def test_a_camera_with_another_frame_rate(rig, tmp_path):
    inputs, _, _ = rig
    data = tmp_path / "videos"
    data.mkdir()
    shutil.copy(inputs / "cam02.mp4", data)
    encode(data / "cam03.mp4", decode(inputs / "cam05.mp4"), fps=25)
    expect_one_line_error(process(data, tmp_path / "scene"), str(data / "cam03.mp4"), "25.000 frames per second")


def test_a_camera_whose_offset_cannot_be_found(rig, tmp_path):
    inputs, _, _ = rig
    data = tmp_path / "videos"
    data.mkdir()
    shutil.copy(inputs / "cam02.mp4", data)
    encode(data / "cam03.mp4", decode(inputs / "cam05.mp4"))  # no audio track
    result = process(data, tmp_path / "scene", "--sync", "audio")
    expect_one_line_error(result, str(data / "cam03.mp4"), "offset cannot be found")


def test_too_few_cameras_registered_names_the_others(tmp_path):
    """Four N3D cameras and one whose frame has no texture: COLMAP cannot register it."""
    data = tmp_path / "videos"
    data.mkdir()
    for index in range(4):
        shutil.copy(FLAME / f"cam{index:02d}.mp4", data)
    blank = np.full_like(decode(FLAME / "cam00.mp4")[0], 128)
    encode(data / "cam_blank.mp4", [blank])
    result = process(data, tmp_path / "scene")
    expect_one_line_error(result, "registered 4 of 5 cameras", "not registered: cam_blank.mp4")


def test_two_calibrations_of_the_same_frames_give_the_same_cameras(tmp_path):
    """COLMAP's verification RANSAC and mapper are seeded: 94 of 395 verified pairs of the Panoptic capture differed
    between runs while they were not (benchmarks/results/process_windows.md)."""
    from PIL import Image
    from rich.progress import Progress

    from gear_nerfstudio.process.calibrate import reconstruct, summarise

    for name in CAMERAS:
        (tmp_path / name).mkdir()
        Image.fromarray(decode(FLAME / f"{name}.mp4")[0]).save(tmp_path / name / "00000.png")
    runs = []
    for _ in range(2):
        with Progress() as progress:
            runs.append(summarise(reconstruct(tmp_path, CAMERAS, [0], "SIMPLE_RADIAL", None, progress), CAMERAS))
    assert np.array_equal(runs[0].cam_from_world, runs[1].cam_from_world)
    assert all(np.array_equal(a.params, b.params) for a, b in zip(runs[0].cameras, runs[1].cameras))

