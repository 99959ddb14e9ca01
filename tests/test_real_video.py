"""Real multi-view video through the real commands: the CMU Panoptic dome capture in the Technicolor layout
(../shared/data/real/panoptic_basketball, SOURCES.md), trained briefly with ns-train, gear updates included."""

from __future__ import annotations

import json
import math
import re

import pytest

from tests.conftest import SHARED_REAL, ns

CAPTURE = SHARED_REAL / "panoptic_basketball"


@pytest.mark.skipif(not CAPTURE.is_dir(), reason="shared real data not present")
def test_ns_train_runs_gear_updates_on_real_video_and_ns_eval_scores_it(tmp_path):
    """40 iterations on 6 frames of 15 cameras with epochs of 2 iterations: updates at steps 6, 12 and 18. The
    motion gate passes the people (real sensor noise does not stop it: the upshift masks are not empty)."""
    result = ns(
        "ns-train", "gear-nerf-small", "--output-dir", str(tmp_path / "runs"), "--experiment-name", "real",
        "--timestamp", "run", "--max-num-iterations", "40", "--machine.device-type", "cpu", "--vis", "tensorboard",
        "--steps-per-eval-all-images", "100000", "--pipeline.gear-updates.iterations-per-epoch", "2",
        "--pipeline.datamanager.sam-cache-dir", str(tmp_path / "sam"),
        "technicolor-data", "--data", str(CAPTURE), "--near", "0.3", "--far", "7", "--frame-count", "6",
        "--held-out-camera", "06", "--cache-dir", str(tmp_path / "frames"), cwd=tmp_path,
    )  # fmt: skip
    log = " ".join(re.sub(r"\S+\.py:\d+", " ", result.stdout).split())  # rich's log lines, unwrapped
    assert "planned at steps 6, 12, 18" in log
    areas = [float(a) for a in re.findall(r"Gear update \d at step \d+: loss-map variance \S+ upshift area ([\d.]+)", log)]
    assert len(areas) == 3 and max(areas) > 0, log[-3000:]
    metrics = tmp_path / "metrics.json"
    config = tmp_path / "runs" / "real" / "gear-nerf-small" / "run" / "config.yml"
    ns("ns-eval", "--load-config", str(config), "--output-path", str(metrics), cwd=tmp_path)
    assert math.isfinite(json.loads(metrics.read_text())["results"]["psnr"])
