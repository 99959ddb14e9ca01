"""`ns-gear-track`: free-viewpoint tracking from clicks on a trained Gear-NeRF (Sec 4.5).

    ns-gear-track --load-config outputs/.../config.yml --click-camera cam01 --click-time 0.4 \
        --positive 31 22 --target-cameras cam00 --output-dir tracking/ball

Clicks are pixels (x, y) of a dataset camera (`--click-camera`) or of one frame of a camera-path JSON
as `ns-render camera-path` reads (`--click-camera-path`, `--click-frame`). Targets are dataset cameras
(default: the held-out ones) and/or every frame of a camera-path JSON, tracked at `--times` (default:
every frame of the trained window). Every view is rendered with the density only where at least `--min-views` (4)
training cameras see (`fields.seen_space`), whatever the run itself renders. Each target view's mask at the clicked
time is completed by multi-view agreement with the training views before it propagates (`--agreement`,
`agreement.agreed_mask`). The output
folder holds `masks/<view>/t<time>.png`, `overlay/<view>.mp4` (rendered colour, mask in red, prompts marked)
and `tracking.json` (the SAM backend
and its settings, the clicks, their 3D points, the prompt of every mask and, when the scene has synthetic
ground truth `ground_truth/<camera>.npz`, IoU and accuracy per mask with mIoU / accuracy at the clicked time and
t-mIoU / t-accuracy at the other times). Everything is checked before anything is written, and the
folder appears only when complete.

A click that works can still miss the object: the clicks are also segmented in the clicked view itself
(with the depth rendered there), and one warning line each (on stderr, and in tracking.json's "warnings")
says when that mask covers most of the view, when the click seems to have hit the background
(`click.check_click`; the numbers behind both are in tracking.json's "click"), and how many tracked masks
cover more than half of their view ("masks_covering_most_of_view"; "share" per mask). Tracking still runs.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
import tyro
from PIL import Image

from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.data_parsers.multiview import cameras_by_name
from gear_nerfstudio.sam.interface import cell_centres
from gear_nerfstudio.tools.synthetic.ground_truth import GroundTruth
from gear_nerfstudio.tools.video import write_video
from gear_nerfstudio.tracking.agreement import agreed_mask, object_views
from gear_nerfstudio.tracking.metrics import score, summarise
from gear_nerfstudio.tracking.click import (
    HIT_ACCUMULATION,
    MOST_OF_VIEW,
    ClickHit,
    TrackingError,
    check_click,
    check_time,
    image_size,
    project_prompt,
    trace_click,
    view_depth,
    view_share,
)
from gear_nerfstudio.tracking.propagation import (
    Propagation,
    frame_times,
    mask_cells,
    render_embedding,
    render_rgb,
    segment,
    track_view,
)


BACKGROUND_ID = 0
"""Object id of the static background (wall, floor, sky) in a synthetic scene's ground truth."""


