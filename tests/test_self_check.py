"""The self-check of `ns-gear-process` through the real command, on real footage: 8 cameras of N3D's flame_steak
(../shared/data/real/n3d_flame_steak_frame0) as folders of frames, one of them knocked between instants. Its own
module, so that the test processes run it beside `test_process.py`."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.conftest import command, ns
from tests.test_process import CAMERAS, FLAME, decode, expect_one_line_error, process

pytestmark = [pytest.mark.cost(170), pytest.mark.skipif(not FLAME.is_dir(), reason="shared real data not present")]


BUMPED_OPTIONS = ("--calibration-frames", "0", "6")


@pytest.fixture(scope="module")
def bumped(tmp_path_factory):
    """Folders of 7 frames of 8 N3D cameras, where cam03 shows cam11's view at every instant but the calibration
    frames 0 and 6 (a camera knocked between them); and the scene ns-gear-process makes of them."""
    from PIL import Image

    root = tmp_path_factory.mktemp("bumped")
    frames = root / "frames"
    views = {name: decode(FLAME / f"{name}.mp4")[0] for name in (*CAMERAS[:8], "cam11")}
    for name in CAMERAS[:8]:
        (frames / name).mkdir(parents=True)
        for instant in range(7):
            view = views["cam11" if name == "cam03" and instant not in (0, 6) else name]
            Image.fromarray(view).save(frames / name / f"{instant:03d}.png")
    output = root / "scene"
    result = ns("ns-gear-process", "--data", str(frames), "--output-dir", str(output), *BUMPED_OPTIONS, cwd=root)
    return frames, output, result


def test_the_self_check_names_a_camera_that_moved_between_instants(bumped):
    """Both checks (frames 1 and 4, 2 and 5) see cam03 elsewhere: one line names it with the evidence,
    transforms.json marks it, and only it, as doubtful."""
    frames, output, result = bumped
    lines = [line for line in result.stdout.splitlines() if line.startswith("Doubtful camera")]
    assert len(lines) == 1 and lines[0].startswith("Doubtful camera cam03: "), result.stdout
    assert "check 1: " in lines[0] and "check 2: " in lines[0] and "cam03 in the scene" in lines[0], lines
    summary = json.loads((output / "transforms.json").read_text())
    assert summary["self_check_frames"] == [[1, 4], [2, 5]]
    doubtful = [frame["source"] for frame in summary["frames"] if frame["self_check"]["doubtful"]]
    assert doubtful == ["cam03"], summary["frames"]
    for frame in summary["frames"]:
        assert len(frame["self_check"]["checks"]) == 2


def test_doubtful_cameras_left_out_or_an_error(bumped, tmp_path):
    frames, _, _ = bumped
    result = process(frames, tmp_path / "scene", *BUMPED_OPTIONS, "--doubtful-cameras", "error")
    expect_one_line_error(result, str(frames), "doubtful cameras: cam03 (check 1: ")
    output = tmp_path / "left_out"
    result = command("ns-gear-process", "--data", str(frames), "--output-dir", str(output), *BUMPED_OPTIONS,
                     "--doubtful-cameras", "leave-out", cwd=tmp_path)  # fmt: skip
    assert "Doubtful camera cam03: " in result.stdout and "left out of the scene" in result.stdout, result.stdout
    summary = json.loads((output / "transforms.json").read_text())
    assert [frame["source"] for frame in summary["frames"]] == [n for n in CAMERAS[:8] if n != "cam03"]
    assert np.load(output / "poses_bounds.npy").shape == (7, 17)
