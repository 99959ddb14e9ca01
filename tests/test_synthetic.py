"""The synthetic scene generator: determinism, its own camera models, ground truth, the command."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from gear_nerfstudio.tools.synthetic.scene import SyntheticScene, scene_objects
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, rig_for
from tests.conftest import SPECS


@pytest.mark.parametrize("name", ["technicolor", "immersive"])
def test_rays_and_projection_are_inverse(name):
    rng = np.random.default_rng(0)
    for camera in rig_for(SPECS[name])[:3]:
        uv = rng.uniform([0, 0], [camera.width, camera.height], size=(200, 2))
        origins, dirs = camera.rays(uv)
        depth = rng.uniform(0.5, 5.0, size=(200, 1))
        back, in_front = camera.project(origins + depth * dirs)
        assert in_front.all()
        np.testing.assert_allclose(back, uv, atol=1e-6)


def test_rendering_is_deterministic_and_objects_move():
    camera = rig_for(SPECS["n3d"])[0]
    first, again = SyntheticScene().render(camera, 2), SyntheticScene().render(camera, 2)
    assert np.array_equal(first.rgb, again.rgb) and np.array_equal(first.object_ids, again.object_ids)
    later = SyntheticScene().render(camera, 3)
    moved = first.object_ids != later.object_ids
    assert moved.any() and not np.isin(first.object_ids[moved], [1]).any()  # the static sphere stays put


def test_speeds_differ_clearly():
    speeds = {obj.name: obj.speed for obj in scene_objects("mixed")}
    assert speeds["static"] == 0.0 and speeds["fast"] > 5 * speeds["slow"] > 0
    assert [obj.name for obj in scene_objects("static")] == ["static"]


def test_ground_truth_files(scene_dirs):
    folder = scene_dirs["n3d"]
    info = json.loads((folder / "ground_truth" / "scene.json").read_text())
    speeds = {obj["id"]: obj["speed_per_frame"] for obj in info["objects"]}
    truth = np.load(folder / "ground_truth" / "cam00.npz")
    spec = SPECS["n3d"]
    assert truth["object_ids"].shape == (spec.frames, spec.height, spec.width)
    assert set(np.unique(truth["object_ids"])) == {0, 1, 2, 3}
    for object_id, speed in speeds.items():
        np.testing.assert_allclose(truth["motion"][truth["object_ids"] == object_id], speed, rtol=1e-6)
    assert (truth["motion"][truth["object_ids"] == 0] == 0).all()


def test_command_writes_all_formats(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "gear_nerfstudio.tools.synthetic.cli", "--output", str(tmp_path / "scenes"),
         "--width", "16", "--height", "12", "--frames", "2", "--cameras", "3", "--rows", "1", "--cols", "3"],
        capture_output=True, text=True, check=True,
    )
    assert "wrote immersive" in result.stdout
    assert (tmp_path / "scenes" / "technicolor" / "cameras_parameters.txt").is_file()
    assert (tmp_path / "scenes" / "n3d" / "poses_bounds.npy").is_file()
    assert json.loads((tmp_path / "scenes" / "immersive" / "models.json").read_text())[0]["name"] == "camera_0001"
    assert len(list((tmp_path / "scenes" / "technicolor").glob("*_undist_*.png"))) == 6


def test_odd_sizes_are_refused():
    with pytest.raises(ValueError, match="even"):
        rig_for(SyntheticSpec(dataset="n3d", width=41))
