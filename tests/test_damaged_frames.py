"""Damaged frames are found while the frame cache is built and named by file and frame: they stop the run, or,
with `skip_damaged_frames`, are left out of the images with one warning line each."""

from __future__ import annotations

import shutil
import struct
import zlib
from pathlib import Path

import av
import numpy as np
import pytest
from PIL import Image

from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.data.frame_cache import cache_image_frames, cache_video_frames, video_info
from tests.conftest import SHARED_REAL, command
from tests.test_dataparsers import parse


@pytest.fixture()
def copy_of(scene_dirs, tmp_path):
    def make(name: str) -> dict:
        return {name: Path(shutil.copytree(scene_dirs[name], tmp_path / name))}

    return make


def conceal(video: Path, frame: int = 0) -> None:
    """Zero the slice data of a frame (0-based, in decode order), keeping the file's structure and the NAL unit
    lengths: the decoder conceals the loss and, by default, returns every frame without raising (the reported
    case)."""
    with av.open(str(video)) as container:
        packet = [p for p in container.demux(video=0) if p.size > 0][frame]
        start, end = packet.pos, packet.pos + packet.size
    data = bytearray(video.read_bytes())
    units = []  # (offset, length) of the NAL units of the packet (4-byte lengths, as in MP4)
    offset = start
    while offset < end:
        length = int.from_bytes(data[offset : offset + 4], "big")
        units.append((offset + 4, length))
        offset += 4 + length
    unit, length = max(units, key=lambda u: u[1])
    data[unit + 8 : unit + length - 8] = bytes(length - 16)
    video.write_bytes(data)


def plain_decode(video: Path) -> int:
    """How many frames PyAV decodes from a video with its default settings (the cache's decoding before damage
    was checked)."""
    with av.open(str(video)) as container:
        return sum(1 for _ in container.decode(video=0))


def test_a_concealed_key_frame_stops_naming_the_video_and_the_frame(copy_of, cache_dir):
    dirs = copy_of("n3d")
    video = dirs["n3d"] / "cam01.mp4"
    conceal(video)
    assert plain_decode(video) == 4  # a plain decode notices nothing

    with pytest.raises(DatasetError) as info:
        parse("n3d", dirs, cache_dir)
    message = str(info.value)
    assert message.startswith(f"{video}: frame 0 is damaged: the decoder reports '"), message
    assert "--skip-damaged-frames True" in message and "\n" not in message
    # cam01 is the first training camera: nothing was cached, nothing half-written.
    assert not list(cache_dir.rglob("*.png")) and not list(cache_dir.rglob("*.tmp"))


def test_damaged_video_frames_are_left_out_on_request(copy_of, cache_dir, capsys):
    dirs = copy_of("n3d")
    video = dirs["n3d"] / "cam01.mp4"
    conceal(video)

    outputs = parse("n3d", dirs, cache_dir, skip_damaged_frames=True)
    names = outputs.metadata["camera_names"]
    kept = [names[int(c)] for c in outputs.metadata["camera_ids"]]
    # Every frame of cam01 is decoded from the damaged key frame: all four are left out, the others kept.
    assert sorted(set(kept)) == ["cam02", "cam03", "cam04"] and len(kept) == 12
    assert len(outputs.image_filenames) == len(outputs.cameras) == 12
    assert outputs.metadata["frame_ids"].tolist() == [0, 1, 2, 3] * 3
    warnings = [line for line in capsys.readouterr().out.splitlines() if "left out" in line]
    assert [line.split(": frame ")[0] for line in warnings] == [str(video)] * 4
    assert [int(line.split(": frame ")[1].split()[0]) for line in warnings] == [0, 1, 2, 3]


