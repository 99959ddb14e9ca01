"""What a scene costs at the datasets' real sizes, on real content upscaled to them: the caches' disk, and peak RSS and
seconds per iteration of short ns-train runs; records accumulate in ``<output>/records.json``."""

from __future__ import annotations

import copy
import dataclasses
import datetime
import json
import os
import shlex
import shutil
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Sequence, Tuple

import numpy as np
from PIL import Image

from benchmarks.common import REAL, fill_page, machine_description, table, timed_train


@dataclass(frozen=True)
class Dataset:
    name: str
    cameras: int
    frames: int
    source_size: Tuple[int, int]
    """(width, height) of the distributed files."""
    train_size: Tuple[int, int]
    """(width, height) trained on (the published downscale)."""
    files: str
    """'png' (frames read by cache_image_frames) or 'video' (decoded by cache_video_frames)."""


DATASETS: Dict[str, Dataset] = {
    d.name: d
    for d in (
        Dataset("Technicolor", 16, 50, (2048, 1088), (2048, 1088), "png"),
        Dataset("N3D", 21, 300, (2704, 2028), (1352, 1014), "video"),
        Dataset("Immersive", 46, 50, (2560, 1920), (1280, 960), "video"),
    )
}

PANOPTIC = REAL / "panoptic_basketball"
SAM_IMAGES = 2
"""Frames per dataset and content encoded for SAM."""
PANOPTIC_SIZE = (320, 180)


def upscaled(image: Image.Image, size: Tuple[int, int]) -> np.ndarray:
    return np.asarray(image.convert("RGB").resize(size, Image.Resampling.BICUBIC))


def real_content() -> Dict[str, List[Image.Image]]:
    """Frame 0 of every camera of the panoptic capture."""
    frames = sorted(PANOPTIC.glob("Basketball_undist_00000_*.png"))
    return {"panoptic_basketball (16 cameras)": [Image.open(p) for p in frames]}


def disk_bytes(folder: Path) -> int:
    """Bytes a folder takes on disk (allocated blocks of its files and sub-folders, as ``du``)."""
    return sum(p.lstat().st_blocks * 512 for p in folder.rglob("*"))


def measure_caches(dataset: Dataset, content: str, images: Sequence[Image.Image], work: Path) -> Dict[str, Any]:
    """The frame cache (of the dataset's files) and the SAM cache of a dataset's real size on upscaled real content."""
    from gear_nerfstudio.data.frame_cache import cache_image_frames, cache_video_frames
    from gear_nerfstudio.tools.video import write_video

    folder = work / "disk" / dataset.name / content.split()[0]
    shutil.rmtree(folder, ignore_errors=True)
    frame_cache = folder / "frame-cache"
    frame_cache.mkdir(parents=True)
    big = [upscaled(image, dataset.source_size) for image in images]
    if dataset.files == "video":
        video = folder / "source.mp4"
        write_video(video, big, fps=30)
        cache_video_frames([video], list(range(len(big))), [dataset.train_size], frame_cache)
        in_place, trained = False, sorted(frame_cache.rglob("*.png"))
    else:
        sources = [folder / f"frame{i:02d}.png" for i in range(len(big))]
        for rgb, path in zip(big, sources):
            Image.fromarray(rgb).save(path)
        cached = cache_image_frames([[p] for p in sources], [0], [dataset.train_size] * len(big), frame_cache)
        in_place, trained = [row[0] for row in cached] == sources, sources
    return {
        "dataset": dataset.name,
        "content": content,
        "in_place": in_place,
        "frame_cache_bytes_per_frame": disk_bytes(frame_cache) / len(big),
        **measure_sam(trained, folder / "sam-cache", SAM_IMAGES),
    }


