"""Shared fixtures: tiny synthetic scenes written in the three on-disk formats."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SHARED_REAL = REPO.parent / "shared" / "data" / "real"

SPECS = {
    "technicolor": SyntheticSpec(dataset="technicolor", width=40, height=30, frames=4, first_frame_number=1),
    "n3d": SyntheticSpec(dataset="n3d", width=40, height=30, frames=4, cameras=5),
    "immersive": SyntheticSpec(dataset="immersive", width=48, height=36, frames=4, cameras=5),
}


@pytest.fixture(scope="session", autouse=True)
def private_cache(tmp_path_factory):
    """Frame and SAM caches of every test (and the commands they start) go to a temporary folder."""
    patch = pytest.MonkeyPatch()
    patch.setenv("XDG_CACHE_HOME", str(tmp_path_factory.mktemp("xdg-cache")))
    yield
    patch.undo()


@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("synthetic")


@pytest.fixture(scope="session")
def scene_dirs(synthetic_root) -> dict:
    """One tiny scene per format, written once per test session."""
    return {name: write_synthetic_scene(synthetic_root / name, spec) for name, spec in SPECS.items()}


@pytest.fixture()
def cache_dir(tmp_path) -> Path:
    return tmp_path / "frame-cache"


IMPORT_WARNING = re.compile(r"Warning: |warnings\.warn\(|^\s+@custom_(fwd|bwd)|^\s*$")
"""Lines of the deprecation warnings that nerfstudio's own modules print when a command imports them, before any
plugin code runs (``gear_nerfstudio.dependency_warnings``)."""


def command(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run a command of the virtual environment, with its bin folder (ffmpeg for videos) on PATH."""
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    return subprocess.run(
        [str(BIN / args[0]), *args[1:]], capture_output=True, text=True, cwd=cwd, timeout=900, env=env
    )


def ns(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """`command`, failing the test with the command's output when it fails."""
    result = command(*args, cwd=cwd)
    assert result.returncode == 0, f"{' '.join(args)} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """A gear-nerf-small run of 20 iterations on a tiny synthetic N3D scene (24 x 18, 3 frames, 5 cameras), with
    epochs of 1 iteration (gear updates at steps 3, 6 and 9), then resumed from its checkpoint for 10 more:
    (root, scene, first run folder, resumed run folder)."""
    root = tmp_path_factory.mktemp("commands")
    scene = write_synthetic_scene(root / "scene", SyntheticSpec(dataset="n3d", width=24, height=18, frames=3, cameras=5))
    common = [
        "--output-dir", str(root / "runs"), "--experiment-name", "tiny", "--machine.device-type", "cpu",
        "--vis", "tensorboard", "--steps-per-save", "10", "--steps-per-eval-all-images", "1000",
        "--pipeline.gear-updates.iterations-per-epoch", "1",
    ]
    data = ["neural-3d-video-data", "--data", str(scene), "--cache-dir", str(root / "cache")]
    ns("ns-train", "gear-nerf-small", *common, "--timestamp", "first", "--max-num-iterations", "20", *data, cwd=root)
    first = root / "runs" / "tiny" / "gear-nerf-small" / "first"
    ns(
        "ns-train", "gear-nerf-small", *common, "--timestamp", "resumed", "--max-num-iterations", "10",
        "--load-dir", str(first / "nerfstudio_models"), *data, cwd=root,
    )
    return root, scene, first, root / "runs" / "tiny" / "gear-nerf-small" / "resumed"