def test_only_the_group_of_pictures_of_a_damaged_frame_is_left_out(tmp_path, capsys):
    """A damaged frame takes the frames decoded from the same key frame with it; the others stay."""
    video = tmp_path / "cam00.mp4"
    with av.open(str(video), mode="w") as container:
        stream = container.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = 32, 24, "yuv420p"
        stream.options = {"g": "3", "keyint_min": "3", "sc_threshold": "0", "bf": "0"}  # key frames 0, 3, 6
        for shade in range(9):
            rgb = np.full((24, 32, 3), 40 * shade, np.uint8)
            rgb[:, : 4 * (shade + 1)] = 255
            for packet in stream.encode(av.VideoFrame.from_ndarray(rgb, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    conceal(video, frame=4)
    assert plain_decode(video) == 9

    paths = cache_video_frames([video], range(9), [(32, 24)], tmp_path / "cache", skip_damaged=True)[0]
    assert [path is not None for path in paths] == [True, True, True, False, False, False, True, True, True]
    warnings = [line for line in capsys.readouterr().out.splitlines() if "left out" in line]
    assert [int(line.split(": frame ")[1].split()[0]) for line in warnings] == [3, 4, 5]
    assert "at frame 4, and frames decoded from the same key frame go with it" in warnings[0]


def png_chunks(data: bytes):
    """(type, offset of the length field, data length) of each chunk of a PNG file."""
    offset, chunks = 8, []
    while offset < len(data):
        length = struct.unpack(">I", data[offset : offset + 4])[0]
        chunks.append((data[offset + 4 : offset + 8], offset, length))
        offset += 12 + length
    return chunks


def damage_png(path: Path, how: str) -> None:
    data = bytearray(path.read_bytes())
    chunks = png_chunks(bytes(data))
    _, offset, length = next(c for c in chunks if c[0] == b"IDAT")
    if how == "end missing":
        del data[chunks[-1][1] :]  # the IEND chunk: every pixel is there, the file ends early
    else:
        data[offset + 8 + length // 4 : offset + 8 + length] = bytes(length - length // 4)
        if how == "data behind a valid checksum":  # broken before the file was written: only decoding finds it
            crc = zlib.crc32(bytes(data[offset + 4 : offset + 8 + length]))
            data[offset + 8 + length : offset + 12 + length] = struct.pack(">I", crc)
    path.write_bytes(data)


@pytest.mark.parametrize("how", ["checksum fails", "data behind a valid checksum", "end missing"])
def test_a_damaged_png_stops_naming_the_file_and_the_frame(how, copy_of, cache_dir):
    dirs = copy_of("technicolor")
    image = dirs["technicolor"] / "Synthetic_undist_00003_05.png"
    damage_png(image, how)
    with Image.open(image) as handle:
        if how == "data behind a valid checksum":  # only a full decode finds it
            handle.verify()
        if how == "end missing":  # only verify finds it
            handle.load()
    with pytest.raises(DatasetError) as info:
        parse("technicolor", dirs, cache_dir)
    message = str(info.value)
    assert message.startswith(f"{image}: frame 3 is damaged: cannot read the image ("), message
    assert "\n" not in message and not list(cache_dir.rglob("*.tmp"))


def test_a_camera_whose_first_png_has_a_damaged_header_stops_naming_the_file_and_the_frame(copy_of, cache_dir):
    dirs = copy_of("technicolor")
    image = dirs["technicolor"] / "Synthetic_undist_00001_05.png"  # the frame the camera's size is read from
    data = bytearray(image.read_bytes())
    data[8:33] = bytes(25)  # the IHDR chunk
    image.write_bytes(data)
    with pytest.raises(DatasetError) as info:
        parse("technicolor", dirs, cache_dir)
    assert str(info.value).startswith(f"{image}: frame 1 is damaged: cannot read the image ("), str(info.value)


def test_a_damaged_png_is_left_out_on_request(copy_of, cache_dir, capsys):
    dirs = copy_of("technicolor")
    image = dirs["technicolor"] / "Synthetic_undist_00003_05.png"
    damage_png(image, "data behind a valid checksum")
    outputs = parse("technicolor", dirs, cache_dir, skip_damaged_frames=True)
    assert image not in outputs.image_filenames
    assert len(outputs.image_filenames) == len(outputs.cameras) == 15 * 4 - 1
    metadata = outputs.metadata
    shown = {
        (metadata["camera_names"][int(c)], metadata["frame_numbers"][int(f)])
        for c, f in zip(metadata["camera_ids"], metadata["frame_ids"])
    }
    assert ("05", 3) not in shown and ("05", 2) in shown and ("04", 3) in shown
    warnings = [line for line in capsys.readouterr().out.splitlines() if "left out" in line]
    assert len(warnings) == 1 and warnings[0].startswith(f"{image}: frame 3 is damaged: cannot read the image")


def test_a_damaged_frame_stops_ns_train_with_one_line(copy_of, tmp_path):
    scene = copy_of("n3d")["n3d"]
    video = scene / "cam02.mp4"
    conceal(video)
    result = command(
        "ns-train", "gear-nerf-small", "--output-dir", str(tmp_path / "runs"), "--machine.device-type", "cpu",
        "--vis", "tensorboard", "--max-num-iterations", "2",
        "neural-3d-video-data", "--data", str(scene), "--cache-dir", str(tmp_path / "cache"),
        cwd=tmp_path,
    )
    output = result.stdout + result.stderr
    assert result.returncode != 0, output[-3000:]
    lines = [line for line in result.stderr.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1 and lines[0].startswith(f"error: {video}: frame 0 is damaged"), output[-3000:]
    assert "Traceback" not in output


@pytest.mark.skipif(
    not (SHARED_REAL / "panoptic_basketball").is_dir() or not (SHARED_REAL / "n3d_flame_steak_frame0").is_dir(),
    reason="shared real data not present",
)
def test_real_captures_have_no_damaged_frames(tmp_path):
    """Every frame of the real captures passes the checks: the PNG capture (16 cameras, 20 frames) and the N3D
    videos (21 cameras)."""
    capture = SHARED_REAL / "panoptic_basketball"
    images = [[capture / f"Basketball_undist_{frame:05d}_{cam:02d}.png" for frame in range(20)] for cam in range(16)]
    checked = cache_image_frames(images, range(20), [(320, 180)] * 16, tmp_path, skip_damaged=True)
    assert checked == images
    videos = sorted((SHARED_REAL / "n3d_flame_steak_frame0").glob("cam*.mp4"))
    sizes = [(info.width, info.height) for info in (video_info(v, tmp_path) for v in videos)]
    decoded = cache_video_frames(videos, [0], sizes, tmp_path, skip_damaged=True)
    assert len(decoded) == 21 and all(paths[0] is not None and paths[0].exists() for paths in decoded)