def measure_sam(frames: Sequence[Path], folder: Path, count: int) -> Dict[str, Any]:
    """SAM cache files of the first `count` frames, written by SamFeatureCache with the built-in backend."""
    from gear_nerfstudio.sam.config import BuiltinSamConfig
    from gear_nerfstudio.sam.feature_cache import MAGIC, SamFeatureCache

    shutil.rmtree(folder, ignore_errors=True)
    encoded = list(frames[:count])
    SamFeatureCache(BuiltinSamConfig().setup(), folder, encoded).precompute()
    files = [p for p in folder.rglob("*") if p.is_file()]
    if len(files) != len(encoded):
        raise RuntimeError(f"{folder}: expected {len(encoded)} cache files, found {len(files)}")
    with open(files[0], "rb") as handle:
        sam_format = handle.read(len(MAGIC)).decode("ascii", "replace")
    return {
        "sam_format": sam_format,
        "sam_bytes_per_file": sum(p.lstat().st_blocks * 512 for p in files) / len(files),
    }


def write_panoptic_scene(folder: Path, size: Tuple[int, int], frames: int) -> Path:
    """The panoptic capture's first `frames` frames in the Technicolor layout, upscaled to `size` (intrinsics scaled:
    f and cu by the horizontal factor, cv by the vertical one, ar by their ratio). Kept when already written."""
    camera_file = folder / "cameras_parameters.txt"
    if camera_file.is_file():
        return folder
    folder.mkdir(parents=True, exist_ok=True)
    sx, sy = size[0] / PANOPTIC_SIZE[0], size[1] / PANOPTIC_SIZE[1]
    for frame in range(frames):
        for path in sorted(PANOPTIC.glob(f"Basketball_undist_{frame:05d}_*.png")):
            Image.fromarray(upscaled(Image.open(path), size)).save(folder / path.name)
    header, *rows = (PANOPTIC / "cameras_parameters.txt").read_text().splitlines()
    lines = [header]
    for row in rows:
        f, cu, cv, ar, *rest = row.split()
        scaled = [float(f) * sx, (float(cu) + 0.5) * sx - 0.5, (float(cv) + 0.5) * sy - 0.5, float(ar) * sy / sx]
        lines.append(" ".join([*(f"{v:.7g}" for v in scaled), *rest]))
    camera_file.write_text("\n".join(lines) + "\n")  # last: its presence marks a complete scene
    return folder


def parameter_bytes(method: str, frames: int) -> int:
    """Bytes of the parameters of `method`'s model built for a video of `frames` frames."""
    import torch
    from nerfstudio.configs.method_configs import all_methods
    from nerfstudio.data.scene_box import SceneBox

    model = copy.deepcopy(all_methods[method].pipeline.model).setup(
        scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])),
        num_train_data=1,
        metadata={"num_frames": frames, "near": 0.1, "far": 2.0, "unbounded": False},
    )
    return sum(p.numel() * p.element_size() for p in model.parameters())


