"""Shared fixtures: tiny synthetic scenes written in the three on-disk formats."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Dict, List, Optional

import pytest
from filelock import FileLock

from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
SHARED_REAL = REPO.parent / "shared" / "data" / "real"

SPECS = {
    "technicolor": SyntheticSpec(dataset="technicolor", width=40, height=30, frames=4, first_frame_number=1),
    "n3d": SyntheticSpec(dataset="n3d", width=40, height=30, frames=4, cameras=5),
    "immersive": SyntheticSpec(dataset="immersive", width=48, height=36, frames=4, cameras=5),
}


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "cost(seconds): about how long a module takes in the suite (its --durations; tiny_run counts in "
        "test_commands, which starts before the other modules that use it)",
    )


def pytest_collection_modifyitems(items):
    """Modules by their ``cost`` mark, costliest first (unmarked ones last, as collected): with each module on one of
    one process per core (scripts/test.sh), the long modules then start at once instead of ending the run alone."""
    items.sort(key=lambda item: -(item.get_closest_marker("cost") or pytest.mark.cost(0)).args[0])


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


class CommandServer:
    """This test process's ``tests/command_server.py``, started at its first command."""

    process: Optional[subprocess.Popen] = None

    @classmethod
    def run(cls, argv: List[str], cwd: Path, env: Dict[str, str], timeout: float) -> subprocess.CompletedProcess:
        if cls.process is None or cls.process.poll() is not None:
            cls.process = subprocess.Popen(
                [sys.executable, "-m", "tests.command_server"], cwd=REPO, env=env, text=True,
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
            )  # fmt: skip
        assert cls.process.stdin is not None and cls.process.stdout is not None
        with tempfile.TemporaryDirectory() as folder:
            out, err = Path(folder) / "stdout", Path(folder) / "stderr"
            request = {"argv": argv, "cwd": str(cwd), "env": env, "stdout": str(out), "stderr": str(err),
                       "timeout": timeout}  # fmt: skip
            print(json.dumps(request), file=cls.process.stdin, flush=True)
            line = cls.process.stdout.readline()
            assert line, "tests/command_server.py ended"
            reply = json.loads(line)
            if reply["timed_out"]:
                raise TimeoutError(f"{' '.join(argv)} took more than {timeout} s")
            return subprocess.CompletedProcess(argv, reply["returncode"], out.read_text(), err.read_text())


def command(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """Run a command of the virtual environment, with its bin folder (ffmpeg for videos) on PATH: the console
    script's entry point in a process of its own, forked from ``tests/command_server.py`` (the same code as the
    installed script, without its 22 s of imports; ``test_plugin.py`` runs the installed scripts themselves)."""
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    return CommandServer.run([str(BIN / args[0]), *args[1:]], cwd, env, timeout=900)


def ns(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """`command`, failing the test with the command's output when it fails."""
    result = command(*args, cwd=cwd)
    assert result.returncode == 0, f"{' '.join(args)} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory, worker_id):
    """A gear-nerf-small run of 20 iterations on a tiny synthetic N3D scene (24 x 18, 3 frames, 5 cameras), with
    epochs of 1 iteration (gear updates at steps 3, 6 and 9), then resumed from its checkpoint for 10 more:
    (root, scene, first run folder, resumed run folder). Trained once for all the test processes (the modules that
    use it may run on several), in their common temporary folder, where the tests write files of their own names."""
    if worker_id == "master":
        root = tmp_path_factory.mktemp("commands")
        train_tiny_run(root)
    else:
        root = tmp_path_factory.getbasetemp().parent / "commands"
        with FileLock(f"{root}.lock"):
            if not (root / "trained").exists():
                shutil.rmtree(root, ignore_errors=True)
                train_tiny_run(root)
                (root / "trained").touch()
    return run_folders(root)


def run_folders(root: Path) -> tuple:
    """``tiny_run``'s (root, scene, first run folder, resumed run folder) under ``root``."""
    runs = root / "runs" / "tiny" / "gear-nerf-small"
    return root, root / "scene", runs / "first", runs / "resumed"


def train_tiny_run(root: Path) -> None:
    """Train ``tiny_run``'s two runs under ``root``."""
    scene = write_synthetic_scene(root / "scene", SyntheticSpec(dataset="n3d", width=24, height=18, frames=3, cameras=5))
    common = [
        "--output-dir", str(root / "runs"), "--experiment-name", "tiny", "--machine.device-type", "cpu",
        "--vis", "tensorboard", "--steps-per-save", "10", "--steps-per-eval-all-images", "1000",
        "--pipeline.gear-updates.iterations-per-epoch", "1", "--pipeline.datamanager.sam-cache-dir", str(root / "sam"),
        "--pipeline.gear-updates.max-steps", "10",  # the Eq 11 steps' fit is not what is checked
    ]
    data = ["neural-3d-video-data", "--data", str(scene), "--cache-dir", str(root / "cache")]
    ns("ns-train", "gear-nerf-small", *common, "--timestamp", "first", "--max-num-iterations", "20", *data, cwd=root)
    _, _, first, _ = run_folders(root)
    ns(
        "ns-train", "gear-nerf-small", *common, "--timestamp", "resumed", "--max-num-iterations", "10",
        "--load-dir", str(first / "nerfstudio_models"), *data, cwd=root,
    )
