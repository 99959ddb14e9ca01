"""`ns-gear-process`: synchronised videos of a rig of fixed cameras -> a scene `neural-3d-video-data` reads.

    ns-gear-process --data my_rig/ --output-dir scenes/my_rig

`--data` holds one video per camera (or one folder of frames per camera). The output holds `cam00.mp4` ... (the
held-out camera first, the others in the sorted order of the input names), `poses_bounds.npy`, `transforms.json`
(cameras, sources, offsets, reprojection errors, the self-check's judgement, points), `sparse_points.ply`, COLMAP's
model in `colmap/sparse/` and `rig.png`. The self-check calibrates the rig again from other frames and names each
camera it doubts, with the evidence (`self_check.py`). Everything is written into a temporary folder beside the
output and renamed at the end, so bad input (reported in one line) leaves nothing behind.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import List, Literal, Optional, Tuple

import numpy as np
import tyro
from nerfstudio.utils.rich_utils import CONSOLE
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from gear_nerfstudio.errors import InputError
from gear_nerfstudio.process import calibrate, self_check, sync, write
from gear_nerfstudio.process.footage import Footage, check_frame_rates, read_footage
from gear_nerfstudio.process.plot import plot_rig


@dataclass
class ProcessCommand:
    """Turn synchronised videos (one per camera, or one folder of frames per camera) into a Neural 3D Video scene:
    COLMAP calibration, undistortion, synchronisation."""

    data: Path
    """Folder of the rig's recordings: one video per camera, or one folder of frames per camera."""
    output_dir: Path
    """Scene folder to write (must not exist); train with `ns-train ... neural-3d-video-data --data <it>`."""
    calibration_frames: Optional[Tuple[int, ...]] = None
    """Instants (frames of the synchronised window) whose frames COLMAP calibrates from; several help a scene with
    little texture at one instant. Default: the first, middle and last frames of the window."""
    camera_model: Literal[calibrate.CAMERA_MODELS] = "SIMPLE_RADIAL"  # type: ignore[valid-type]
    """COLMAP camera model of every camera (intrinsics shared by a camera's frames)."""
    camera_params: Optional[Tuple[float, ...]] = None
    """Known intrinsics of every camera in the model's COLMAP order (e.g. SIMPLE_RADIAL: f cx cy k), held fixed."""
    held_out: Optional[str] = None
    """Input camera (file or folder name, with or without extension) to hold out: it becomes cam00. Default: the
    first."""
    offsets: Optional[Tuple[float, ...]] = None
    """Per camera, in sorted input order: the instant its frame 0 shows, in frames of the first camera."""
    sync: Literal["none", "audio"] = "none"
    """'audio': estimate the offsets from the audio tracks (cross-correlation); 'none': --offsets or all 0."""
    frame_rate: float = 30.0
    """Frame rate of folders of frames (videos carry their own)."""
    self_check: bool = True
    """Calibrate the rig again from other frames, twice, and name each camera that both disagree with as doubtful."""
    doubtful_cameras: Literal["keep", "leave-out", "error"] = "keep"
    """Doubtful cameras: 'keep' them (each named in one line), 'leave-out' of the scene, or stop with an 'error'."""

    def main(self) -> None:
        output = self.output_dir
        if output.exists():
            raise InputError(f"{output}: the output folder already exists; remove it or choose another --output-dir")
        cameras = read_footage(self.data, self.frame_rate)
        if len(cameras) > 100:
            raise InputError(f"{self.data}: {len(cameras)} cameras; the Neural 3D Video layout names at most 100")
        check_frame_rates(cameras)
        offsets = self._offsets(cameras)
        firsts, count = sync.window(cameras, offsets)
        if self.calibration_frames is None:
            self.calibration_frames = (0, count // 2, count - 1)
        for instant in self.calibration_frames:
            if not 0 <= instant < count:
                raise InputError(f"--calibration-frames {instant}: outside the synchronised window 0..{count - 1}")
        order = self._order(cameras)
        names = [f"cam{index:02d}" for index in range(len(cameras))]

        temporary = output.parent / f".{output.name}.tmp-{os.getpid()}"
        output.parent.mkdir(parents=True, exist_ok=True)
        try:
            temporary.mkdir()
            self._write(cameras, offsets, firsts, count, order, names, temporary)
            os.rename(temporary, output)
        finally:
            shutil.rmtree(temporary, ignore_errors=True)
        CONSOLE.print(f"Wrote {output}: train with `ns-train gear-nerf neural-3d-video-data --data {output}`")

    def _offsets(self, cameras: List[Footage]) -> List[float]:
        if self.sync == "audio":
            if self.offsets is not None:
                raise InputError("--offsets and --sync audio: give one of them")
            estimates = sync.audio_offsets(cameras)
            for camera, estimate in zip(cameras, estimates):
                CONSOLE.print(
                    f"{camera.name}: offset {estimate.offset:+.2f} frames (confidence {estimate.confidence:.2f})",
                    markup=False,
                )
            return [estimate.offset for estimate in estimates]
        if self.offsets is None:
            return [0.0] * len(cameras)
        if len(self.offsets) != len(cameras):
            raise InputError(
                f"--offsets: {len(self.offsets)} values for {len(cameras)} cameras ({', '.join(c.name for c in cameras)})"
            )
        return list(self.offsets)

    def _order(self, cameras: List[Footage]) -> List[int]:
        """Input cameras in output order: the held-out one first, then the others in sorted order."""
        if self.held_out is None:
            return list(range(len(cameras)))
        matches = [i for i, c in enumerate(cameras) if self.held_out in (c.name, Path(c.name).stem)]
        if not matches:
            raise InputError(f"--held-out {self.held_out}: no such camera; cameras: {', '.join(c.name for c in cameras)}")
        return matches[:1] + [i for i in range(len(cameras)) if i != matches[0]]

    def _write(
        self, cameras: List[Footage], offsets: List[float], firsts: List[int], count: int, order: List[int],
        names: List[str], folder: Path,
    ) -> None:
        colmap = folder / "colmap"
        images = colmap / "images"
        instants = sorted(set(self.calibration_frames))
        checks = self_check.check_instants(instants, count) if self.self_check else []
        decoded = sorted(set(instants).union(*checks))
        with Progress(
            TextColumn("[bold blue]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
            console=CONSOLE, transient=True,
        ) as progress:
            task = progress.add_task("Decoding calibration frames", total=len(cameras) * len(decoded))
            for camera, first in zip(cameras, firsts):
                (images / camera.name).mkdir(parents=True)
                for instant, rgb in zip(decoded, camera.frames_at([first + instant for instant in decoded])):
                    _save_png(rgb, images / camera.name / f"{instant:05d}.png")
                    progress.advance(task)
            inputs = [c.name for c in cameras]
            result = calibrate.summarise(
                calibrate.reconstruct(images, inputs, instants, self.camera_model, self.camera_params, progress), inputs
            )
            judgements = self_check.judge(result, inputs, [
                calibrate.reconstruct(
                    images, inputs, frames, self.camera_model, self.camera_params, progress, seed=calibrate.SEED + k,
                    label=f"Self-check {k}/{len(checks)}: ",
                )
                for k, frames in enumerate(checks, start=1)
            ])
            order, names = self._judged(judgements, cameras, order, names, checks)
            outputs = write.output_cameras(result)
            task = progress.add_task("Writing videos (frames)", total=len(order) * count)
            for index, name in zip(order, names):
                maps = write.resampling_map(result.cameras[index], outputs[index])
                write.write_video(
                    cameras[index], firsts[index], count, maps, folder / f"{name}.mp4", lambda: progress.advance(task)
                )

        c2w = write.camera_to_world(result.cam_from_world)[order]
        bounds = [write.near_far(result.depths[i]) for i in order]
        np.save(folder / "poses_bounds.npy", write.poses_bounds(c2w, [outputs[i] for i in order], bounds))
        frames = []
        for index, name, pose, (near, far) in zip(order, names, c2w, bounds):
            frame = write.transforms_frame(name, cameras[index], pose, outputs[index])
            frame.update(
                near=near, far=far, offset_frames=offsets[index], first_source_frame=firsts[index],
                colmap_camera={"model": result.cameras[index].model_name, "params": result.cameras[index].params.tolist()},
                reprojection_error_px=float(result.reprojection_errors[index]),
                observations=int(len(result.depths[index])),
            )
            if checks:
                frame["self_check"] = judgements[index].as_dict()
            frames.append(frame)
        summary = {
            "camera_model": "PINHOLE",
            "frame_rate": float(cameras[0].frame_rate),
            "num_frames": count,
            "calibration_frames": instants,
            "self_check_frames": checks,
            "colmap_camera_model": self.camera_model,
            "reprojection_error_px": float(result.reconstruction.compute_mean_reprojection_error()),
            "num_points": int(len(result.points)),
            "ply_file_path": "sparse_points.ply",
            "frames": frames,
        }
        (folder / "transforms.json").write_text(json.dumps(summary, indent=2))
        result.reconstruction.export_PLY(folder / "sparse_points.ply")
        plot_rig(folder / "rig.png", c2w, names, result.points, result.colors, [judgements[i].doubtful for i in order])
        (colmap / "sparse").mkdir()
        result.reconstruction.write(colmap / "sparse")
        shutil.rmtree(images)
        CONSOLE.print(
            f"{len(order)} cameras in the scene, {len(result.points)} points, mean reprojection error "
            f"{summary['reprojection_error_px']:.2f} px; {count} frames of {outputs[0].width}x{outputs[0].height}; "
            f"check the rig in {self.output_dir / 'rig.png'}",
            markup=False,
        )

    def _judged(
        self, judgements: List[self_check.Judgement], cameras: List[Footage], order: List[int], names: List[str],
        checks: List[List[int]],
    ) -> Tuple[List[int], List[str]]:
        """Name each doubtful camera in one line; leave them out of `order` (and `names`) or stop, as asked."""
        doubtful = [i for i in order if judgements[i].doubtful]
        if doubtful and self.doubtful_cameras == "error":
            raise InputError(
                f"{self.data}: doubtful cameras: "
                + ", ".join(f"{cameras[i].name} ({judgements[i].evidence})" for i in doubtful)
                + "; calibrate from other --calibration-frames, or --doubtful-cameras leave-out"
            )
        kept = [i for i in order if i not in doubtful] if self.doubtful_cameras == "leave-out" else order
        if len(kept) < 2:
            raise InputError(f"{self.data}: {len(doubtful)} of {len(order)} cameras doubtful, fewer than 2 left")
        scene = dict(zip(kept, names))
        for i in doubtful:
            advice = "left out of the scene" if i not in scene else (
                f"{scene[i]} in the scene, orange in rig.png: check it there, calibrate from other "
                "--calibration-frames, or --doubtful-cameras leave-out"
            )
            CONSOLE.print(
                f"Doubtful camera {cameras[i].name}: calibrated again from frames "
                f"{' and '.join(map(str, checks))}: {judgements[i].evidence}; {advice}",
                markup=False, soft_wrap=True,
            )
        return kept, names[: len(kept)]


def _save_png(rgb: np.ndarray, path: Path) -> None:
    from PIL import Image

    Image.fromarray(rgb).save(path)


def entrypoint() -> None:
    """Console script; bad input is reported in one line (``gear_nerfstudio.errors``)."""
    tyro.cli(ProcessCommand).main()


if __name__ == "__main__":
    entrypoint()