@dataclass
class TrackCommand:
    """Track the object under one or more clicks into other views and times (Gear-NeRF Sec 4.5)."""

    load_config: Path
    """config.yml of a trained Gear-NeRF run."""
    output_dir: Path = Path("tracking")
    """Folder to create with the masks, overlay videos and tracking.json."""
    click_camera: Optional[str] = None
    """Dataset camera that was clicked (e.g. cam01); or use --click-camera-path."""
    click_camera_path: Optional[Path] = None
    """Camera-path JSON (ns-render format) whose frame --click-frame was clicked."""
    click_frame: int = 0
    """Frame of --click-camera-path that was clicked."""
    click_time: Optional[float] = None
    """Time of the click in [0, 1]; default: the camera-path frame's render_time."""
    positive: List[Tuple[float, float]] = field(default_factory=list)
    """Positive clicks: pixel x y pairs (x y x y ... for several)."""
    negative: List[Tuple[float, float]] = field(default_factory=list)
    """Negative clicks: pixel x y pairs."""
    target_cameras: Optional[List[str]] = None
    """Dataset cameras to track in; default: the held-out cameras (unless --target-camera-path is given)."""
    target_camera_path: Optional[Path] = None
    """Camera-path JSON whose every frame is a target view."""
    times: Optional[List[float]] = None
    """Times in [0, 1] to track to; default: every frame of the trained window."""
    propagation: Propagation = "embedding"
    """Prompt at t +- 1: "box", the mask's box (the paper); "embedding": the same, then points over the cells whose
    rendered features match the object's, and their box, where the box's mask disagrees with those cells."""
    agreement: bool = True
    """Refine each target view's mask at the clicked time by multi-view agreement: add the cells that the object's
    masks in most training views that see them, at the same time, put inside it (`agreement.agreed_mask`)."""
    min_views: int = 4
    """Render every view with the density only where at least this many training cameras see a point, whatever
    the run's `--pipeline.model.render.min-views`; 0: all space."""
    min_accumulation: float = HIT_ACCUMULATION
    """A click ray whose accumulated density stays below this hits nothing (lower it for a model trained
    only briefly, whose density is still faint)."""
    video: bool = True
    """Write overlay/<view>.mp4 (renders the colour image of every view and time)."""
    fps: int = 5
    """Frame rate of the overlay videos."""
    overwrite: bool = False
    """Replace an existing output folder (only once the new one is complete)."""

    def main(self) -> None:
        """Check the arguments, load the model, plan every prompt (all checks), then write."""
        self.check_arguments()
        config, pipeline, checkpoint, step = self.load()
        plan = Plan.make(self, config, pipeline)
        for warning in plan.warnings:  # before the long part: the user may stop and click again
            warn(warning)
        backend = pipeline.sam_backend  # named in the summary: which decoder made the masks
        header = {
            "config": str(self.load_config), "checkpoint": str(checkpoint), "step": step,
            "sam_backend": {"name": backend.name, "settings": backend.settings}, "min_views": self.min_views,
        }  # fmt: skip
        summary = plan.write(self, header)
        for warning in summary["warnings"][len(plan.warnings) :]:
            warn(warning)
        print(format_summary(summary, self.output_dir))

    def load(self) -> Tuple[Any, Any, Path, int]:
        """The trained run (`eval_setup`), its renders keeping the density where --min-views training cameras see."""
        from nerfstudio.utils.eval_utils import eval_setup

        config, pipeline, checkpoint, step = eval_setup(self.load_config, test_mode="test")
        pipeline.model.see_from(pipeline.datamanager.train_dataparser_outputs.cameras, self.min_views)
        return config, pipeline, checkpoint, step

    def check_arguments(self) -> None:
        """Everything that needs no model: the click, times, files and the output folder."""
        if (self.click_camera is None) == (self.click_camera_path is None):
            raise TrackingError("give exactly one of --click-camera (a dataset camera) or --click-camera-path")
        if not self.positive:
            raise TrackingError("give at least one positive click: --positive X Y")
        if self.click_time is not None:
            check_time(self.click_time, "--click-time")
        for time in self.times or []:
            check_time(time, "--times value")
        if self.min_views < 0:
            raise TrackingError(f"--min-views must be at least 0, got {self.min_views}")
        if not 0.0 < self.min_accumulation <= 1.0:
            raise TrackingError(f"--min-accumulation must be in (0, 1], got {self.min_accumulation}")
        if self.fps < 1:
            raise TrackingError(f"--fps must be at least 1, got {self.fps}")
        if not self.load_config.is_file():
            raise TrackingError(f"{self.load_config}: config file not found")
        for path in (self.click_camera_path, self.target_camera_path):
            if path is not None and not path.is_file():
                raise TrackingError(f"{path}: camera path file not found")
        if self.output_dir.exists() and not self.overwrite:
            raise TrackingError(f"{self.output_dir} already exists; choose another --output-dir or pass --overwrite")


def load_camera_path(path: Path):
    """Cameras of a camera-path JSON (ns-render's format), with times when every frame has render_time."""
    from nerfstudio.cameras.camera_paths import get_path_from_json

    try:
        cameras = get_path_from_json(json.loads(path.read_text()))
    except (OSError, ValueError, KeyError, TypeError, RuntimeError) as err:
        raise TrackingError(f"{path}: not a readable camera path ({type(err).__name__}: {err})") from err
    if cameras.size == 0:
        raise TrackingError(f"{path}: the camera path has no frames")
    return cameras


