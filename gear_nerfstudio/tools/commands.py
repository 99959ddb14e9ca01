"""Running this environment's commands (ns-train, ns-eval, ns-render, ...) from the plugin's own tools."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Dict, List, Optional

from gear_nerfstudio.dependency_warnings import pythonwarnings


def run_command(command: List[str], prefix: str, env: Optional[Dict[str, str]] = None) -> None:
    """Run a command of this environment, with its bin folder (ns-*, ffmpeg) first on PATH and without
    nerfstudio's import-time deprecation warnings; ``env`` adds variables. Raises CalledProcessError."""
    bin_dir = Path(sys.executable).parent
    print(f"[{prefix}] $ {' '.join(command)}", flush=True)
    warning_filters = [os.environ.get("PYTHONWARNINGS", ""), pythonwarnings()]
    full_env = {
        **os.environ,
        **(env or {}),
        "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}",
        "PYTHONWARNINGS": ",".join(filter(None, warning_filters)),
    }
    subprocess.run([str(bin_dir / command[0]), *command[1:]], check=True, env=full_env)
