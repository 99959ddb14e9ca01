"""ns-gear-chunks with the Ray executor gives the local executor's checkpoints (a module of its own, so that the
test runs beside test_chunks.py's)."""

from __future__ import annotations

import pytest
import torch

from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene
from tests.conftest import ns
from tests.test_chunks import train_args

pytestmark = pytest.mark.cost(200)


def test_ray_executor_gives_the_local_executors_checkpoints(tmp_path):
    pytest.importorskip("ray")
    scene = write_synthetic_scene(tmp_path / "scene", SyntheticSpec(dataset="n3d", width=24, height=18, frames=6, cameras=4))
    args = train_args(scene, tmp_path / "cache", 20)
    states = {}
    for executor in ("local", "ray"):
        out = tmp_path / executor
        ns("ns-gear-chunks", "train", "--output-dir", str(out), "--chunk-frames", "3", "--executor", executor, "--",
           *args, cwd=tmp_path)
        states[executor] = [
            torch.load(out / f"chunk_{k:03d}" / "gear-nerf-small" / "run" / "nerfstudio_models" / "step-000000019.ckpt",
                       map_location="cpu", weights_only=False)["pipeline"]
            for k in range(2)
        ]
    for local, ray in zip(states["local"], states["ray"]):
        assert set(local) == set(ray)
        for key in local:
            assert torch.equal(local[key], ray[key]), key
    # the two chunks model different frames: their radiance fields differ
    assert not torch.equal(states["local"][0]["_model.field.basis.weight"], states["local"][1]["_model.field.basis.weight"])
