"""Speed / accuracy: Gear-NeRF against plain K-Planes and one-change variants (``METHODS``), on real captures
(``SCENES``), with seeds; held-out PSNR / SSIM / LPIPS, moving-region PSNR and gear shares
(``gear_nerfstudio.model.moving_region``, as ns-eval), render FPS, samples per ray, parameters and peak RSS at every
checkpoint; scored at equal iterations and at equal training time (CPU seconds of a single-threaded training process
on the CPU, wall-clock on CUDA). Writes ``<output>/speed_accuracy.md``, ``.png`` and ``records.json``
(``benchmarks/results/speed_accuracy.md`` says how it was run)."""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import re
import shlex
import shutil
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import numpy as np
import tyro

from benchmarks.common import REAL, contact_sheet, page, table, timed, timed_train, write_report
from gear_nerfstudio.method_configs.gear_nerf import schedule_options

Clock = Literal["seconds", "cpu_seconds"]
"""A checkpoint's training time: wall-clock or CPU seconds of the training process."""

LR = " ".join(f"--optimizers.{group}.optimizer.lr 0.01" for group in ("fields", "proposal-networks", "gear-field"))
DECAY = " ".join(f"--optimizers.{group}.scheduler.max-steps {{steps}}" for group in ("fields", "proposal-networks"))
METHODS: Dict[str, Tuple[str, str]] = {
    "gear-nerf": ("Gear-NeRF", ""),
    "kplanes": ("plain K-Planes (N_gear = 1) with L_SAM", "--pipeline.model.num-gears 1"),
    "no-split": ("Gear-NeRF w/o split sampling", "--pipeline.model.split-base 1"),
    "random-background": ("Gear-NeRF trained on a random background colour (transparency costs loss)",
                          "--pipeline.model.background-color random"),
    "lr-0.01": ("Gear-NeRF at learning rate 0.01 (K-Planes') instead of 0.02", LR),
    "rays-2048": ("Gear-NeRF on 2,048 rays per batch instead of 1,024",
                  "--pipeline.datamanager.train-num-rays-per-batch 2048"),
    "initial-density": ("Gear-NeRF starting from density 2 per scene unit instead of about 0.37",
                        "--pipeline.model.initial-density 2"),
    "contraction": ("Gear-NeRF with space beyond the scene box contracted (far plane 1,000, as nerfacto)",
                    "--pipeline.model.unbounded True --pipeline.model.far-plane 1000"),
    "samples-16": ("Gear-NeRF with 16 base samples per ray instead of 24", "--pipeline.model.num-samples 16"),
    "samples-16-rays-768": ("Gear-NeRF with 16 base samples per ray and 768 rays per batch",
                            "--pipeline.model.num-samples 16 --pipeline.datamanager.train-num-rays-per-batch 768"),
    "proposal-warmup": ("Gear-NeRF with the proposal networks' update warm-up at 1/6 of the run (K-Planes' ratio)",
                        "--pipeline.model.proposal.warmup {sixth}"),
    "gear-rows-1": ("Gear-NeRF with a gear function constant in time (k' of 1 row)",
                    "--pipeline.model.gear-time-resolution 1"),
    "gear-rows-4": ("Gear-NeRF with a gear function of 4 rows in time (k')", "--pipeline.model.gear-time-resolution 4"),
    "gear-1-static": ("Gear-NeRF whose gear 1 has one row in time (Sec 4.4, the paper) instead of the presets' T/4",
                      "--pipeline.model.gear1-row-fraction 0"),
    "gear-rows-all": ("Gear-NeRF whose every gear has T rows in time (no gear is static) instead of T/4 to T",
                      "--pipeline.model.gear1-row-fraction 1"),
    "lr-half-decay": ("Gear-NeRF whose learning rates follow the cosine schedule of a run twice as long (end at half)",
                      DECAY.replace("{steps}", "{double}")),
    "views-every-frame": ("Gear-NeRF whose updates render a view at every frame (loss maps of 64 pixels) instead of 4",
                          "--pipeline.gear-updates.views-per-update {frames} --pipeline.gear-updates.loss-map-size 64 "
                          "--pipeline.gear-updates.patch-size 4"),
    "resolutions-64-128": ("Gear-NeRF with planes of 64 and 128 cells instead of 32 and 64",
                           "--pipeline.model.resolutions 64 128"),
    "time-smoothness-1e-4": ("Gear-NeRF with the time-smoothness weight at 1e-4 instead of 1e-3",
                             "--pipeline.model.losses.time-smoothness 1e-4"),
}
"""Method keys: (label in the tables and the plot, ns-train overrides on the base preset; ``method_overrides``)."""


