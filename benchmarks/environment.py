"""Where the benchmarks find the virtual environment's commands (ns-train, ns-gear-track, ffmpeg)."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Dict

BIN = Path(sys.executable).parent
"""The bin folder of the Python running the benchmark, i.e. of the project's virtual environment."""


def command_environment() -> Dict[str, str]:
    """os.environ with ``BIN`` first on PATH, so child commands and the commands they start are the venv's."""
    return {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
