"""Shared fixtures: tiny synthetic scenes written in the three on-disk formats."""

from __future__ import annotations

from pathlib import Path

import pytest

from gear_nerfstudio.synthetic.writers import SyntheticSpec, write_synthetic_scene

REPO = Path(__file__).resolve().parents[1]
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
