"""The real nerfstudio commands on a tiny synthetic scene: ns-train (and resume), ns-eval, ns-render."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image

from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene
from tests.conftest import IMPORT_WARNING, command, ns

pytestmark = pytest.mark.cost(200)


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
    # the spheres move, so the held-out view's colour changes: scores inside and outside that region, and gear shares
    assert all(math.isfinite(results[key]) for key in ("psnr_moving", "psnr_static"))
    assert all(0.0 <= results[key] <= 1.0 for key in ("moving_at_gear_2", "static_at_gear_1"))


def edited_config(config_path: Path, target: Path, edit) -> Path:
    """A copy of a run's config.yml (same checkpoints) with `edit` applied to the loaded config."""
    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    edit(config)
    target.write_text(yaml.dump(config))
    return target


def test_eval_of_a_single_held_out_image_writes_no_nan(trained):
    """With one held-out image (a one-frame window of the same run) ns-eval leaves the spread out instead of NaN."""
    root, _, _, resumed = trained

    def one_frame(config):
        config.pipeline.model.num_frames = 3
        config.pipeline.datamanager.dataparser.frame_count = 1

    config = edited_config(resumed / "config.yml", root / "one-frame.yml", one_frame)
    out = root / "one-frame.json"
    ns("ns-eval", "--load-config", str(config), "--output-path", str(out), cwd=root)
    results = json.loads(out.read_text())["results"]
    assert math.isfinite(results["psnr"]) and not any(key.endswith("_std") for key in results), results
    assert "NaN" not in out.read_text()
    # one frame without masks: nothing can be seen to move, so the moving region's scores are missing, not zero
    assert "psnr_moving" not in results and "moving_at_gear_2" not in results and math.isfinite(results["psnr_static"])


def test_eval_with_missing_data_stops_in_one_line(trained):
    root, _, _, resumed = trained

    def moved(config):
        config.pipeline.datamanager.dataparser.data = root / "moved-away"

    config = edited_config(resumed / "config.yml", root / "moved.yml", moved)
    result = command("ns-eval", "--load-config", str(config), "--output-path", str(root / "moved.json"), cwd=root)
    assert result.returncode == 1
    errors = [line for line in result.stderr.splitlines() if not IMPORT_WARNING.search(line)]
    assert errors == [f"error: {root / 'moved-away'}: the scene folder does not exist"], result.stderr
    assert not (root / "moved.json").exists()


@pytest.fixture(scope="module")
def moving_run(tmp_path_factory):
    """gear-nerf-small trained for 200 iterations of 256 rays (gear updates at steps 30, 60, 90) on a 32x24, 4-frame
    N3D scene: enough for its renders to show the spheres moving. (root, scene, config.yml)"""
    root = tmp_path_factory.mktemp("moving")
    scene = write_synthetic_scene(root / "scene", SyntheticSpec(dataset="n3d", width=32, height=24, frames=4, cameras=5))
    ns(
        "ns-train", "gear-nerf-small", "--output-dir", str(root / "runs"), "--timestamp", "run",
        "--max-num-iterations", "200", "--pipeline.gear-updates.iterations-per-epoch", "10",
        "--pipeline.datamanager.train-num-rays-per-batch", "256",
        "--machine.device-type", "cpu", "--vis", "tensorboard", "--steps-per-eval-all-images", "100000",
        "neural-3d-video-data", "--data", str(scene), "--cache-dir", str(root / "cache"), cwd=root,
    )
    return root, scene, root / "runs" / "scene" / "gear-nerf-small" / "run" / "config.yml"


def rendered_frames(folder: Path) -> np.ndarray:
    return np.stack([np.asarray(Image.open(p), dtype=np.float32) / 255 for p in sorted(folder.glob("*.jpg"))])


@pytest.fixture(scope="module")
def time_sweep(moving_run):
    """ns-gear-path time-sweep of the held-out camera, rendered by ns-render camera-path: (path, rendered frames)."""
    root, _, config = moving_run
    path = root / "sweep.json"
    result = ns("ns-gear-path", "time-sweep", "--load-config", str(config), "--output-path", str(path), cwd=root)
    assert "Warning" not in result.stderr, result.stderr  # the plugin loads first: nerfstudio's warnings filtered
    ns(
        "ns-render", "camera-path", "--load-config", str(config), "--camera-path-filename", str(path),
        "--output-path", str(root / "sweep"), "--output-format", "images", cwd=root,
    )
    return path, rendered_frames(root / "sweep")


def test_time_sweep_path_renders_the_video_from_a_fixed_view(moving_run, time_sweep):
    """ns-gear-path time-sweep writes the held-out camera at each frame's time; ns-render camera-path renders it, and
    the frames change where the spheres move (ground truth) and hardly elsewhere."""
    root, scene, _ = moving_run
    path, images = time_sweep
    frames = json.loads(path.read_text())["camera_path"]
    held_out = Neural3DVideoDataParserConfig(data=scene, cache_dir=root / "cache").setup()
    pose = held_out.get_dataparser_outputs("test").cameras.camera_to_worlds[0].numpy()
    assert [frame["render_time"] for frame in frames] == pytest.approx([0, 1 / 3, 2 / 3, 1])
    for frame in frames:
        np.testing.assert_allclose(np.reshape(frame["camera_to_world"], (4, 4))[:3], pose, atol=1e-6)
    assert images.shape == (4, 24, 32, 3)
    motion = np.load(scene / "ground_truth" / "cam00.npz")["motion"]
    moving = (motion[0] > 0) | (motion[-1] > 0)
    change = np.abs(images[-1] - images[0]).mean(axis=-1)
    assert change[moving].mean() > 3 * change[~moving].mean(), (change[moving].mean(), change[~moving].mean())


def test_spiral_starts_upright_at_its_source_camera(moving_run, time_sweep):
    """ns-render spiral's first frame (time 0, a small step from the held-out camera) looks like the held-out camera's
    render at time 0 (the time sweep's first frame), not like it turned upside down (nerfstudio's spiral assumes the
    camera looks along -y)."""
    root, _, config = moving_run
    ns(
        "ns-render", "spiral", "--load-config", str(config), "--output-path", str(root / "spiral"),
        "--output-format", "images", "--seconds", "1", "--frame-rate", "4", "--radius", "0.01", cwd=root,
    )
    source, spiral = time_sweep[1][0], rendered_frames(root / "spiral")[0]
    upright = np.abs(spiral - source).mean()
    assert upright < 0.5 * np.abs(spiral - source[::-1, ::-1]).mean(), upright


def test_interpolate_warns_that_it_renders_time_zero(moving_run):
    """ns-render interpolate drops the cameras' times: the model says so and names the command that keeps them."""
    root, _, config = moving_run
    result = ns(
        "ns-render", "interpolate", "--load-config", str(config), "--output-path", str(root / "interpolated"),
        "--output-format", "images", "--frame-rate", "2", "--interpolation-steps", "1", cwd=root,
    )
    assert "without a time is rendered at time 0" in result.stdout + result.stderr
