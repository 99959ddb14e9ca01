"""Speed / accuracy: Gear-NeRF against plain K-Planes on real captures, with seeds; held-out quality at every
checkpoint, scored at equal iterations and at equal training time (CPU seconds on the CPU, wall-clock on CUDA)."""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import shlex
import shutil
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import numpy as np

from benchmarks.common import REAL, page, table, timed_train, write_report
from gear_nerfstudio.method_configs.gear_nerf import schedule_options
from gear_nerfstudio.spread import evenly_spread

Clock = Literal["seconds", "cpu_seconds"]
"""A checkpoint's training time: wall-clock or CPU seconds of the training process."""

DECAY = " ".join(f"--optimizers.{group}.scheduler.max-steps {{steps}}" for group in ("fields", "proposal-networks"))
METHODS: Dict[str, Tuple[str, str]] = {
    "gear-nerf": ("Gear-NeRF", ""),
    "kplanes": ("plain K-Planes (N_gear = 1) with L_SAM", "--pipeline.model.num-gears 1"),
    "gear-nerf-no-points": ("Gear-NeRF without sparse points", "--pipeline.datamanager.sparse-depth-share 0"),
}
"""Method keys: (label in the tables and the plot, ns-train overrides on the base preset)."""


def method_overrides(method: str) -> List[str]:
    """``ns-train`` overrides of a method."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    return METHODS[method][1].split()


@dataclasses.dataclass(frozen=True)
class Scene:
    """A real capture as ns-train reads it, and its held-out camera."""

    name: str
    description: str
    held_out: str
    data: Path
    parser: str = "neural-3d-video-data"
    parser_options: Tuple[str, ...] = ()

    def dataparser(self, output: Path) -> List[str]:
        return [
            self.parser, "--data", str(self.data), "--held-out-camera", self.held_out,
            "--cache-dir", str(output / "cache" / self.name), *self.parser_options,
        ]  # fmt: skip


VIDEO, VIDEO_MASKS = REAL / "panoptic_basketball_video", str(REAL / "panoptic_basketball_video_masks")
LAYOUT = "real: CMU Panoptic basketball in the Neural 3D Video layout"
SCENES: Dict[str, Scene] = {
    scene.name: scene
    for scene in (
        Scene("panoptic", "real: CMU Panoptic basketball, 320x180, 16 cameras (15 trained), 20 frames", "06",
              REAL / "panoptic_basketball", "technicolor-data",
              ("--near", "0.3", "--far", "7", "--moving-masks", str(REAL / "panoptic_basketball_masks"))),
        Scene("panoptic-video", f"{LAYOUT}, 304x168 (downscale 2), 31 cameras (30 trained), frames 0-29", "cam00",
              VIDEO, parser_options=("--downscale-factor", "2", "--frame-count", "30")),
        Scene("panoptic-video-60", f"{LAYOUT}, 304x168 (downscale 2), 31 cameras (30 trained), frames 60-89 (no "
              "default was chosen on them), held-out cam20 with person masks", "cam20", VIDEO,
              parser_options=("--downscale-factor", "2", "--frame-start", "60", "--frame-count", "30",
                              "--moving-masks", VIDEO_MASKS)),
        Scene("panoptic-video-full", f"{LAYOUT} at full size, 608x336, 31 cameras (30 trained), all 90 frames (for "
              "the GPU)", "cam00", VIDEO),
        Scene("panoptic-video-full-30", f"{LAYOUT} at full size, 608x336, 31 cameras (30 trained), frames 0-29, "
              "held-out cam20 with person masks (for the GPU)", "cam20", VIDEO,
              parser_options=("--frame-count", "30", "--moving-masks", VIDEO_MASKS)),
    )
}  # fmt: skip
"""Scenes by name. ``panoptic`` holds out camera 06 (not the usual 10) because 10 has no masks; ``panoptic-video``
holds out cam00, the parser's default and the view published methods hold out, which has none (its moving region
is the held-out view's colour change); ``panoptic-video-60`` is the window of the same capture that no default was
chosen on, held out at cam20, which has masks."""


@dataclasses.dataclass
class SpeedAccuracy:
    """Train and evaluate Gear-NeRF and plain K-Planes (``METHODS``) on ``SCENES``; tables and a plot."""

    output: Path = Path("outputs/speed_accuracy")
    """Working folder: runs, logs, records.json, speed_accuracy.md / .png."""
    results: Optional[Path] = None
    """Also copy speed_accuracy.md and speed_accuracy.png here (e.g. benchmarks/results)."""
    scenes: Tuple[str, ...] = ("panoptic-video", "panoptic")
    """Scenes to run (``SCENES``)."""
    main_methods: Tuple[str, ...] = ("gear-nerf", "kplanes")
    """Methods run with every seed; the equal-time budget is the shortest of their mean training times."""
    ablations: Tuple[str, ...] = ()
    """Methods run with the first seed only."""
    seeds: int = 3
    """Seeds of the main methods (``--machine.seed`` first_seed, first_seed + 1, ...)."""
    first_seed: int = 42
    """The first seed (the ablations' only one): another value adds seeds to earlier runs in another folder."""
    iterations: Optional[int] = None
    """Training iterations of every run, with the gear-update schedule scaled to them as the presets scale theirs
    (``schedule_options``); default: the base preset's own, with its own schedule."""
    checkpoints: int = 8
    """Evaluated checkpoints per run, evenly spaced (the last is the final one)."""
    eval_frames: int = 6
    """Held-out frames scored per checkpoint, evenly spaced over the video (all when the video is shorter)."""
    device: Literal["cpu", "cuda"] = "cpu"
    """cpu: the CPU preset gear-nerf-small; cuda: the paper preset gear-nerf."""
    report_only: bool = False
    """Train nothing: write the tables and plot from the records of every planned run in the output folder."""

    def main(self) -> None:
        if self.device == "cpu":
            os.environ["CUDA_VISIBLE_DEVICES"] = ""  # the held-out renders run on the CPU as well
        for name in self.scenes:
            if name not in SCENES:
                raise ValueError(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
            for method in (*self.main_methods, *self.ablations):
                method_overrides(method)  # fail early on an unknown name
        self.output.mkdir(parents=True, exist_ok=True)
        started, load = datetime.datetime.now(datetime.timezone.utc), os.getloadavg()[0]
        records: List[Dict[str, Any]] = []
        for name in self.scenes:
            for method in (*self.main_methods, *self.ablations):
                seeds = self.seeds if method in self.main_methods else 1
                for seed in range(self.first_seed, self.first_seed + seeds):
                    records.append(self.run(SCENES[name], method, seed))
                    (self.output / "records.json").write_text(json.dumps(records, indent=1))
        finished = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
        how = f"{started.isoformat(timespec='seconds')} to {finished} (UTC); 1-minute load average {load:.2f} at the "
        report = Report(self, records)
        report.plot(self.output / "speed_accuracy.png")
        lines = report.markdown(how + f"{os.getloadavg()[0]:.2f} at the end")
        text = page("Speed / accuracy benchmark", lines, self.device)
        write_report(text, self.output / "speed_accuracy.md")
        if self.results is not None:
            self.results.mkdir(parents=True, exist_ok=True)
            for path in (self.output / "speed_accuracy.md", self.output / "speed_accuracy.png", *report.views):
                shutil.copyfile(path, self.results / path.name)

    @property
    def base_preset(self) -> str:
        return "gear-nerf" if self.device == "cuda" else "gear-nerf-small"

    def preset_iterations(self) -> int:
        if self.iterations is not None:
            return self.iterations
        from nerfstudio.configs.method_configs import all_methods

        return all_methods[self.base_preset].max_num_iterations

    def run_dir(self, scene: str, method: str, seed: int) -> Path:
        """Where one run's checkpoints, log and record go."""
        return self.output / "runs" / scene / self.base_preset / f"{method}-seed{seed}"

    def train_command(self, scene: Scene, method: str, seed: int) -> List[str]:
        """Arguments of ``ns-train`` for one run."""
        iterations = self.preset_iterations()
        steps_per_save = max(1, iterations // max(1, self.checkpoints))
        return [
            self.base_preset,
            "--output-dir", str(self.output / "runs"), "--experiment-name", scene.name,
            "--timestamp", f"{method}-seed{seed}", "--machine.seed", str(seed),
            "--max-num-iterations", str(iterations),
            *DECAY.format(steps=iterations).split(),
            "--steps-per-save", str(steps_per_save), "--save-only-latest-checkpoint", "False",
            "--steps-per-eval-batch", "0", "--steps-per-eval-image", "0", "--steps-per-eval-all-images", "0",
            "--machine.device-type", self.device, "--vis", "tensorboard",
            "--pipeline.datamanager.sam-cache-dir", str(self.output / "sam-cache"),
            *([] if self.iterations is None else schedule_options(iterations)),
            *method_overrides(method),
            *scene.dataparser(self.output),
        ]  # fmt: skip

    def run(self, scene: Scene, method: str, seed: int) -> Dict[str, Any]:
        """Train one (scene, method, seed) in a child process, then evaluate its checkpoints."""
        command = self.train_command(scene, method, seed)
        run_dir = self.run_dir(scene.name, method, seed)
        record_path = run_dir / "benchmark_record.json"
        if self.report_only:  # a run without a record fails here, naming the missing file
            return json.loads(record_path.read_text())
        shutil.rmtree(run_dir, ignore_errors=True)
        run_dir.mkdir(parents=True)
        print(f"[speed_accuracy] {scene.name} / {method} / {seed}: ns-train {shlex.join(command)}", flush=True)
        timing, _ = timed_train(command, run_dir / "benchmark_timing.json", run_dir / "train.log")
        record = {
            "command": command,
            "scene": scene.name,
            "method": method,
            "seed": seed,
            "iterations": self.preset_iterations(),
            "train_seconds": timing["train_seconds"],
            "train_cpu_seconds": timing["train_cpu_seconds"],
            "views": f"views_{scene.name}_{method}-seed{seed}.png",
        }
        record["checkpoints"] = evaluate_checkpoints(
            run_dir / "config.yml", timing["checkpoints"], self.eval_frames, self.output / record["views"]
        )
        record_path.write_text(json.dumps(record, indent=1))
        return record


CLOCKS: Dict[Clock, str] = {"cpu_seconds": "training CPU time (s)", "seconds": "training time (s)"}
QUALITY = ("PSNR", "PSNR moving", "PSNR rest", "SSIM", "LPIPS")


def quality(points: List[Dict[str, Any]]) -> List[str]:
    """The ``QUALITY`` cells of checkpoints."""
    return [cell(points, key, digits) for key, digits in
            (("psnr", 2), ("psnr_moving", 2), ("psnr_static", 2), ("ssim", 3), ("lpips", 3))]  # fmt: skip


class Report:
    """Tables and plot of a set of run records."""

    def __init__(self, benchmark: SpeedAccuracy, records: List[Dict[str, Any]]) -> None:
        self.benchmark = benchmark
        self.records = records
        self.scenes = list(dict.fromkeys(r["scene"] for r in records))
        self.views = [benchmark.output / r["views"] for r in records if "views" in r]
        """The runs' pictures (``evaluate_checkpoints``)."""
        self.clock: Clock = "cpu_seconds" if benchmark.device == "cpu" else "seconds"
        """The headline clock: CPU time of the training process on the CPU, wall-clock time on CUDA."""

    def runs(self, scene: str, method: str) -> List[Dict[str, Any]]:
        return [r for r in self.records if r["scene"] == scene and r["method"] == method]

    def methods(self, scene: str) -> List[str]:
        return list(dict.fromkeys(r["method"] for r in self.records if r["scene"] == scene))

    def iterations(self, scene: str) -> str:
        """The iteration counts of a scene's runs."""
        return ", ".join(map(str, sorted({r["iterations"] for r in self.records if r["scene"] == scene})))

    def budget(self, scene: str, clock: Clock) -> float:
        """Equal-time budget of a scene on a clock: the shortest mean training time of the main methods."""
        means = [np.mean([r["train_" + clock] for r in self.runs(scene, m)]) for m in self.benchmark.main_methods]
        return float(min(m for m in means if not np.isnan(m)))

    def at_budget(self, scene: str, method: str, clock: Clock) -> List[Optional[Dict[str, Any]]]:
        """Each run's last checkpoint within the scene's budget on the clock (1 ms tolerance), None for none."""
        budget = self.budget(scene, clock)
        return [next((p for p in reversed(r["checkpoints"]) if p[clock] <= budget + 1e-3), None)
                for r in self.runs(scene, method)]  # fmt: skip

    def markdown(self, how: str) -> List[str]:
        b = self.benchmark
        lines = [
            f"Base preset `{b.base_preset}` with its own defaults, device {b.device}; held-out metrics on "
            f"{b.eval_frames} frames of the held-out camera; mean ± sample standard deviation over the n seeds; "
            f"{how}.",
            "",
            *(f"- `{s}`: {SCENES[s].description}; held-out camera {SCENES[s].held_out}; {self.iterations(s)} "
              "iterations per run." for s in self.scenes),
            "",
            "![PSNR against training time](speed_accuracy.png)",
        ]  # fmt: skip
        for clock in ("cpu_seconds", "seconds") if self.clock == "cpu_seconds" else ("seconds",):
            lines += ["", f"## Equal {CLOCKS[clock]}: the main methods' shortest mean", "", *self.equal_time(clock)]
        gains = [self.gain(scene) for scene in self.scenes if {"gear-nerf", "kplanes"} <= set(self.methods(scene))]
        lines += ["", "## Equal iterations", "", *self.equal_iterations(),
                  "", f"## Gear-NeRF minus plain K-Planes, equal {CLOCKS[self.clock]}, paired by seed", "", *gains,
                  "", "## Held-out views at the last checkpoint: ground truth | render | gear map, two frames", "",
                  *(f"![{path.stem}]({path.name})" for path in self.views)]  # fmt: skip
        return lines

    def equal_time(self, clock: Clock) -> List[str]:
        """Each run at its last checkpoint within the scene's budget on this clock."""
        rows = []
        for scene in self.scenes:
            for method in self.methods(scene):
                points = self.at_budget(scene, method, clock)
                cells = ["a run has no checkpoint within the budget"] if None in points else [
                    spread([p["step"] + 1 for p in points], 0), *quality(points)]  # fmt: skip
                rows.append([scene, f"{self.budget(scene, clock):.0f}", METHODS[method][0], len(points), *cells])
        return table(["scene", "budget (s)", "method", "n", "iteration reached", *QUALITY], rows)

    def equal_iterations(self) -> List[str]:
        """Each run at its last checkpoint."""
        rows = []
        for scene in self.scenes:
            for method in self.methods(scene):
                runs = self.runs(scene, method)
                finals = [r["checkpoints"][-1] for r in runs]
                rows.append([
                    scene, METHODS[method][0], len(runs), cell(runs, "train_seconds", 0),
                    cell(runs, "train_cpu_seconds", 0),
                    spread([1000 * r["train_seconds"] / r["iterations"] for r in runs], 0),
                    *quality(finals), cell(finals, "accumulation", 3),
                    cell(finals, "near_layer", 0, 100, " %"), cell(finals, "gear_updates", 0),
                    cell(finals, "moving_at_gear_2", 0, 100, " %"), cell(finals, "static_at_gear_1", 0, 100, " %"),
                ])  # fmt: skip
        header = ["scene", "method", "n", CLOCKS["seconds"], CLOCKS["cpu_seconds"], "ms / iteration", *QUALITY,
                  "accumulation", "near layer", "gear updates", "moving px at gear >= 2", "static px at gear 1"]
        return table(header, rows)

    def gain(self, scene: str) -> str:
        """Gear-NeRF's held-out PSNR minus plain K-Planes' at the scene's headline budget, paired by seed."""
        gear, kplanes = self.at_budget(scene, "gear-nerf", self.clock), self.at_budget(scene, "kplanes", self.clock)
        if None in gear + kplanes:
            return f"- {scene}: a run has no checkpoint within the budget."
        return f"- {scene}: {spread([g['psnr'] - k['psnr'] for g, k in zip(gear, kplanes)], signed=True)} dB"

    def plot(self, path: Path) -> None:
        """Held-out PSNR against training time: one panel per scene, per method the mean over seeds (line) and
        the range (band)."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        columns = min(3, len(self.scenes))
        rows = math.ceil(len(self.scenes) / columns)
        figure, axes = plt.subplots(rows, columns, figsize=(5.5 * columns, 4.2 * rows), squeeze=False)
        for axis, scene in zip(axes.flat, self.scenes):
            for method in self.methods(scene):
                runs = self.runs(scene, method)
                seconds = np.mean([[p[self.clock] for p in r["checkpoints"]] for r in runs], axis=0)
                psnrs = np.array([[p["psnr"] for p in r["checkpoints"]] for r in runs])
                line = axis.plot(seconds, psnrs.mean(axis=0), marker="o", markersize=3,
                                 label=f"{METHODS[method][0]} (n={len(runs)})")[0]
                if len(runs) > 1:
                    axis.fill_between(seconds, psnrs.min(axis=0), psnrs.max(axis=0), color=line.get_color(), alpha=0.15)
            axis.axvline(self.budget(scene, self.clock), color="grey", linestyle="--", linewidth=0.8)
            axis.set_title(f"{scene} ({self.iterations(scene)} iterations)")
            axis.set_xlabel(CLOCKS[self.clock])
            axis.set_ylabel("held-out PSNR (dB)")
            axis.grid(alpha=0.3)
            axis.legend(fontsize=6)
        for axis in list(axes.flat)[len(self.scenes):]:
            axis.set_visible(False)
        b = self.benchmark
        figure.suptitle(f"Held-out PSNR vs training time ({b.base_preset}, {b.device})\nmean over seeds, band: "
                        "min-max; dashed: equal-time budget", fontsize=9)  # two lines: one scene's figure is narrow
        figure.tight_layout()
        figure.savefig(path, dpi=120)
        plt.close(figure)


def spread(values: List[float], digits: int = 2, signed: bool = False) -> str:
    """Mean ± sample standard deviation (just the value for one); ``signed``: with the mean's sign."""
    sign = "+" if signed else ""
    if len(values) == 1:
        return f"{values[0]:{sign}.{digits}f}"
    return f"{np.mean(values):{sign}.{digits}f} ± {np.std(values, ddof=1):.{digits}f}"


def cell(points: List[Dict[str, Any]], key: str, digits: int = 2, scale: float = 1.0, unit: str = "") -> str:
    """``spread`` of a value of runs or checkpoints, times ``scale``; "missing" where one lacks it."""
    values = [p.get(key) for p in points]
    return "missing" if None in values else spread([scale * v for v in values], digits) + unit


def evaluate_checkpoints(
    config_path: Path, checkpoints: List[Dict[str, float]], eval_frames: int, picture: Path
) -> List[Dict[str, Any]]:
    """Held-out metrics and gear shares of each checkpoint of a run, loaded in turn into one pipeline (``eval_setup``,
    test split = held-out camera, SAM features off: the metrics do not use them); ``picture``: the last checkpoint's
    ground truth | render | gear map at the first and middle scored frames."""
    import torch
    from PIL import Image
    from nerfstudio.utils.eval_utils import eval_load_checkpoint, eval_setup

    from gear_nerfstudio.model.metrics import MIN_MSE
    from gear_nerfstudio.model.moving_region import SUMS, region_scores

    def no_sam(config):
        config.pipeline.datamanager.use_sam_features = False
        return config

    config, pipeline, _, _ = eval_setup(config_path, test_mode="test", update_config_callback=no_sam)
    model = pipeline.model
    dataset = pipeline.datamanager.eval_dataset
    frames = evenly_spread(len(dataset), eval_frames)
    results = []
    last = max(entry["step"] for entry in checkpoints)
    for entry in sorted(checkpoints, key=lambda e: e["step"]):
        config.load_step = int(entry["step"])
        eval_load_checkpoint(config, pipeline)
        metrics: Dict[str, List[float]] = {"psnr": [], "ssim": [], "lpips": [], "accumulation": [], "near_layer": []}
        sums = {key: 0.0 for key in SUMS}
        rows = []
        for index in frames:
            outputs = model.get_outputs_for_camera(dataset.cameras[index : index + 1].to(pipeline.device))
            image_metrics, images = model.get_image_metrics_and_images(outputs, dataset[index])
            if entry["step"] == last and index in (frames[0], frames[len(frames) // 2]):
                rows.append(torch.cat([images["img"], images["gear"]], dim=1))
            for name in metrics:
                metrics[name] += [float(image_metrics[name])] if name in image_metrics else []
            for name in SUMS:
                sums[name] += image_metrics[name]
        results.append({
            "step": int(entry["step"]), "seconds": float(entry["seconds"]), "cpu_seconds": float(entry["cpu_seconds"]),
            **{name: float(np.mean(values)) if values else None for name, values in metrics.items()},
            **dict.fromkeys(("psnr_moving", "psnr_static", "moving_at_gear_2", "static_at_gear_1")),
            **region_scores(sums, MIN_MSE),
            "gear_updates": int(pipeline.gear_update_state.num_updates),
        })  # fmt: skip
        print(f"[speed_accuracy]   step {entry['step']:>6}  {entry['seconds']:8.1f} s  PSNR {results[-1]['psnr']:.2f}"
              f"  updates {results[-1]['gear_updates']}", flush=True)
    Image.fromarray((torch.cat(rows).clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)).save(picture)
    return results