def method_overrides(method: str, frames: int, iterations: int) -> List[str]:
    """``ns-train`` overrides of a method for a run of ``iterations`` on ``frames`` frames."""
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    return METHODS[method][1].format(frames=frames, sixth=max(1, iterations // 6), double=2 * iterations).split()


@dataclasses.dataclass(frozen=True)
class Scene:
    """A real capture as ns-train reads it, and its held-out camera."""

    name: str
    description: str
    frames: int
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
        Scene("panoptic", "real: CMU Panoptic basketball, 320x180, 16 cameras (15 trained), 20 frames", 20, "06",
              REAL / "panoptic_basketball", "technicolor-data",
              ("--near", "0.3", "--far", "7", "--moving-masks", str(REAL / "panoptic_basketball_masks"))),
        Scene("panoptic-video", f"{LAYOUT}, 304x168 (downscale 2), 31 cameras (30 trained), frames 0-29", 30, "cam00",
              VIDEO, parser_options=("--downscale-factor", "2", "--frame-count", "30")),
        Scene("panoptic-video-60", f"{LAYOUT}, 304x168 (downscale 2), 31 cameras (30 trained), frames 60-89 (no "
              "default was chosen on them), held-out cam20 with person masks", 30, "cam20", VIDEO,
              parser_options=("--downscale-factor", "2", "--frame-start", "60", "--frame-count", "30",
                              "--moving-masks", VIDEO_MASKS)),
        Scene("panoptic-video-full", f"{LAYOUT} at full size, 608x336, 31 cameras (30 trained), all 90 frames (for "
              "the GPU)", 90, "cam00", VIDEO),
        Scene("panoptic-video-full-30", f"{LAYOUT} at full size, 608x336, 31 cameras (30 trained), frames 0-29, "
              "held-out cam20 with person masks (for the GPU)", 30, "cam20", VIDEO,
              parser_options=("--frame-count", "30", "--moving-masks", VIDEO_MASKS)),
        Scene("flame-steak", "real: Neural 3D Video flame_steak, frame 0 only, 336x252 (downscale 2), 21 "
              "forward-facing cameras (20 trained)", 1, "cam00", REAL / "n3d_flame_steak_frame0",
              parser_options=("--downscale-factor", "2")),
    )
}  # fmt: skip
"""Scenes by name. ``panoptic`` holds out camera 06 (not the usual 10) because 10 has no masks; ``panoptic-video``
holds out cam00, the parser's default and the view published methods hold out, which has none (its moving region
is the held-out view's colour change); ``panoptic-video-60`` is the window of the same capture that no default was
chosen on, held out at cam20, which has masks."""


@dataclasses.dataclass
class SpeedAccuracy:
    """Train and evaluate Gear-NeRF, plain K-Planes and variants (``METHODS``) on ``SCENES``; tables and a plot."""

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
                method_overrides(method, SCENES[name].frames, self.preset_iterations())  # fail early on an unknown name
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
        pictures = report.pictures(self.output)
        report.plot(self.output / "speed_accuracy.png")
        lines = report.markdown(how + f"{os.getloadavg()[0]:.2f} at the end", pictures)
        text = page("Speed / accuracy benchmark", lines, self.device)
        write_report(text, self.output / "speed_accuracy.md")
        if self.results is not None:
            self.results.mkdir(parents=True, exist_ok=True)
            for path in (self.output / "speed_accuracy.md", self.output / "speed_accuracy.png", *pictures):
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
        """Where one run's checkpoints, log, record and pictures go."""
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
            *method_overrides(method, scene.frames, iterations),
            *scene.dataparser(self.output),
        ]  # fmt: skip

    def run(self, scene: Scene, method: str, seed: int) -> Dict[str, Any]:
        """Train one (scene, method, seed) in a child process, then evaluate its checkpoints."""
        command = self.train_command(scene, method, seed)
        run_dir = self.run_dir(scene.name, method, seed)
        record_path = run_dir / "benchmark_record.json"
        if self.report_only:
            if not record_path.is_file():
                raise FileNotFoundError(f"{record_path}: no record of {scene.name} / {method} / {seed} to report")
            return json.loads(record_path.read_text())
        shutil.rmtree(run_dir, ignore_errors=True)
        run_dir.mkdir(parents=True)
        print(f"[speed_accuracy] {scene.name} / {method} / {seed}: ns-train {shlex.join(command)}", flush=True)
        timing, usage = timed_train(command, run_dir / "benchmark_timing.json", run_dir / "train.log", True)
        record = {
            "command": command,
            "scene": scene.name,
            "method": method,
            "seed": seed,
            "iterations": self.preset_iterations(),
            "train_seconds": timing["train_seconds"],
            "train_cpu_seconds": timing["train_cpu_seconds"],
            "setup_seconds": timing["setup_seconds"],
            "peak_rss_mib": usage.ru_maxrss / 1024.0,  # Linux: KiB
            "peak_cuda_mib": timing.get("peak_cuda_mib"),
            "before_first_update": timing.get("before_first_update"),
            "update_reviews": update_reviews((run_dir / "train.log").read_text()),
            "checkpoints": evaluate_checkpoints(
                run_dir / "config.yml", timing["checkpoints"], self.eval_frames, run_dir
            ),
        }
        record_path.write_text(json.dumps(record, indent=1))
        return record


