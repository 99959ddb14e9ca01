"""The real nerfstudio commands on a tiny synthetic scene: ns-train (and resume), ns-eval, ns-render."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from PIL import Image

from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from tests.conftest import ns


@pytest.fixture(scope="module")
def trained(tiny_run):
    return tiny_run


def test_train_writes_config_and_checkpoints_and_resumes(trained):
    _, _, first, resumed = trained
    assert (first / "config.yml").is_file()
    assert (first / "nerfstudio_models" / "step-000000019.ckpt").is_file()
    # Resuming continues after step 19 (10 more iterations end at step 29) instead of starting again.
    assert (resumed / "nerfstudio_models" / "step-000000029.ckpt").is_file()


def test_eval_reports_psnr_and_ssim_on_the_held_out_camera(trained):
    root, _, _, resumed = trained
    out = root / "metrics.json"
    ns("ns-eval", "--load-config", str(resumed / "config.yml"), "--output-path", str(out), cwd=root)
    results = json.loads(out.read_text())["results"]
    assert math.isfinite(results["psnr"]) and 0.0 < results["ssim"] <= 1.0
    assert results["num_rays_per_sec"] > 0


def test_render_camera_path_with_times(trained):
    """A camera path from the viewer's format with render_time per keyframe renders every frame."""
    root, scene, _, resumed = trained
    cameras = Neural3DVideoDataParserConfig(data=scene, cache_dir=root / "cache").setup()
    held_out = cameras.get_dataparser_outputs("test").cameras
    c2w = np.eye(4)
    c2w[:3] = held_out.camera_to_worlds[0].numpy()
    height, width = int(held_out.height[0]), int(held_out.width[0])
    fov = math.degrees(2 * math.atan(height / 2 / float(held_out.fy[0])))
    keyframe = {"camera_to_world": c2w.ravel().tolist(), "fov": fov, "aspect": width / height}
    path = {
        "render_height": height,
        "render_width": width,
        "camera_type": "perspective",
        "seconds": 2,
        "camera_path": [{**keyframe, "render_time": 0.0}, {**keyframe, "render_time": 1.0}],
    }
    (root / "path.json").write_text(json.dumps(path))
    frames = root / "frames"
    ns(
        "ns-render", "camera-path", "--load-config", str(resumed / "config.yml"),
        "--camera-path-filename", str(root / "path.json"), "--output-path", str(frames), "--output-format", "images",
        cwd=root,
    )
    images = sorted(frames.glob("*.jpg")) + sorted(frames.glob("*.png"))
    assert len(images) == 2
    assert all(Image.open(p).size == (width, height) for p in images)


def test_render_spiral_video(trained):
    root, _, _, resumed = trained
    video = root / "spiral.mp4"
    ns(
        "ns-render", "spiral", "--load-config", str(resumed / "config.yml"), "--output-path", str(video),
        "--seconds", "1", "--frame-rate", "4", "--radius", "0.05", cwd=root,
    )
    import av

    with av.open(str(video)) as container:
        assert sum(1 for _ in container.decode(video=0)) == 4
