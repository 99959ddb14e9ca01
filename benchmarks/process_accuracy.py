"""How close ns-gear-process's calibration comes to a capture's own: the videos alone are processed and the recovered
cameras compared after a similarity alignment (``gear_nerfstudio.process.accuracy.pose_errors``): centre error in %
of the rig's size, rotation error in degrees, per camera, beside the cameras the self-check named as doubtful. Writes
``benchmarks/results/process_accuracy.md`` and each capture's rig plot."""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import shutil
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Dict, Sequence, Tuple

import numpy as np

from benchmarks.common import BIN, REAL, REPO
from gear_nerfstudio.process.accuracy import pose_errors

CAPTURES = {
    "panoptic_basketball_video": ("panoptic_basketball_video", ()),
    "n3d_flame_steak_frame0": ("n3d_flame_steak_frame0", ()),
}


def run_capture(folder: Path, extra: Sequence[str], work: Path, cameras: int) -> Tuple[Dict[str, np.ndarray], float, Path]:
    """Copy the videos only, run ns-gear-process, compare; (errors, seconds, output folder)."""
    videos = sorted(folder.glob("cam*.mp4"))[:cameras]
    stripped = work / f"{folder.name}-videos"
    stripped.mkdir()
    for video in videos:
        shutil.copy(video, stripped / video.name)
    output = work / f"{folder.name}-processed"
    start = time.perf_counter()
    command = [str(BIN / "ns-gear-process"), "--data", str(stripped), "--output-dir", str(output), *extra]
    subprocess.run(command, check=True)
    seconds = time.perf_counter() - start
    truth = np.load(folder / "poses_bounds.npy")[: len(videos)]
    return pose_errors(np.load(output / "poses_bounds.npy"), truth), seconds, output


@dataclasses.dataclass
class ProcessAccuracy:
    """Process each capture's videos and compare the cameras with its own calibration."""

    captures: Tuple[str, ...] = tuple(CAPTURES)
    cameras: int = 100
    """Use the first N cameras of each capture."""
    output: Path = REPO / "benchmarks" / "results" / "process_accuracy.md"

    def main(self) -> None:
        rows, details = [], []
        with tempfile.TemporaryDirectory() as work:
            for key in self.captures:
                name, extra = CAPTURES[key]
                errors, seconds, output = run_capture(REAL / name, extra, Path(work), self.cameras)
                picture = self.output.with_name(f"process_accuracy_{key}.png")
                shutil.copy(output / "rig.png", picture)
                c, r = errors["centre_pct"], errors["rotation_deg"]
                good = int(((c <= 2) & (r <= 1)).sum())
                frames = json.loads((output / "transforms.json").read_text())["frames"]
                doubtful = [i for i, frame in enumerate(frames) if frame["self_check"]["doubtful"]]
                missed = [i for i in np.flatnonzero((c > 2) | (r > 1)) if i not in doubtful]
                rows.append(
                    f"| {key} | {len(c)} | {c.mean():.2f} | {np.median(c):.2f} | {c.max():.2f} | {r.mean():.2f} | "
                    f"{np.median(r):.2f} | {r.max():.2f} | {good} / {len(c)} | {_names(doubtful)} | {_names(missed)} | {seconds:.0f} s | "
                    f"{' '.join(extra) or 'defaults (instants: first, middle, last frame)'} |"
                )
                details.append(
                    f"- {key}: per camera (cam00, cam01, ...), centre % "
                    + ", ".join(f"{x:.2f}" for x in c)
                    + "; rotation deg "
                    + ", ".join(f"{x:.2f}" for x in r)
                    + f". Rig: ![{key}]({picture.name})"
                )
        command = "OMP_NUM_THREADS=1 .venv/bin/python -m benchmarks process-accuracy " + " ".join(
            ["--captures", *self.captures] + (["--cameras", str(self.cameras)] if self.cameras != 100 else [])
        )
        text = "\n".join(
            [
                "# ns-gear-process: recovered cameras against the captures' own calibration",
                "",
                "Calibration stripped (the videos only), `ns-gear-process` run on them, its `poses_bounds.npy` compared with",
                "the capture's after a similarity alignment (Umeyama, on each camera's centre and two points one rig radius",
                "along its viewing and down axes; `gear_nerfstudio/process/accuracy.py`). Centre error in % of the rig's",
                "size (diagonal of the box of the true centres); rotation error in degrees. Target: 2 % and 1 degree.",
                "Times are wall-clock on a machine shared with other runs; they include the self-check's two calibrations.",
                "",
                "| capture | cameras | centre % mean | median | max | rotation deg mean | median | max | cameras within both | "
                "named doubtful | outside both, not named | time | options |",
                "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
                *rows,
                "",
                *details,
                "",
                "Notes (measured while this script was written, not re-run by it): on the Panoptic capture, one",
                "calibration instant is not enough (one run registered 2 of 31 cameras, another registered all 31 with",
                "one or more turned by 70-170 degrees), nor are 12-15 of its cameras with two instants (cameras 20-30 degrees",
                "apart at 608x336: some are not registered or registered upside down); `--calibration-frames 15 60`",
                "registered cam24 and cam25 turned by 144 degrees, and `0 30 60` cam25 by 70 degrees (twice); `0 45 89`",
                "(the start, middle and end of the video: the default) put all 31 within both targets in 5 runs of 5,",
                "`0 45` in 1 of 2.",
                "COLMAP runs multi-threaded, so repeated runs differ slightly. The flame_steak file's own calibration comes from COLMAP on 2690x2016 images with fx != fy",
                "(SOURCES.md); part of its 0.3-degree rotation difference may be that calibration's, not ours.",
                "",
                f"Command: `{command}`",
                "",
                f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, no GPU; "
                f"Python {platform.python_version()}, pycolmap {_pycolmap_version()}, OMP_NUM_THREADS="
                f"{os.environ.get('OMP_NUM_THREADS', 'unset')}.",
                "",
            ]
        )
        self.output.write_text(text)
        print(text)


def _names(cameras: Sequence[int]) -> str:
    return ", ".join(f"cam{i:02d}" for i in cameras) or "none"


def _pycolmap_version() -> str:
    import pycolmap

    return pycolmap.__version__

