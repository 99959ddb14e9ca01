"""How close ns-gear-process's calibration comes to a capture's own: the videos alone are processed and the recovered
cameras compared after a similarity alignment (``gear_nerfstudio.process.accuracy.pose_errors``), beside the cameras
the self-check named as doubtful; the table goes between the ``<!-- run -->`` markers of ``process_accuracy.md``."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Dict, Sequence, Tuple

import numpy as np

from benchmarks.common import BIN, REAL, REPO, fill_page, machine_description, provenance, table

CAPTURES = ("panoptic_basketball_video", "n3d_flame_steak_frame0")


def run_capture(folder: Path, work: Path) -> Tuple[Dict[str, np.ndarray], float, Path]:
    """Copy the videos only, run ns-gear-process, compare; (errors, seconds, output folder)."""
    from gear_nerfstudio.process.accuracy import pose_errors

    videos = sorted(folder.glob("cam*.mp4"))
    stripped = work / f"{folder.name}-videos"
    stripped.mkdir()
    for video in videos:
        shutil.copy(video, stripped / video.name)
    output = work / f"{folder.name}-processed"
    start = time.perf_counter()
    subprocess.run([str(BIN / "ns-gear-process"), "--data", str(stripped), "--output-dir", str(output)], check=True)
    seconds = time.perf_counter() - start
    truth = np.load(folder / "poses_bounds.npy")[: len(videos)]
    return pose_errors(np.load(output / "poses_bounds.npy"), truth), seconds, output


def names(cameras: Sequence[int]) -> str:
    return ", ".join(f"cam{i:02d}" for i in cameras) or "none"


@dataclasses.dataclass
class ProcessAccuracy:
    """Process each capture's videos and compare the cameras with its own calibration."""

    captures: Tuple[str, ...] = CAPTURES
    output: Path = REPO / "benchmarks" / "results" / "process_accuracy.md"

    def main(self) -> None:
        import pycolmap

        rows = []
        with tempfile.TemporaryDirectory() as work:
            for key in self.captures:
                errors, seconds, output = run_capture(REAL / key, Path(work))
                c, r = errors["centre_pct"], errors["rotation_deg"]
                frames = json.loads((output / "transforms.json").read_text())["frames"]
                doubtful = [i for i, frame in enumerate(frames) if frame["self_check"]["doubtful"]]
                missed = [i for i in np.flatnonzero((c > 2) | (r > 1)) if i not in doubtful]
                rows.append([key, len(c), *(f"{f(x):.2f}" for x in (c, r) for f in (np.mean, np.median, np.max)),
                             f"{int(((c <= 2) & (r <= 1)).sum())} / {len(c)}", names(doubtful), names(missed),
                             f"{seconds:.0f} s"])  # fmt: skip
        header = ["capture", "cameras", "centre % mean", "median", "max", "rotation deg mean", "median", "max",
                  "cameras within both", "named doubtful", "outside both, not named", "time"]  # fmt: skip
        machine = f"{machine_description()}; pycolmap {pycolmap.__version__}"
        run = [*table(header, rows), "", *provenance(machine)]
        fill_page(self.output, {"run": "\n".join(run)})
        print("\n".join(run))