CLOCKS: Dict[Clock, str] = {"cpu_seconds": "training CPU time (s)", "seconds": "training time (s)"}
QUALITY = ("PSNR", "PSNR moving", "PSNR rest", "SSIM", "LPIPS")


def quality(points: List[Dict[str, Any]]) -> List[str]:
    """The ``QUALITY`` cells of checkpoints."""
    return [cell(points, key, digits) for key, digits in
            (("psnr", 2), ("psnr_moving", 2), ("psnr_static", 2), ("ssim", 3), ("lpips", 3))]  # fmt: skip


class Report:
    """Tables, plot and pictures of a set of run records."""

    def __init__(self, benchmark: SpeedAccuracy, records: List[Dict[str, Any]]) -> None:
        self.benchmark = benchmark
        self.records = records
        self.scenes = list(dict.fromkeys(r["scene"] for r in records))
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

    def markdown(self, how: str, pictures: List[Path]) -> List[str]:
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
                  "", "## What each gear update did (at its review)", "", *self.reviews_table(),
                  "", "## Pictures", "", *(f"![{path.stem}]({path.name})" for path in pictures)]  # fmt: skip
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
                    *quality(finals), before_first_update(runs), cell(finals, "accumulation", 3),
                    cell(finals, "near_layer", 0, 100, " %"), cell(finals, "gear_updates", 0),
                    cell(finals, "moving_at_gear_2", 0, 100, " %"), cell(finals, "static_at_gear_1", 0, 100, " %"),
                    cell(finals, "samples_per_ray", 1), cell(finals, "fps"),
                    f"{finals[0]['parameters']:,} ({finals[0]['parameters_in_use']:,})", cell(runs, "peak_rss_mib", 0),
                ])  # fmt: skip
        header = ["scene", "method", "n", CLOCKS["seconds"], CLOCKS["cpu_seconds"], "ms / iteration", *QUALITY,
                  "PSNR just before the first gear update", "accumulation", "near layer", "gear updates",
                  "moving px at gear >= 2", "static px at gear 1", "samples / ray", "render FPS", "parameters (in use)",
                  "peak RSS (MiB)"]  # fmt: skip
        return table(header, rows)

    def gain(self, scene: str) -> str:
        """Gear-NeRF's held-out PSNR minus plain K-Planes' at the scene's headline budget, paired by seed."""
        gear, kplanes = self.at_budget(scene, "gear-nerf", self.clock), self.at_budget(scene, "kplanes", self.clock)
        if None in gear + kplanes:
            return f"- {scene}: a run has no checkpoint within the budget."
        return f"- {scene}: {spread([g['psnr'] - k['psnr'] for g, k in zip(gear, kplanes)], signed=True)} dB"

    def reviews_table(self) -> List[str]:
        """What each gear update did, as the guard measured it at its review (``GearUpdater.review``, L epochs
        later): the change of its training views' PSNR and of the held-out view's at the same times; undone ones."""
        rows = []
        for scene in self.scenes:
            for method in self.methods(scene):
                reviews = [v for r in self.runs(scene, method) for v in r.get("update_reviews", [])]
                for update in sorted({v["update"] for v in reviews}):
                    done = [v for v in reviews if v["update"] == update]
                    held = [v["held_out_after"] - v["held_out_before"] for v in done if v["held_out_after"] is not None]
                    rows.append([
                        scene, METHODS[method][0], len(done), update, spread([v["step"] for v in done], 0),
                        spread([v["views_after"] - v["views_before"] for v in done], 2, True),
                        spread(held, 2, True) if held else "n/a", sum(not v["kept"] for v in done),
                    ])  # fmt: skip
        header = ["scene", "method", "n", "update", "reviewed at step", "its views (dB)", "held-out view (dB)"]
        return table([*header, "undone"], rows)

    def pictures(self, folder: Path) -> List[Path]:
        """Per scene, the held-out view at two times (rows): ground truth, Gear-NeRF, plain K-Planes and Gear-NeRF's
        gear map, from the first seed's last checkpoint; one PNG per scene."""
        written = []
        for scene in self.scenes:
            runs = {m: self.runs(scene, m) for m in ("gear-nerf", "kplanes")}
            if not all(runs.values()):
                continue
            gear, kplanes = (self.benchmark.run_dir(scene, m, min(r["seed"] for r in rs)) for m, rs in runs.items())
            path = folder / f"speed_accuracy_{scene}.png"
            columns = [("ground truth", gear, "truth"), ("Gear-NeRF", gear, "render")]
            columns += [("plain K-Planes (one gear)", kplanes, "render"), ("Gear-NeRF gear map", gear, "gear")]
            views_sheet(columns).save(path)
            written.append(path)
        return written

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