def dataset_cameras(pipeline) -> Tuple[Dict[str, Any], List[str]]:
    """One Cameras per dataset camera name (train and held-out), and the held-out names."""
    cameras: Dict[str, Any] = {}
    held_out: List[str] = []
    manager = pipeline.datamanager
    for dataset, is_eval in ((manager.train_dataset, False), (getattr(manager, "eval_dataset", None), True)):
        if dataset is None:
            continue
        metadata = dataset.metadata
        if "camera_names" not in metadata or "camera_ids" not in metadata:
            raise TrackingError("the dataset has no camera names (metadata camera_names / camera_ids)")
        named = cameras_by_name(dataset.cameras, metadata)
        if is_eval:
            held_out = [name for name in named if name not in cameras]
        for name, camera in named.items():
            cameras.setdefault(name, camera)
    return cameras, held_out


@dataclass
class Plan:
    """Everything checked before writing: the clicks' 3D points and each target view's prompts."""

    pipeline: Any
    click_name: str
    click_time: float
    pixels: np.ndarray  # (N, 2) clicked pixels
    labels: np.ndarray  # (N,)
    hits: List[ClickHit]  # where each click ray meets a surface (its point, depth, bounds, accumulation)
    click_check: Dict[str, Any]  # the clicks' mask in the clicked view: its shares (`click.check_click`)
    warnings: List[str]  # signs that the click missed its object (`click.check_click`)
    views: Dict[str, Any]  # name -> Cameras
    training_views: Dict[str, Any]  # name -> Cameras of the training cameras (multi-view agreement)
    view_pixels: Dict[str, np.ndarray]  # name -> (N, 2) projected prompts
    times: List[float]
    ground_truth: Optional[GroundTruth]
    target_object: Optional[int]

    @classmethod
    def make(cls, command: TrackCommand, config, pipeline) -> "Plan":
        model = pipeline.model
        cameras, held_out = dataset_cameras(pipeline)
        click_time = command.click_time
        if command.click_camera is not None:
            if command.click_camera not in cameras:
                raise TrackingError(f"unknown click camera {command.click_camera!r}; cameras: {sorted(cameras)}")
            click_name, click_camera = command.click_camera, cameras[command.click_camera]
        else:
            path = load_camera_path(command.click_camera_path)
            if not 0 <= command.click_frame < path.size:
                raise TrackingError(
                    f"{command.click_camera_path}: frame {command.click_frame} does not exist "
                    f"(the path has frames 0..{path.size - 1})"
                )
            click_camera = path[command.click_frame : command.click_frame + 1]
            click_name = f"{command.click_camera_path.name}#{command.click_frame}"
            if click_time is None and click_camera.times is not None:
                click_time = float(click_camera.times.reshape(-1)[0])
        if click_time is None:
            raise TrackingError("the click has no time: give --click-time (in [0, 1])")
        click_time = check_time(click_time, "click time")

        views: Dict[str, Any] = {}
        names = command.target_cameras
        if names is None and command.target_camera_path is None:
            names = held_out
        for name in names or []:
            if name not in cameras:
                raise TrackingError(f"unknown target camera {name!r}; cameras: {sorted(cameras)}")
            views[name] = cameras[name]
        if command.target_camera_path is not None:
            path = load_camera_path(command.target_camera_path)
            for index in range(path.size):
                views[f"{command.target_camera_path.stem}_{index:04d}"] = path[index : index + 1]
        if not views:
            raise TrackingError("no target views: give --target-cameras or --target-camera-path")

        pixels = np.array([*command.positive, *command.negative], dtype=np.float64)
        labels = np.array([1] * len(command.positive) + [0] * len(command.negative), dtype=np.int64)
        hits = []
        for (x, y), label in zip(pixels, labels):
            kind = "positive" if label else "negative"
            try:
                hits.append(trace_click(model, click_camera, (x, y), click_time, command.min_accumulation))
            except (TrackingError, DatasetError) as err:
                raise TrackingError(f"{kind} click on {click_name}: {err}") from err
        points = [hit.point for hit in hits]

        problems, view_pixels = [], {}
        for name, camera in views.items():
            try:
                view_pixels[name] = np.array([project_prompt(camera, point) for point in points])
            except (TrackingError, DatasetError) as err:
                problems.append(f"target view {name}: {err}")
        if problems:
            raise TrackingError("cannot prompt every target view:\n  " + "\n  ".join(problems))

        num_frames = int(getattr(model, "num_frames", 1))
        times = sorted({*(command.times if command.times is not None else frame_times(num_frames))})
        metadata = pipeline.datamanager.train_dataset.metadata
        ground_truth = GroundTruth.find(getattr(config.pipeline.datamanager.dataparser, "data", None), metadata)
        target_object = None
        if ground_truth is not None and command.click_camera is not None:
            ids = ground_truth.object_ids(click_name, click_time, image_size(click_camera))
            if ids is not None:
                x, y = command.positive[0]
                target_object = int(ids[int(y), int(x)])

        backend = pipeline.sam_backend  # the clicks' own mask, and the depth on its grid (`click.check_click`)
        mask = segment(backend, render_embedding(model, click_camera, click_time, backend), pixels, labels)
        depth = view_depth(model, click_camera, click_time, cell_centres(image_size(click_camera), backend.grid_size))
        click_check, warnings = check_click(
            click_name, click_time, mask, mask_cells(mask, backend.grid_size), depth, pixels.tolist(),
            labels.tolist(), hits, None if target_object is None else target_object == BACKGROUND_ID,
        )
        training_views = {name: camera for name, camera in cameras.items() if name not in held_out}
        return cls(
            pipeline, click_name, click_time, pixels, labels, hits, click_check, warnings, views, training_views,
            view_pixels, times, ground_truth, target_object,
        )

    def write(self, command: TrackCommand, header: Dict[str, Any]) -> Dict[str, Any]:
        """Track every view and write the outputs into a temporary folder, renamed when complete."""
        command.output_dir.parent.mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{command.output_dir.name}.", dir=command.output_dir.parent))
        try:
            summary = self._write_into(staging, command, header)
            if command.output_dir.exists():
                old = Path(tempfile.mkdtemp(prefix=f".{command.output_dir.name}.old.", dir=command.output_dir.parent))
                os.replace(command.output_dir, old / "previous")
                os.replace(staging, command.output_dir)
                shutil.rmtree(old)
            else:
                os.replace(staging, command.output_dir)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
        return summary

    def _write_into(self, folder: Path, command: TrackCommand, header: Dict[str, Any]) -> Dict[str, Any]:
        model = self.pipeline.model
        backend = self.pipeline.sam_backend
        num_frames = int(getattr(model, "num_frames", 1))
        records, scores = [], []
        seen = {}  # the object in every training view at the clicked time, for the multi-view agreement
        if command.agreement:
            points = [hit.point for hit in self.hits]
            seen = object_views(model, backend, self.training_views, points, self.labels, self.click_time)
        for name, camera in self.views.items():
            others = [view for other, view in seen.items() if other != name]
            refine = partial(agreed_mask, camera, views=others) if command.agreement else None
            tracked = track_view(
                model,
                backend,
                camera,
                self.view_pixels[name],
                self.labels,
                self.click_time,
                self.times,
                num_frames,
                command.propagation,
                refine,
            )
            frames = []
            for item in tracked:
                relative = Path("masks") / name / f"t{item.time:.4f}.png"
                (folder / relative).parent.mkdir(parents=True, exist_ok=True)
                Image.fromarray(item.mask.astype(np.uint8) * 255).save(folder / relative)
                record = {"view": name, "time": item.time, "mask": str(relative), "area": int(item.mask.sum())}
                record["share"] = view_share(item.mask)
                record["prompt"] = item.prompt
                truth = self._truth(name, item.time, image_size(camera))
                if truth is not None:
                    result = score(name, item.time, item.time == self.click_time, item.mask, truth)
                    scores.append(result)
                    record.update(iou=result.iou, accuracy=result.accuracy)
                records.append(record)
                if command.video:
                    frames.append(overlay(render_rgb(model, camera, item.time), item.mask, item.prompt))
            if frames:
                (folder / "overlay").mkdir(exist_ok=True)
                write_video(folder / "overlay" / f"{name}.mp4", [even(frame) for frame in frames], command.fps)

        large = [f"{r['view']} t={r['time']:.2f}" for r in records if r["share"] > MOST_OF_VIEW]
        warnings = list(self.warnings)
        if large:
            warnings.append(
                f"{len(large)} of {len(records)} tracked masks cover more than half of their view "
                f"({', '.join(large[:5])}{', ...' if len(large) > 5 else ''}): likely background, not the object"
            )
        summary = {
            **header,
            "depth": "median termination depth: where the click ray's accumulated weight reaches half its total",
            "min_accumulation": command.min_accumulation,
            "propagation": command.propagation,
            "click": {
                "camera": self.click_name,
                "time": self.click_time,
                "prompts": [
                    {
                        "pixel": pixel.tolist(),
                        "label": int(label),
                        "point": hit.point.tolist(),
                        "depth": hit.depth,
                        "depth_share": hit.depth_share,
                        "accumulation": hit.accumulation,
                    }
                    for pixel, label, hit in zip(self.pixels, self.labels, self.hits)
                ],
                **self.click_check,
            },
            "targets": list(self.views),
            "times": self.times,
            "masks": records,
            "masks_covering_most_of_view": len(large),
            "warnings": warnings,
            "ground_truth_object": self.target_object,
            "metrics": summarise(scores) if scores else None,
        }
        if not scores:
            summary["metrics_note"] = (
                "no metrics: they need a dataset click camera on a frame time and ground-truth masks "
                "(ground_truth/<camera>.npz, synthetic scenes) for the target views"
            )
        (folder / "tracking.json").write_text(json.dumps(summary, indent=2))
        return summary

    def _truth(self, view: str, time: float, size: Tuple[int, int]) -> Optional[np.ndarray]:
        if self.ground_truth is None or self.target_object is None:
            return None
        ids = self.ground_truth.object_ids(view, time, size)
        return None if ids is None else ids == self.target_object


