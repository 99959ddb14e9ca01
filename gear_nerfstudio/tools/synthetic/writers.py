"""Write a synthetic scene in the Technicolor, Neural 3D Video and Google Immersive on-disk formats.

Each writer renders every (camera, frame), writes the dataset's own files, and writes ground truth to
`ground_truth/`: `scene.json` (objects, speeds, rig) and one `<camera name>.npz` per camera holding
`object_ids` (T, H, W) uint8, `motion` (T, H, W) float32 (world units per frame) and `depth`
(T, H, W) float32 (distance along the ray).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List, Literal, Sequence

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

from gear_nerfstudio.data.llff import llff_row
from gear_nerfstudio.tools.synthetic.rigs import immersive_rig, n3d_rig, technicolor_rig
from gear_nerfstudio.tools.synthetic.scene import MotionKind, Render, RigCamera, SyntheticScene
from gear_nerfstudio.tools.video import write_video

DatasetFormat = Literal["technicolor", "n3d", "immersive"]


@dataclass(frozen=True)
class SyntheticSpec:
    """Size of a synthetic capture. Defaults are test-sized (tens of pixels, a few frames)."""

    dataset: DatasetFormat = "technicolor"
    width: int = 40
    height: int = 30
    frames: int = 4
    cameras: int = 6  # N3D and Immersive; Technicolor uses rows x cols
    rows: int = 4
    cols: int = 4
    motion: MotionKind = "mixed"
    scene_name: str = "Synthetic"
    first_frame_number: int = 0  # Technicolor file numbering (real scenes start at 0 or 1)
    calibration_scale: float = 2.0  # N3D: poses_bounds.npy describes a camera this much larger
    fps: int = 30


def rig_for(spec: SyntheticSpec) -> List[RigCamera]:
    if spec.width % 2 or spec.height % 2:
        raise ValueError(f"width and height must be even for H.264 video, got {spec.width}x{spec.height}")
    if spec.dataset == "technicolor":
        return technicolor_rig(spec.rows, spec.cols, spec.width, spec.height)
    if spec.dataset == "n3d":
        return n3d_rig(spec.cameras, spec.width, spec.height)
    if spec.dataset == "immersive":
        return immersive_rig(spec.cameras, spec.width, spec.height)
    raise ValueError(f"unknown dataset format {spec.dataset!r}")


def write_synthetic_scene(output: Path, spec: SyntheticSpec = SyntheticSpec()) -> Path:
    """Render the scene from the rig of `spec.dataset` and write it to `output` in that format."""
    output = Path(output)
    output.mkdir(parents=True, exist_ok=True)
    scene = SyntheticScene(motion=spec.motion)
    cameras = rig_for(spec)
    writers: Dict[str, Callable] = {"technicolor": _write_technicolor, "n3d": _write_n3d, "immersive": _write_immersive}
    writers[spec.dataset](output, scene, cameras, spec)
    _write_scene_json(output, scene, cameras, spec)
    return output


def _render_camera(output: Path, scene: SyntheticScene, camera: RigCamera, frames: int) -> List[Render]:
    renders = [scene.render(camera, frame) for frame in range(frames)]
    gt_dir = output / "ground_truth"
    gt_dir.mkdir(exist_ok=True)
    np.savez_compressed(
        gt_dir / f"{camera.name}.npz",
        object_ids=np.stack([r.object_ids for r in renders]),
        motion=np.stack([r.motion for r in renders]),
        depth=np.stack([r.depth for r in renders]),
    )
    return renders


def _write_technicolor(output: Path, scene: SyntheticScene, cameras: Sequence[RigCamera], spec: SyntheticSpec):
    rows = ["f cu cv ar sk qw qx qy qz tx ty tz"]
    for index, camera in enumerate(cameras):
        for frame, render in enumerate(_render_camera(output, scene, camera, spec.frames)):
            number = spec.first_frame_number + frame
            Image.fromarray(render.rgb).save(output / f"{spec.scene_name}_undist_{number:05d}_{index:02d}.png")
        qx, qy, qz, qw = Rotation.from_matrix(camera.rotation).as_quat()
        values = [camera.fx, camera.cx, camera.cy, camera.fy / camera.fx, 0.0, qw, qx, qy, qz, *camera.translation]
        rows.append(" ".join(f"{v:.10g}" for v in values))
    (output / "cameras_parameters.txt").write_text("\n".join(rows) + "\n")


def _write_n3d(output: Path, scene: SyntheticScene, cameras: Sequence[RigCamera], spec: SyntheticSpec):
    poses = []
    for camera in cameras:
        renders = _render_camera(output, scene, camera, spec.frames)
        write_video(output / f"{camera.name}.mp4", [r.rgb for r in renders], spec.fps)
        c2w = np.concatenate([camera.rotation.T, camera.centre[:, None]], axis=1)
        s = spec.calibration_scale
        depths = np.concatenate([r.depth[np.isfinite(r.depth)] for r in renders])
        hwf = (camera.height * s, camera.width * s, camera.fx * s)
        poses.append(llff_row(c2w, hwf, 0.9 * depths.min(), 1.1 * depths.max()))
    np.save(output / "poses_bounds.npy", np.stack(poses))


def _write_immersive(output: Path, scene: SyntheticScene, cameras: Sequence[RigCamera], spec: SyntheticSpec):
    models = []
    for camera in cameras:
        renders = _render_camera(output, scene, camera, spec.frames)
        write_video(output / f"{camera.name}.mp4", [r.rgb for r in renders], spec.fps)
        k1, k2 = camera.fisheye
        models.append(
            {
                "name": camera.name,
                "width": camera.width,
                "height": camera.height,
                "position": camera.centre.tolist(),
                "orientation": Rotation.from_matrix(camera.rotation).as_rotvec().tolist(),
                "focal_length": camera.fx,
                "principal_point": [camera.cx, camera.cy],
                "pixel_aspect_ratio": camera.fy / camera.fx,
                "radial_distortion": [k1, k2, 0.0],
                "projection_type": "fisheye",
            }
        )
    (output / "models.json").write_text(json.dumps(models, indent=2))


def _write_scene_json(output: Path, scene: SyntheticScene, cameras: Sequence[RigCamera], spec: SyntheticSpec):
    info = {
        "spec": spec.__dict__,
        "objects": [
            {"id": obj.object_id, "name": obj.name, "radius": obj.radius, "speed_per_frame": obj.speed}
            for obj in scene.objects
        ],
        "cameras": [
            {
                "name": c.name,
                "rotation_world_to_camera_opencv": c.rotation.tolist(),
                "centre": c.centre.tolist(),
                "fx": c.fx,
                "fy": c.fy,
                "cx": c.cx,
                "cy": c.cy,
                "width": c.width,
                "height": c.height,
                "fisheye_k1_k2": list(c.fisheye) if c.fisheye else None,
            }
            for c in cameras
        ],
    }
    (output / "ground_truth" / "scene.json").write_text(json.dumps(info, indent=2))