def train(args: "RealSizeCosts", dataset: Dataset, method: str, frames: int) -> Dict[str, Any]:
    """One ns-train run (child process with timing hooks); the first iteration is left out of the median."""
    w, h = dataset.train_size
    scene = write_panoptic_scene(args.output / "scenes" / f"{w}x{h}-{frames}f", dataset.train_size, frames)
    name = f"{dataset.name}-{frames}f"
    shutil.rmtree(args.output / "runs" / name / method / "run", ignore_errors=True)
    command = [
        method, "--output-dir", str(args.output / "runs"), "--experiment-name", name, "--timestamp", "run",
        "--max-num-iterations", str(args.iterations),
        "--pipeline.gear-updates.enabled", "False",
        "--steps-per-save", str(args.iterations), "--machine.device-type", "cpu", "--vis", "tensorboard",
        "--steps-per-eval-batch", "0", "--steps-per-eval-image", "0", "--steps-per-eval-all-images", "0",
        "--pipeline.datamanager.sam-cache-dir", str(args.output / "sam-cache"),
        "technicolor-data", "--data", str(scene), "--near", "0.3", "--far", "7",
        "--cache-dir", str(args.output / "frame-cache"),
    ]  # fmt: skip
    (args.output / "runs").mkdir(parents=True, exist_ok=True)
    log_path = args.output / "runs" / f"{name}-{method}.log"
    print(f"[real_size_costs] {name} {method}: ns-train {shlex.join(command)}", flush=True)
    timing, usage = timed_train(command, args.output / "runs" / f"{name}-{method}.json", log_path)
    iterations = timing["iteration_seconds"]
    record = {
        "dataset": dataset.name,
        "method": method,
        "frames": frames,
        "images": 16 * frames,
        "command": ["ns-train", *command],
        "peak_rss_bytes": usage.ru_maxrss * 1024,  # Linux: KiB
        "median_iteration_seconds": statistics.median(iterations[1:]),
        "timed_iterations": len(iterations[1:]),
        "parameter_bytes": parameter_bytes(method, frames),
        "parameter_bytes_at_real_frames": parameter_bytes(method, dataset.frames),
    }
    print(f"[real_size_costs] {name} {method}: peak RSS {record['peak_rss_bytes'] / 2**20:.0f} MiB, "
          f"{record['median_iteration_seconds']:.2f} s / iteration", flush=True)
    return record


def size(value: float) -> str:
    """Bytes in the largest binary unit that keeps the number at least 1."""
    for unit, power in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if abs(value) >= 2**power:
            return f"{value / 2**power:,.2f} {unit}"
    return f"{value:.0f} B"


def disk_table(records: List[Dict[str, Any]]) -> List[str]:
    rows = []
    for r in records:
        d = DATASETS[r["dataset"]]
        count = d.cameras * d.frames
        frames, sam = r["frame_cache_bytes_per_frame"] * count, r["sam_bytes_per_file"] * count
        rows.append([
            f"{d.name} ({d.cameras} x {d.frames} = {count}, {d.train_size[0]}x{d.train_size[1]})", r["content"],
            f"`{r['sam_format']}`", "yes (empty check markers only)" if r["in_place"] else "no: PNG copies",
            size(r["frame_cache_bytes_per_frame"]), size(d.train_size[0] * d.train_size[1] * 3), size(frames),
            size(r["sam_bytes_per_file"]), size(sam), size(frames + sam),
        ])  # fmt: skip
    return table(["dataset (cameras x frames, training size)", "content (upscaled)", "SAM cache format",
                  "frame cache: frames read in place?", "frame cache / frame **(measured)**",
                  "uncompressed RGB / frame (computed)", "frame cache / scene (computed)", "SAM file **(measured)**",
                  "SAM cache / scene (computed)", "both caches / scene (computed)"], rows)  # fmt: skip


def train_table(records: List[Dict[str, Any]]) -> List[str]:
    rows = []
    for r in records:
        d = DATASETS[r["dataset"]]
        rows.append([
            f"{d.train_size[0]}x{d.train_size[1]} ({d.name})", r["method"], f"{r['frames']} ({r['images']})",
            size(r["peak_rss_bytes"]), f"{r['median_iteration_seconds']:.2f} (of {r['timed_iterations']})",
            size(r["parameter_bytes"]), f"{size(r['parameter_bytes_at_real_frames'])} ({d.frames} frames)",
            size(4 * (r["parameter_bytes_at_real_frames"] - r["parameter_bytes"])),
        ])  # fmt: skip
    header = ["training size (dataset)", "method", "frames (images)", "peak RSS **(measured)**",
              "s / iteration, median **(measured)**", "parameters at these frames **(measured)**",
              "parameters at the real frame count **(measured, model built)**",
              "training memory added at the real frame count, at most (computed)"]
    return table(header, rows)


