"""Real multi-view video through the real commands: the CMU Panoptic dome capture in the Technicolor layout
(../shared/data/real/panoptic_basketball) and in the Neural 3D Video layout (panoptic_basketball_video; SOURCES.md),
trained briefly with ns-train, gear updates and their guard included."""

from __future__ import annotations

import json
import re

import pytest

from tests.conftest import SHARED_REAL, ns

pytestmark = pytest.mark.cost(250)

CAPTURE = SHARED_REAL / "panoptic_basketball"
VIDEO = SHARED_REAL / "panoptic_basketball_video"


@pytest.mark.skipif(not CAPTURE.is_dir(), reason="shared real data not present")
def test_ns_train_runs_gear_updates_on_real_video(tmp_path):
    """40 iterations on 6 frames of 15 cameras at 80x45 with epochs of 2 iterations: updates at steps 6, 12 and
    18. The motion gate passes the people (real sensor noise does not stop it: the upshift masks are not empty). The
    guard reviews each update when the next is due and logs its verdict; after an update it undoes, none runs.
    (ns-eval on real video: the next test.)"""
    result = ns(
        "ns-train", "gear-nerf-small", "--output-dir", str(tmp_path / "runs"), "--experiment-name", "real",
        "--timestamp", "run", "--max-num-iterations", "40", "--machine.device-type", "cpu", "--vis", "tensorboard",
        "--steps-per-eval-all-images", "100000", "--pipeline.gear-updates.iterations-per-epoch", "2",
        "--pipeline.gear-updates.max-steps", "10",  # the Eq 11 steps' fit is not what is checked
        "--pipeline.datamanager.sam-cache-dir", str(tmp_path / "sam"),
        "technicolor-data", "--data", str(CAPTURE), "--near", "0.3", "--far", "7", "--frame-count", "6",
        "--downscale-factor", "4", "--held-out-camera", "06", "--cache-dir", str(tmp_path / "frames"), cwd=tmp_path,
    )  # fmt: skip
    log = " ".join(re.sub(r"\S+\.py:\d+", " ", result.stdout).split())  # rich's log lines, unwrapped
    assert "planned at steps 6, 12, 18" in log and "Upshift masks from the RGB loss threshold." in log  # the stand-in's
    areas = [float(a) for a in re.findall(r"Gear update \d at step \d+: loss-map variance \S+ upshift area ([\d.]+)", log)]
    reviews = re.findall(r"Gear update (\d) reviewed at step (\d+): its views [\d.]+ -> [\d.]+ dB, held-out view "
                         r"[\d.]+ -> [\d.]+ dB(: kept|; more than 0.1 dB worse: undone)", log)  # fmt: skip
    assert [(int(u), int(s)) for u, s, _ in reviews] == [(k, 6 * k + 6) for k in range(1, len(areas) + 1)], log[-3000:]
    undone = [verdict.endswith("undone") for _, _, verdict in reviews]
    assert len(areas) == (undone.index(True) + 1 if any(undone) else 3) and max(areas) > 0, log[-3000:]


@pytest.mark.skipif(not VIDEO.is_dir(), reason="shared real data not present")
@pytest.mark.parametrize("seed", [42, 43])
def test_the_held_out_camera_on_the_dome_wall_sees_the_scene_not_a_layer_in_front_of_itself(tmp_path, seed):
    """Each camera of the dome sits on the wall that the others see, and no training ray crosses the space just in
    front of the held-out camera. Rendered from its centre (nerfstudio resets the near plane outside training), its
    view began inside the wall and was dark and opaque; from its near plane it sees the room (300 iterations of 512
    rays on 4 frames of the 31-camera capture at 152x84, at two seeds: a layer can form at one seed and not another;
    24.2 and 24.1 dB, no near layer, on 2026-12-07)."""
    ns(
        "ns-train", "gear-nerf-baseline", "--output-dir", str(tmp_path / "runs"), "--experiment-name", "dome",
        "--timestamp", "run", "--max-num-iterations", "300", "--machine.device-type", "cpu", "--vis", "tensorboard",
        "--machine.seed", str(seed), "--pipeline.datamanager.train-num-rays-per-batch", "512",
        "--steps-per-eval-all-images", "100000", "--pipeline.datamanager.use-sam-features", "False",
        "--pipeline.gear-updates.sam-loss-weight", "0", "--pipeline.gear-updates.iterations-per-epoch", "15",
        "neural-3d-video-data", "--data", str(VIDEO), "--downscale-factor", "4", "--frame-count", "4",
        "--cache-dir", str(tmp_path / "frames"), cwd=tmp_path,
    )  # fmt: skip
    metrics = tmp_path / "metrics.json"
    config = tmp_path / "runs" / "dome" / "gear-nerf-baseline" / "run" / "config.yml"
    ns("ns-eval", "--load-config", str(config), "--output-path", str(metrics), cwd=tmp_path)
    results = json.loads(metrics.read_text())["results"]
    assert results["near_layer"] < 0.05 and results["psnr"] > 18 and 0 < results["accumulation"] <= 1, results