def warn(message: str) -> None:
    """One warning line on stderr."""
    print(f"ns-gear-track: warning: {message}", file=sys.stderr, flush=True)


def overlay(rgb: np.ndarray, mask: np.ndarray, prompt: Dict[str, Any]) -> np.ndarray:
    """Rendered colour with the mask tinted red, the box in yellow, positive clicks green, negative blue."""
    image = rgb.astype(np.float32)
    image[mask] = 0.5 * image[mask] + 0.5 * np.array([255.0, 0.0, 0.0])
    height, width = mask.shape
    if prompt.get("box") is not None:
        x0, y0, x1, y1 = (int(v) for v in prompt["box"])
        x1, y1 = min(x1, width) - 1, min(y1, height) - 1
        image[y0, x0 : x1 + 1] = image[y1, x0 : x1 + 1] = (255, 255, 0)
        image[y0 : y1 + 1, x0] = image[y0 : y1 + 1, x1] = (255, 255, 0)
    for (x, y), label in zip(prompt.get("points", []), prompt.get("labels", [])):
        colour = (0, 255, 0) if label else (0, 128, 255)
        image[max(0, int(y) - 1) : int(y) + 2, max(0, int(x) - 1) : int(x) + 2] = colour
    return image.astype(np.uint8)


def even(frame: np.ndarray) -> np.ndarray:
    """Pad a frame to even width and height by repeating its last row / column (H.264)."""
    return np.pad(frame, ((0, frame.shape[0] % 2), (0, frame.shape[1] % 2), (0, 0)), mode="edge")


def format_summary(summary: Dict[str, Any], output_dir: Path) -> str:
    """A few lines for the terminal: where the outputs are and the metrics, in percent."""
    lines = [f"Tracked {len(summary['targets'])} view(s) x {len(summary['times'])} time(s) -> {output_dir}"]
    metrics = summary.get("metrics")
    if metrics:
        parts = []
        for key in ("mIoU", "accuracy", "t-mIoU", "t-accuracy"):
            value = metrics[key]
            parts.append(f"{key} {'n/a' if value is None else f'{100 * value:.1f}'}")
        lines.append(" | ".join(parts))
    else:
        lines.append(summary.get("metrics_note", ""))
    return "\n".join(lines)


def entrypoint() -> None:
    """Console script: clear one-line errors (exit status 2) instead of tracebacks for bad input."""
    command = tyro.cli(TrackCommand)
    try:
        command.main()
    except (TrackingError, DatasetError) as err:
        print(f"ns-gear-track: error: {err}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    entrypoint()