def parts(records: Dict[str, Any]) -> Dict[str, str]:
    """The generated parts of the results page, by their markers' names."""
    runs = [f"- `{run['command']}` (part: {', '.join(run['parts'])}), {run['date']}; 1-minute load average "
            f"{run['load']}; {run['machine']}" for run in records["invocations"]]  # fmt: skip
    return {"runs": "\n".join(runs), "disk": "\n".join(disk_table(records["disk"])),
            "train": "\n".join(train_table(records["train"]))}


@dataclasses.dataclass
class RealSizeCosts:
    """Measure the caches' disk, and short training runs' memory and speed, at the datasets' real sizes."""

    output: Path = Path("outputs/real_size_costs")
    """Working folder: scenes, caches, runs, records.json, real_size_costs.md (the tables)."""
    results: Optional[Path] = None
    """Also write the tables into real_size_costs.md here, between its ``<!-- part -->`` markers."""
    only: Optional[Literal["disk", "train"]] = None
    """One part; the other part's records stay."""
    datasets: Tuple[Literal["Technicolor", "N3D", "Immersive"], ...] = ("Technicolor", "N3D", "Immersive")
    methods: Tuple[str, ...] = ("gear-nerf", "gear-nerf-baseline")
    iterations: int = 4
    """Iterations per run."""
    frames: int = 3
    """Frames of the training scenes (the panoptic capture has 20)."""

    def main(self) -> None:
        records_path = self.output / "records.json"
        empty = {"invocations": [], "disk": [], "train": []}
        records = json.loads(records_path.read_text()) if records_path.is_file() else empty
        parts_run = ["disk", "train"] if self.only is None else [self.only]
        self.output.mkdir(parents=True, exist_ok=True)
        load = os.getloadavg()[0]
        if "disk" in parts_run:
            records["disk"] = self.measure_disk(records["disk"])
        command = shlex.join(["nice", "-n", str(os.nice(0)), ".venv/bin/python", "-m", "benchmarks", *sys.argv[1:]])
        invocation = {"command": command, "parts": parts_run, "machine": machine_description("cpu")}
        records["invocations"].insert(0, invocation)

        def save() -> None:
            """Records and pages as they stand (after every run, so that a stopped benchmark keeps what it measured)."""
            date = datetime.datetime.now().strftime("%Y-%m-%d %H:%M")
            invocation.update(date=date, load=f"{load:.2f} at the start, {os.getloadavg()[0]:.2f} at the end")
            records_path.write_text(json.dumps(records, indent=1))
            generated = parts(records)
            (self.output / "real_size_costs.md").write_text("\n\n".join(f"## {n}\n\n{t}" for n, t in generated.items()))
            if self.results is not None:
                fill_page(self.results / "real_size_costs.md", generated)

        save()
        runs = [(name, method) for method in self.methods for name in self.datasets]
        for name, method in runs if "train" in parts_run else []:
            record = train(self, DATASETS[name], method, self.frames)
            kept = [r for r in records["train"] if (r["dataset"], r["method"]) != (name, method)]
            records["train"] = sorted(kept + [record], key=lambda r: (r["method"], list(DATASETS).index(r["dataset"]),
                                                                      r["frames"]))  # fmt: skip
            save()
        print((self.output / "real_size_costs.md").read_text())

    def measure_disk(self, old: List[Dict[str, Any]]) -> List[Dict[str, Any]]:
        """The frame and SAM caches of every dataset and content; ``old``'s records of other datasets, contents and
        SAM formats kept."""
        measured = []
        for name in self.datasets:
            dataset = DATASETS[name]
            for source, images in real_content().items():
                measured.append(measure_caches(dataset, source, images, self.output))
                print(f"[real_size_costs] disk: {measured[-1]}", flush=True)
        keys = {(r["dataset"], r["content"], r["sam_format"]) for r in measured}
        measured += [r for r in old if (r["dataset"], r["content"], r["sam_format"]) not in keys]
        return sorted(measured, key=lambda r: (list(DATASETS).index(r["dataset"]), r["content"], r["sam_format"]))