def before_first_update(runs: List[Dict[str, Any]]) -> str:
    """``spread`` of the held-out PSNR at each run's checkpoint just before its first gear update."""
    steps = [(r["checkpoints"], r.get("before_first_update")) for r in runs]
    values = [next(p["psnr"] for p in points if p["step"] == step) for points, step in steps if step is not None]
    return spread(values) if values else "n/a"


def evaluate_checkpoints(
    config_path: Path,
    checkpoints: List[Dict[str, float]],
    eval_frames: int,
    pictures: Path,
) -> List[Dict[str, Any]]:
    """Held-out metrics (PSNR, SSIM, LPIPS when local, accumulation, near layer), gear maps, render speed, samples per
    ray and parameters of each checkpoint of a run; the last checkpoint's renders of two scored frames (ground truth,
    render, gear map) go to ``pictures`` as PNG files.

    The pipeline is set up once (nerfstudio's ``eval_setup``, test split = held-out camera, SAM features off:
    the metrics do not use them); each checkpoint is then loaded into it with ``eval_load_checkpoint``.
    """
    from PIL import Image

    import torch
    from nerfstudio.utils.eval_utils import eval_load_checkpoint, eval_setup

    from gear_nerfstudio.model.metrics import MIN_MSE
    from gear_nerfstudio.model.moving_region import SUMS, region_scores

    def no_sam(config):
        config.pipeline.datamanager.use_sam_features = False
        return config

    config, pipeline, _, _ = eval_setup(config_path, test_mode="test", update_config_callback=no_sam)
    model = pipeline.model
    dataset = pipeline.datamanager.eval_dataset
    frames = sorted({int(round(i)) for i in np.linspace(0, len(dataset) - 1, min(eval_frames, len(dataset)))})
    cuda = torch.device(pipeline.device).type == "cuda"

    def render(index: int) -> Dict[str, Any]:
        with model.rendering("num_samples"):
            return model.get_outputs_for_camera(dataset.cameras[index : index + 1].to(pipeline.device))

    render(frames[0])  # warm-up, untimed
    results = []
    for entry in sorted(checkpoints, key=lambda e: e["step"]):
        config.load_step = int(entry["step"])
        eval_load_checkpoint(config, pipeline)
        metrics: Dict[str, List[float]] = {"psnr": [], "ssim": [], "lpips": [], "accumulation": [], "near_layer": []}
        last = entry["step"] == max(e["step"] for e in checkpoints)
        render_seconds, samples, pixels = 0.0, 0.0, 0
        sums = {key: 0.0 for key in SUMS}
        for index in frames:
            seconds, outputs = timed(lambda: render(index), 1, torch.cuda.synchronize if cuda else lambda: None)
            render_seconds += seconds
            image_metrics, _ = model.get_image_metrics_and_images(outputs, dataset[index])
            for name in metrics:
                metrics[name] += [float(image_metrics[name])] if name in image_metrics else []
            for name in SUMS:
                sums[name] += image_metrics[name]
            samples += float(outputs["num_samples"].sum())
            pixels += outputs["num_samples"].numel()
            if last and index in (frames[0], frames[len(frames) // 2]):
                truth = dataset[index]["image"][..., :3]
                for name, image in (("truth", truth), ("render", outputs["rgb"]), ("gear", outputs["gear"])):
                    pixels_uint8 = (image.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
                    Image.fromarray(pixels_uint8).save(pictures / f"held_out_{index:04d}_{name}.png")
        total = sum(p.numel() for p in model.parameters())
        unused = sum(p.numel() for p in model.field.parameters()) - model.field.parameters_in_use()
        results.append({
            "step": int(entry["step"]), "seconds": float(entry["seconds"]), "cpu_seconds": float(entry["cpu_seconds"]),
            **{name: float(np.mean(values)) if values else None for name, values in metrics.items()},
            "fps": len(frames) / render_seconds, "samples_per_ray": samples / pixels,
            **dict.fromkeys(("psnr_moving", "psnr_static", "moving_at_gear_2", "static_at_gear_1")),
            **region_scores(sums, MIN_MSE),
            "gear_updates": int(pipeline.gear_update_state.num_updates),
            "parameters": int(total), "parameters_in_use": int(total - unused),
        })  # fmt: skip
        print(f"[speed_accuracy]   step {entry['step']:>6}  {entry['seconds']:8.1f} s  PSNR {results[-1]['psnr']:.2f}"
              f"  samples/ray {results[-1]['samples_per_ray']:.1f}  updates {results[-1]['gear_updates']}", flush=True)
    del pipeline, model
    return results


REVIEW = re.compile(
    r"Gear update (\d+) reviewed at step (\d+): its views ([\d.]+) -> ([\d.]+) dB"
    r"(?:, held-out view ([\d.]+) -> ([\d.]+) dB)?(?:.*?)(kept|undone)"
)
"""The guard's review of an update in a training log (``GearUpdater.review``), unwrapped."""


def update_reviews(log: str) -> List[Dict[str, Any]]:
    """Each gear update's review from a training log: its views' PSNR before it and at the review, the held-out
    view's at the same times (None when not measured), and whether it was kept."""
    text = " ".join(re.sub(r"\S+\.py:\d+", " ", log).split())  # rich's log lines, unwrapped
    return [
        {
            "update": int(m[1]), "step": int(m[2]), "views_before": float(m[3]), "views_after": float(m[4]),
            "held_out_before": None if m[5] is None else float(m[5]),
            "held_out_after": None if m[6] is None else float(m[6]), "kept": m[7] == "kept",
        }
        for m in REVIEW.finditer(text)
    ]  # fmt: skip


def views_sheet(columns: List[Tuple[str, Path, str]], crop: Optional[Tuple[int, int, int, int]] = None):
    """Contact sheet of run folders' ``held_out_<frame>_<kind>.png``: one row per held-out frame of the first
    column's folder, one column per (label, folder, kind); ``crop``: only that box, enlarged twice."""
    from PIL import Image

    stems = sorted({f.name.rsplit("_", 1)[0] for f in columns[0][1].glob("held_out_*_truth.png")})
    if not stems:
        raise SystemExit(f"error: {columns[0][1]} has no held_out_*_truth.png (a speed-accuracy run folder has them)")
    rows = [[Image.open(folder / f"{stem}_{kind}.png") for _, folder, kind in columns] for stem in stems]
    if crop is not None:
        size = (2 * (crop[2] - crop[0]), 2 * (crop[3] - crop[1]))
        rows = [[tile.crop(crop).resize(size, Image.NEAREST) for tile in row] for row in rows]
    return contact_sheet([label for label, _, _ in columns], rows)


@dataclasses.dataclass
class CompareViews:
    """Held-out views of speed-accuracy runs side by side (the pictures beside the quality tables): the first run's
    ground truth, each run's render, then the gear maps of the runs named in ``--gear-maps``."""

    output: tyro.conf.Positional[Path]
    """The PNG to write."""
    runs: tyro.conf.Positional[Tuple[str, ...]]
    """``label=run folder`` each."""
    gear_maps: Tuple[str, ...] = ()
    """Labels of the runs whose gear maps are shown."""
    crop: Optional[Tuple[int, int, int, int]] = None
    """left top right bottom: only that box of every view (held-out pixels), enlarged twice."""

    def main(self) -> None:
        folders = {label: Path(folder) for label, folder in (run.split("=", 1) for run in self.runs)}
        first = next(iter(folders.values()))
        columns = [("ground truth", first, "truth"), *((label, folder, "render") for label, folder in folders.items())]
        columns += [(f"{label} gear map", folders[label], "gear") for label in self.gear_maps]
        views_sheet(columns, self.crop).save(self.output)
        print(self.output)
