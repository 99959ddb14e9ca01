"""`ns-gear-process`: synchronised videos of a rig of fixed cameras -> a scene `neural-3d-video-data` reads.

    ns-gear-process --data my_rig/ --output-dir scenes/my_rig

`--data` holds one video per camera (or one folder of frames per camera). The output holds `cam00.mp4` ... (the
held-out camera first, the others in the sorted order of the input names), `poses_bounds.npy`, `transforms.json`
(cameras, sources, offsets, reprojection errors, points), `sparse_points.ply`, COLMAP's model in `colmap/sparse/` and
`rig.png`. Everything is written into a temporary folder beside the output and renamed at the end, so bad input
(reported in one line) leaves nothing behind.
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
from gear_nerfstudio.process import calibrate, sync, write
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
        with Progress(
            TextColumn("[bold blue]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
            console=CONSOLE, transient=True,
        ) as progress:
            task = progress.add_task("Decoding calibration frames", total=len(cameras) * len(instants))
            for camera, first in zip(cameras, firsts):
                (images / camera.name).mkdir(parents=True)
                for instant, rgb in zip(instants, camera.frames_at([first + instant for instant in instants])):
                    _save_png(rgb, images / camera.name / f"{instant:05d}.png")
                    progress.advance(task)
            result = calibrate.calibrate(
                images, [c.name for c in cameras], instants, self.camera_model,
                self.camera_params, progress,
            )
            outputs = write.output_cameras(result)
            task = progress.add_task("Writing videos (frames)", total=len(cameras) * count)
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
            frames.append(frame)
        summary = {
            "camera_model": "PINHOLE",
            "frame_rate": float(cameras[0].frame_rate),
            "num_frames": count,
            "calibration_frames": instants,
            "colmap_camera_model": self.camera_model,
            "reprojection_error_px": float(result.reconstruction.compute_mean_reprojection_error()),
            "num_points": int(len(result.points)),
            "ply_file_path": "sparse_points.ply",
            "frames": frames,
        }
        (folder / "transforms.json").write_text(json.dumps(summary, indent=2))
        result.reconstruction.export_PLY(folder / "sparse_points.ply")
        plot_rig(folder / "rig.png", c2w, names, result.points, result.colors)
        (colmap / "sparse").mkdir()
        result.reconstruction.write(colmap / "sparse")
        shutil.rmtree(images)
        CONSOLE.print(
            f"{len(cameras)} cameras registered, {len(result.points)} points, mean reprojection error "
            f"{summary['reprojection_error_px']:.2f} px; {count} frames of {outputs[0].width}x{outputs[0].height}; "
            f"check the rig in {self.output_dir / 'rig.png'}",
            markup=False,
        )


def _save_png(rgb: np.ndarray, path: Path) -> None:
    from PIL import Image

    Image.fromarray(rgb).save(path)


def entrypoint() -> None:
    """Console script; bad input is reported in one line (``gear_nerfstudio.errors``)."""
    tyro.cli(ProcessCommand).main()


if __name__ == "__main__":
    entrypoint()
