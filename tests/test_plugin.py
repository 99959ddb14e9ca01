"""The installed plugin: entry points seen by nerfstudio, namespaced packages, cheap imports."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import command

pytestmark = pytest.mark.cost(35)

BIN = Path(sys.executable).parent
PARSERS = ["technicolor-data", "neural-3d-video-data", "google-immersive-data"]


def run(args, cwd):
    return subprocess.run(args, capture_output=True, text=True, cwd=cwd, timeout=300)


def test_ns_train_lists_the_method_and_the_parsers(tmp_path):
    """The installed script itself, then its entry point (the same code, without another 22 s of imports)."""
    listing = run([str(BIN / "ns-train"), "--help"], tmp_path)
    assert listing.returncode == 0, listing.stderr
    assert "gear-nerf" in listing.stdout and "nerfacto" in listing.stdout  # other methods still work
    method = command("ns-train", "gear-nerf", "--help", cwd=tmp_path)
    assert method.returncode == 0, method.stderr
    for parser in PARSERS:
        assert parser in method.stdout


def test_packages_are_namespaced_and_imports_stay_light(tmp_path):
    """No generic top-level modules; video decoding and ONNX load only when used (cv2 comes with nerfstudio)."""
    code = (
        "import importlib.util, sys\n"
        "import gear_nerfstudio.data_parsers, gear_nerfstudio.method_configs\n"
        "print(importlib.util.find_spec('data_parsers') is None, importlib.util.find_spec('method_configs') is None)\n"
        "print(sorted(m for m in ('av', 'onnxruntime') if m in sys.modules))\n"
    )
    result = run([sys.executable, "-c", code], tmp_path)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split("\n")[:2] == ["True True", "[]"]
