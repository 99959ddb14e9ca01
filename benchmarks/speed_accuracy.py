"""Speed / accuracy benchmark: Gear-NeRF against its baselines and ablations, at several scene sizes and on
real multi-view video, with seeds.

One command trains and evaluates every (scene, method, seed), one run after the other on this machine:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/speed_accuracy.py --output outputs/speed_accuracy --results benchmarks/results

Scenes (``SCENES``): synthetic scenes with ground truth (``gear_nerfstudio.tools.synthetic``, Neural 3D Video format,
held-out camera cam00; moving pixels from the ground-truth motion) at two sizes, and the real capture
``panoptic_basketball`` (Technicolor layout, held-out camera 06, which has foreground masks of the moving
people; ``../shared/data/real/SOURCES.md``).

Methods (``METHODS``), all ``ns-train <preset> <overrides>`` on the same base preset (``gear-nerf-small`` on
the CPU, ``gear-nerf`` with ``--device cuda``) with the same data, iterations, batch and losses, except the one
thing each changes:

* ``gear-nerf``: the preset (N_gear = 4, gear updates, split sampling, L_SAM).
* ``kplanes``: N_gear = 1 (plain K-Planes: one volume with one row per frame, n uniform samples), with L_SAM as
  Gear-NeRF: the main baseline.
* ablations: ``no-split`` (gears and updates, but no extra samples: split base 1), ``no-updates`` (no gear
  update: every point stays in gear 1), ``gear-nerf-no-sam`` and ``kplanes-no-sam`` (no L_SAM; the upshift
  masks still come from the SAM decoder on the ground-truth frames' embeddings), and the paper's
  baselines ``uniform-128``, ``naive-medium`` and ``no-embedding`` (see ``method_overrides``).

Seeds: ``--seeds`` seeds (``--machine.seed`` 42, 43, ...) for ``--main-methods``, one seed for the others.

What is measured, and how:

* Training: each run is a child process running nerfstudio's ``ns-train`` entry point, with the evaluation
  inside the training loop turned off and a checkpoint every ``iterations / checkpoints`` steps. The child
  records, at each checkpoint, the training time since ``Trainer.train`` started, minus the time spent
  writing earlier checkpoints (data loading, SAM encoding and set-up are not counted; gear updates are), in
  wall-clock seconds and in CPU seconds of the training process.
* Held-out metrics, per checkpoint: ``--eval-frames`` frames of the held-out camera, evenly spaced over the
  video, rendered with ``model.get_outputs_for_camera`` and scored with the model's
  ``get_image_metrics_and_images`` (PSNR, SSIM; LPIPS only when its weights are on disk, else "missing").
* Gear maps, per checkpoint: ``model.visible_gear_levels`` (Eq 5 at the surface each pixel sees) on the same
  frames: the share of moving pixels at gear >= 2 and of static pixels at gear 1 (synthetic: ground-truth
  motion > 0; real: the foreground masks).
* Render FPS, samples per ray, parameters (all, and in use), gear updates run (from the checkpoint), peak RSS.
* Equal iterations: the last checkpoint. Equal training time (the headline): per scene, a time budget (the
  shortest mean total training time of the main methods, or ``--time-budget``); each run is scored at its
  last checkpoint within the budget. On the CPU the headline clock is the CPU time of the training process
  (run it single-threaded, ``OMP_NUM_THREADS=1``: then it equals the wall-clock time of an idle machine and
  does not depend on what else the machine runs); the wall-clock table follows. On CUDA the headline is the
  wall-clock time. Means and sample standard deviations are over seeds.

Writes ``<output>/speed_accuracy.md`` (tables, targets, command, machine, date), ``<output>/speed_accuracy.png``
(PSNR against training time per scene, mean and range over seeds) and ``<output>/records.json``; with
``--results DIR`` the markdown and the plot are copied there too. ``--report-only`` writes them from the run
records already in the output folder (from one or several earlier invocations), without training.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
import math
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Literal, Optional, Tuple

import numpy as np
import tyro

from environment import command_environment
from gear_nerfstudio.method_configs.gear_nerf import schedule_options

TRAIN_CHILD = "_train"
"""First argument of the child process that runs ``ns-train`` with the timing hooks."""

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
"""The real captures (``../shared/data/real`` next to the repository)."""

Clock = Literal["seconds", "cpu_seconds"]
"""A checkpoint's training time: wall-clock or CPU seconds of the training process."""

METHODS: Dict[str, str] = {
    "gear-nerf": "Gear-NeRF",
    "kplanes": "plain K-Planes (N_gear = 1) with L_SAM",
    "no-split": "Gear-NeRF w/o split sampling",
    "no-updates": "Gear-NeRF w/o gear updates",
    "gear-nerf-no-sam": "Gear-NeRF w/o L_SAM",
    "kplanes-no-sam": "plain K-Planes w/o L_SAM",
    "uniform-128": "K-Planes, 128 uniform samples, with L_SAM",
    "naive-medium": "naive temporal, medium (T/2 rows), with L_SAM",
    "no-embedding": "Gear-NeRF w/o embedding (loss-threshold masks, no L_SAM)",
}
"""Method keys and their labels in the tables and the plot."""


def method_overrides(method: str, frames: int) -> List[str]:
    """``ns-train`` overrides of a method on top of the base preset."""
    no_sam = ["--pipeline.datamanager.use-sam-features", "False", "--pipeline.gear-updates.sam-loss-weight", "0"]
    single = ["--pipeline.model.num-gears", "1"]
    overrides = {
        "gear-nerf": [],
        "kplanes": single,
        "no-split": ["--pipeline.model.split-base", "1"],
        "no-updates": ["--pipeline.gear-updates.enabled", "False"],
        "gear-nerf-no-sam": no_sam,
        "kplanes-no-sam": [*single, *no_sam],
        "uniform-128": [*single, "--pipeline.model.num-samples", "128"],
        "naive-medium": [*single, "--pipeline.model.time-resolutions", str(max(1, math.ceil(frames / 2)))],
        "no-embedding": [*no_sam, "--pipeline.gear-updates.mask-source", "loss_threshold"],
    }
    if method not in overrides:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    return overrides[method]


@dataclasses.dataclass(frozen=True)
class Scene:
    """A benchmark scene: how ns-train reads it and which held-out pixels move."""

    name: str
    description: str
    frames: int
    held_out: str
    synthetic: Optional[Dict[str, Any]] = None
    """SyntheticSpec fields of a generated scene (written under <output>/scenes/<name>); None: real."""
    data: Optional[Path] = None
    """A real capture in the Technicolor layout."""
    masks: Optional[Path] = None
    """Foreground masks of a real capture: <camera>/<frame:05d>.png."""
    parser_options: Tuple[str, ...] = ()

    def folder(self, output: Path) -> Path:
        return output / "scenes" / self.name if self.synthetic else self.data

    def write(self, output: Path) -> None:
        """Generate a synthetic scene (kept when one of the same spec is there)."""
        if not self.synthetic:
            return
        from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene

        spec = SyntheticSpec(dataset="n3d", **self.synthetic)
        scene = self.folder(output)
        info = scene / "ground_truth" / "scene.json"
        if info.is_file() and json.loads(info.read_text())["spec"] == json.loads(json.dumps(spec.__dict__)):
            return
        for stale in (scene, output / "cache" / self.name):
            shutil.rmtree(stale, ignore_errors=True)
        write_synthetic_scene(scene, spec)

    def dataparser(self, output: Path) -> List[str]:
        parser = "neural-3d-video-data" if self.synthetic else "technicolor-data"
        return [
            parser, "--data", str(self.folder(output)), "--held-out-camera", self.held_out,
            "--cache-dir", str(output / "cache" / self.name), *self.parser_options,
        ]

    def moving(self, output: Path) -> Callable[[int, int], np.ndarray]:
        """(frame index in the window, dataset frame number) -> (H, W) bool map of the held-out camera's moving
        pixels."""
        if self.synthetic:
            motion = np.load(self.folder(output) / "ground_truth" / f"{self.held_out}.npz")["motion"]
            return lambda index, number: motion[index] > 0
        from PIL import Image

        return lambda index, number: (
            np.array(Image.open(self.masks / self.held_out / f"{number:05d}.png").convert("L")) > 127
        )


SCENES: Dict[str, Scene] = {
    "mixed": Scene(
        "mixed", "synthetic, 64x48, 6 cameras, 6 frames: textured static room, a static, a slow and a fast sphere",
        6, "cam00", synthetic=dict(width=64, height=48, frames=6, cameras=6, motion="mixed"),
    ),
    "mixed-large": Scene(
        "mixed-large", "synthetic, 160x120, 12 cameras, 24 frames: the same content", 24, "cam00",
        synthetic=dict(width=160, height=120, frames=24, cameras=12, motion="mixed"),
    ),
    "static": Scene(
        "static", "synthetic, 64x48, 6 cameras, 6 frames, nothing moves", 6, "cam00",
        synthetic=dict(width=64, height=48, frames=6, cameras=6, motion="static"),
    ),
    "panoptic": Scene(
        "panoptic", "real: CMU Panoptic basketball, 320x180, 16 cameras (15 trained), 20 frames", 20, "06",
        data=REAL / "panoptic_basketball", masks=REAL / "panoptic_basketball_masks",
        parser_options=("--near", "0.3", "--far", "7"),
    ),
}
"""Scenes by name. The real capture holds out camera 06 (not the usual 10) because 10 has no masks."""


@dataclasses.dataclass
class SpeedAccuracyBenchmark:
    """Train and evaluate Gear-NeRF, its baseline and ablations; write tables and a plot."""

    output: Path = Path("outputs/speed_accuracy")
    """Working folder: scenes, runs, logs, records.json, speed_accuracy.md / .png."""
    results: Optional[Path] = None
    """Also copy speed_accuracy.md and speed_accuracy.png here (e.g. benchmarks/results)."""
    scenes: Tuple[str, ...] = ("mixed", "mixed-large", "panoptic")
    """Scenes to run (``SCENES``)."""
    main_methods: Tuple[str, ...] = ("gear-nerf", "kplanes")
    """Methods run with every seed; the equal-time budget is the shortest of their mean training times."""
    ablations: Tuple[str, ...] = ("no-split", "no-updates", "gear-nerf-no-sam", "kplanes-no-sam")
    """Methods run with the first seed only."""
    ablation_scenes: Tuple[str, ...] = ("mixed", "panoptic")
    """Scenes on which the ablations run."""
    seeds: int = 3
    """Seeds of the main methods (``--machine.seed`` 42, 43, ...)."""
    iterations: Optional[int] = None
    """Training iterations of every run, with the gear-update schedule scaled to them as the presets scale theirs
    (``schedule_options``); default: the base preset's own, with its own schedule."""
    checkpoints: int = 8
    """Evaluated checkpoints per run, evenly spaced (the last is the final one)."""
    eval_frames: int = 6
    """Held-out frames scored per checkpoint, evenly spaced over the video (all when the video is shorter)."""
    device: Literal["cpu", "cuda"] = "cpu"
    """cpu: the CPU preset gear-nerf-small; cuda: the paper preset gear-nerf."""
    preset: Optional[str] = None
    """Base preset; default gear-nerf-small on cpu, gear-nerf on cuda."""
    time_budget: Optional[float] = None
    """Equal-time budget in seconds for every scene; default per scene (see ``main_methods``)."""
    reuse_runs: bool = False
    """Skip training a run whose record (same command) is already in the output folder."""
    report_only: bool = False
    """Train nothing: write the tables and plot from the records of every planned run in the output folder."""

    def main(self) -> None:
        if self.device == "cpu":
            os.environ["CUDA_VISIBLE_DEVICES"] = ""  # the held-out renders run on the CPU as well
        for name in self.scenes:
            if name not in SCENES:
                raise ValueError(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
            for method in (*self.main_methods, *self.ablations):
                method_overrides(method, SCENES[name].frames)  # fail early on an unknown name
        self.output.mkdir(parents=True, exist_ok=True)
        started = datetime.datetime.now(datetime.timezone.utc)
        load_before = os.getloadavg()
        records: List[Dict[str, Any]] = []
        for name in self.scenes:
            scene = SCENES[name]
            if not self.report_only:
                scene.write(self.output)
            ablations = self.ablations if name in self.ablation_scenes else ()
            for method in (*self.main_methods, *ablations):
                for seed in range(42, 42 + (self.seeds if method in self.main_methods else 1)):
                    records.append(self.run(scene, method, seed))
                    (self.output / "records.json").write_text(json.dumps(records, indent=1))
        finished = datetime.datetime.now(datetime.timezone.utc)
        context = {
            "command": "python benchmarks/speed_accuracy.py " + shlex.join(sys.argv[1:]),
            "started": started.isoformat(timespec="seconds"),
            "finished": finished.isoformat(timespec="seconds"),
            "machine": machine_description(self.device),
            "load": f"1-minute load average {load_before[0]:.2f} at the start, {os.getloadavg()[0]:.2f} at the end",
        }
        markdown = Report(self, records).markdown(context)
        (self.output / "speed_accuracy.md").write_text(markdown)
        Report(self, records).plot(self.output / "speed_accuracy.png")
        print(markdown)
        if self.results is not None:
            self.results.mkdir(parents=True, exist_ok=True)
            for name in ("speed_accuracy.md", "speed_accuracy.png"):
                shutil.copyfile(self.output / name, self.results / name)
            print(f"[speed_accuracy] wrote {self.results / 'speed_accuracy.md'} and speed_accuracy.png")

    @property
    def base_preset(self) -> str:
        return self.preset or ("gear-nerf" if self.device == "cuda" else "gear-nerf-small")

    def preset_iterations(self) -> int:
        if self.iterations is not None:
            return self.iterations
        from nerfstudio.configs.method_configs import all_methods

        return all_methods[self.base_preset].max_num_iterations

    def train_command(self, scene: Scene, method: str, seed: int) -> List[str]:
        """Arguments of ``ns-train`` for one run."""
        iterations = self.preset_iterations()
        steps_per_save = max(1, iterations // max(1, self.checkpoints))
        return [
            self.base_preset,
            "--output-dir", str(self.output / "runs"), "--experiment-name", scene.name,
            "--timestamp", f"{method}-seed{seed}", "--machine.seed", str(seed),
            "--max-num-iterations", str(iterations),
            "--optimizers.fields.scheduler.max-steps", str(iterations),
            "--optimizers.proposal-networks.scheduler.max-steps", str(iterations),
            "--steps-per-save", str(steps_per_save), "--save-only-latest-checkpoint", "False",
            "--steps-per-eval-batch", "0", "--steps-per-eval-image", "0", "--steps-per-eval-all-images", "0",
            "--machine.device-type", self.device, "--vis", "tensorboard",
            "--pipeline.datamanager.sam-cache-dir", str(self.output / "sam-cache"),
            *([] if self.iterations is None else schedule_options(iterations)),
            *method_overrides(method, scene.frames),
            *scene.dataparser(self.output),
        ]  # fmt: skip

    def run(self, scene: Scene, method: str, seed: int) -> Dict[str, Any]:
        """Train one (scene, method, seed) in a child process, then evaluate its checkpoints."""
        command = self.train_command(scene, method, seed)
        run_dir = self.output / "runs" / scene.name / self.base_preset / f"{method}-seed{seed}"
        record_path = run_dir / "benchmark_record.json"
        if self.report_only:
            if not record_path.is_file():
                raise FileNotFoundError(f"{record_path}: no record of {scene.name} / {method} / {seed} to report")
            return json.loads(record_path.read_text())
        if self.reuse_runs and record_path.is_file():
            record = json.loads(record_path.read_text())
            if record.get("command") == command:
                print(f"[speed_accuracy] {scene.name} / {method} / {seed}: reusing {record_path}", flush=True)
                return record
        shutil.rmtree(run_dir, ignore_errors=True)
        run_dir.mkdir(parents=True)
        timing_path = run_dir / "benchmark_timing.json"
        print(f"[speed_accuracy] {scene.name} / {method} / {seed}: ns-train {shlex.join(command)}", flush=True)
        with open(run_dir / "train.log", "w") as log:
            child = subprocess.Popen(
                [sys.executable, str(Path(__file__).resolve()), TRAIN_CHILD, str(timing_path), *command],
                stdout=log, stderr=subprocess.STDOUT, env=command_environment(),
            )
            _, status, usage = os.wait4(child.pid, 0)
            child.returncode = os.waitstatus_to_exitcode(status)
        if child.returncode != 0:
            raise RuntimeError(f"ns-train failed ({child.returncode}) for {scene.name} / {method}: see {run_dir}/train.log")
        timing = json.loads(timing_path.read_text())
        print(f"[speed_accuracy] {scene.name} / {method} / {seed}: trained in {timing['train_seconds']:.1f} s; "
              "evaluating", flush=True)
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
            "checkpoints": evaluate_checkpoints(
                run_dir / "config.yml", timing["checkpoints"], scene.moving(self.output), self.eval_frames
            ),
        }
        record_path.write_text(json.dumps(record, indent=1))
        return record


class Report:
    """Tables, targets and plot of a set of run records."""

    def __init__(self, benchmark: SpeedAccuracyBenchmark, records: List[Dict[str, Any]]) -> None:
        self.benchmark = benchmark
        self.records = records
        self.scenes = list(dict.fromkeys(r["scene"] for r in records))

    def runs(self, scene: str, method: str) -> List[Dict[str, Any]]:
        return [r for r in self.records if r["scene"] == scene and r["method"] == method]

    def methods(self, scene: str) -> List[str]:
        return list(dict.fromkeys(r["method"] for r in self.records if r["scene"] == scene))

    @property
    def headline_clock(self) -> Clock:
        """CPU time of the training process on the CPU, wall-clock time on CUDA."""
        return "cpu_seconds" if self.benchmark.device == "cpu" else "seconds"

    def budget(self, scene: str, clock: Optional[Clock] = None) -> float:
        """Equal-time budget of a scene on a clock (default the headline's): ``--time-budget``, or the shortest
        mean training time of the main methods."""
        if self.benchmark.time_budget is not None:
            return self.benchmark.time_budget
        total = "train_" + (clock or self.headline_clock)
        means = [np.mean([r[total] for r in self.runs(scene, m)]) for m in self.benchmark.main_methods]
        return float(min(m for m in means if not np.isnan(m)))

    def at_budget(self, scene: str, method: str, clock: Optional[Clock] = None) -> List[Optional[Dict[str, Any]]]:
        clock = clock or self.headline_clock
        return [at_budget(r, self.budget(scene, clock), clock) for r in self.runs(scene, method)]

    def equal_time_table(self, clock: Clock) -> List[str]:
        """Each run at its last checkpoint within the scene's budget on this clock."""
        lines = [
            "| scene | budget (s) | method | n | iteration reached | PSNR | SSIM | LPIPS |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for scene in self.scenes:
            budget = self.budget(scene, clock)
            for method in self.methods(scene):
                points = self.at_budget(scene, method, clock)
                if any(p is None for p in points):
                    lines.append(f"| {scene} | {budget:.0f} | {METHODS[method]} | {len(points)} | "
                                 "a run has no checkpoint within the budget | | | |")
                    continue
                lines.append(
                    f"| {scene} | {budget:.0f} | {METHODS[method]} | {len(points)} | "
                    f"{spread([p['step'] + 1 for p in points], 0)} | {spread([p['psnr'] for p in points])} | "
                    f"{spread([p['ssim'] for p in points], 3)} | {lpips_of(points)} |"
                )
        return lines

    def finals(self, scene: str, method: str) -> List[Dict[str, Any]]:
        return [r["checkpoints"][-1] for r in self.runs(scene, method)]

    def markdown(self, context: Dict[str, str]) -> str:
        b = self.benchmark
        lpips_note = "" if has_lpips() else " LPIPS: missing (AlexNet weights not on disk; nothing downloaded)."
        lines = [
            "# Speed / accuracy benchmark",
            "",
            f"Base preset `{b.base_preset}` with its own defaults (gear-update schedule included), "
            f"{b.preset_iterations()} iterations per run, device {b.device}. Held-out metrics on {b.eval_frames} "
            f"frames of the held-out camera, evenly spaced over the video.{lpips_note} Mean ± sample standard "
            f"deviation over seeds; `n` is the number of seeds ({b.seeds} for "
            f"{', '.join(METHODS[m] for m in b.main_methods)}, 1 for the ablations, which ran on "
            f"{', '.join(b.ablation_scenes)} only).",
            "",
            "Scenes:",
            "",
        ]
        lines += [f"- `{name}`: {SCENES[name].description}; held-out camera {SCENES[name].held_out}." for name in self.scenes]
        budget_rule = (
            "Each run at its last checkpoint within the scene's budget (the shortest mean total training time of "
            + ", ".join(METHODS[m] for m in b.main_methods) + ")"
        )
        lines += ["", "![PSNR against training time](speed_accuracy.png)", ""]
        if self.headline_clock == "cpu_seconds":
            lines += ["## Equal training CPU time (headline)", "", budget_rule + ", in CPU seconds of the "
                      "single-threaded training process.", "", *self.equal_time_table("cpu_seconds"), ""]
            lines += ["## Equal wall-clock time", "", budget_rule + ", in wall-clock seconds (these depend on what "
                      "else the machine ran at the same time; see the load below).", ""]
        else:
            lines += ["## Equal wall-clock time (headline)", "", budget_rule + ".", ""]
        lines += self.equal_time_table("seconds")
        lines += [
            "",
            "## Equal iterations",
            "",
            "| scene | method | n | training time (s) | ms / iteration | PSNR | SSIM | LPIPS | gear updates "
            "| moving px at gear >= 2 | static px at gear 1 | samples / ray | render FPS | parameters (in use) "
            "| peak RSS (MiB) | training CPU time (s) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for scene in self.scenes:
            for method in self.methods(scene):
                runs, finals = self.runs(scene, method), self.finals(scene, method)
                lines.append(
                    f"| {scene} | {METHODS[method]} | {len(runs)} | {spread([r['train_seconds'] for r in runs], 0)} | "
                    f"{spread([1000 * r['train_seconds'] / r['iterations'] for r in runs], 0)} | "
                    f"{spread([p['psnr'] for p in finals])} | {spread([p['ssim'] for p in finals], 3)} | "
                    f"{lpips_of(finals)} | {spread([p['gear_updates'] for p in finals], 0)} | "
                    f"{share(finals, 'moving_at_gear_2')} | {share(finals, 'static_at_gear_1')} | "
                    f"{spread([p['samples_per_ray'] for p in finals], 1)} | {spread([p['fps'] for p in finals])} | "
                    f"{finals[0]['parameters']:,} ({finals[0]['parameters_in_use']:,}) | "
                    f"{spread([r['peak_rss_mib'] for r in runs], 0)} | "
                    f"{spread([r['train_cpu_seconds'] for r in runs], 0)} |"
                )
        lines += ["", "## Targets", ""] + self.targets() + [
            "",
            "## How it was run",
            "",
            "```bash",
            f".venv/bin/{context['command']}",
            "```",
            "",
            f"- date: {context['started']} to {context['finished']} (UTC)",
            f"- machine: {context['machine']}",
            f"- {context['load']}",
            "- training time: wall-clock seconds inside nerfstudio's training loop up to each checkpoint, without "
            "writing checkpoints and with in-loop evaluation off; training CPU time: the same in CPU seconds of the "
            "training process; render FPS: held-out frames per second of `get_outputs_for_camera`; gear maps: "
            "`visible_gear_levels` on the scored frames; peak RSS: `ru_maxrss` of the training process.",
            "",
        ]
        return "\n".join(lines)

    def targets(self) -> List[str]:
        """The issue's targets, with the measured numbers (met or not)."""
        lines = []
        for scene in self.scenes:
            gear, kplanes = self.at_budget(scene, "gear-nerf"), self.at_budget(scene, "kplanes")
            clock = "CPU" if self.headline_clock == "cpu_seconds" else "wall-clock"
            finals = self.finals(scene, "gear-nerf")
            if not gear or not kplanes or any(p is None for p in (*gear, *kplanes)):
                lines.append(f"- {scene}: not evaluated (needs gear-nerf and kplanes runs within the budget).")
                continue
            gain = np.mean([p["psnr"] for p in gear]) - np.mean([p["psnr"] for p in kplanes])
            updates = min(p["gear_updates"] for p in finals)
            moving = [p["moving_at_gear_2"] for p in finals if p["moving_at_gear_2"] is not None]
            static = np.mean([p["static_at_gear_1"] for p in finals])
            required = 0.0 if scene == "panoptic" else 0.5
            moving_target = 0.5 if scene == "panoptic" else 0.8
            lines.append(
                f"- {scene}: Gear-NeRF {gain:+.2f} dB against plain K-Planes with L_SAM at equal {clock} time "
                f"(target >= {required:+.1f}: {'met' if gain >= required else 'not met'}); at least {updates} gear "
                f"updates per run (target >= 2: {'met' if updates >= 2 else 'not met'}); "
                + (f"{100 * np.mean(moving):.0f} % of moving pixels at gear >= 2 (target >= {100 * moving_target:.0f} %: "
                   f"{'met' if np.mean(moving) >= moving_target else 'not met'}); " if moving else "")
                + f"{100 * static:.0f} % of static pixels at gear 1 (target >= 90 %: {'met' if static >= 0.9 else 'not met'})."
            )
        return lines

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
                seconds = np.mean([[p[self.headline_clock] for p in r["checkpoints"]] for r in runs], axis=0)
                psnrs = np.array([[p["psnr"] for p in r["checkpoints"]] for r in runs])
                line = axis.plot(seconds, psnrs.mean(axis=0), marker="o", markersize=3,
                                 label=f"{METHODS[method]} (n={len(runs)})")[0]
                if len(runs) > 1:
                    axis.fill_between(seconds, psnrs.min(axis=0), psnrs.max(axis=0), color=line.get_color(), alpha=0.15)
            axis.axvline(self.budget(scene), color="grey", linestyle="--", linewidth=0.8)
            axis.set_title(f"{scene}")
            axis.set_xlabel("training CPU time (s)" if self.headline_clock == "cpu_seconds" else "training time (s)")
            axis.set_ylabel("held-out PSNR (dB)")
            axis.grid(alpha=0.3)
            axis.legend(fontsize=6)
        for axis in list(axes.flat)[len(self.scenes):]:
            axis.set_visible(False)
        b = self.benchmark
        figure.suptitle(f"Held-out PSNR vs training time ({b.base_preset}, {b.device}, {b.preset_iterations()} "
                        "iterations; mean over seeds, band: min-max; dashed: equal-time budget)", fontsize=9)
        figure.tight_layout()
        figure.savefig(path, dpi=120)
        plt.close(figure)


def spread(values: List[float], digits: int = 2) -> str:
    """Mean ± sample standard deviation (just the value for one)."""
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return f"{np.mean(values):.{digits}f} ± {np.std(values, ddof=1):.{digits}f}"


def share(points: List[Dict[str, Any]], key: str) -> str:
    values = [p[key] for p in points if p[key] is not None]
    return "n/a" if not values else spread([100 * v for v in values], 0) + " %"


def lpips_of(points: List[Dict[str, Any]]) -> str:
    values = [p["lpips"] for p in points if p.get("lpips") is not None]
    return "missing" if len(values) < len(points) else spread(values, 3)


def at_budget(run: Dict[str, Any], budget: float, clock: Clock) -> Optional[Dict[str, Any]]:
    """The last checkpoint of a run whose training time on the clock is within the budget (1 ms tolerance)."""
    within = [p for p in run["checkpoints"] if p[clock] <= budget + 1e-3]
    return within[-1] if within else None


def has_lpips() -> bool:
    from gear_nerfstudio.model.gear_model import lpips_weights_path

    return lpips_weights_path().is_file()


def evaluate_checkpoints(
    config_path: Path, checkpoints: List[Dict[str, float]], moving: Callable[[int, int], np.ndarray], eval_frames: int
) -> List[Dict[str, Any]]:
    """Held-out metrics, gear maps, render speed, samples per ray and parameters of each checkpoint of a run.

    The pipeline is set up once (nerfstudio's ``eval_setup``, test split = held-out camera, SAM features off:
    the metrics do not use them); each checkpoint is then loaded into it with ``eval_load_checkpoint``.
    """
    import torch
    from nerfstudio.utils.eval_utils import eval_load_checkpoint, eval_setup

    def no_sam(config):
        config.pipeline.datamanager.use_sam_features = False
        return config

    config, pipeline, _, _ = eval_setup(config_path, test_mode="test", update_config_callback=no_sam)
    model = pipeline.model
    dataset = pipeline.datamanager.eval_dataset
    frames = sorted({int(round(i)) for i in np.linspace(0, len(dataset) - 1, min(eval_frames, len(dataset)))})
    cuda = torch.device(pipeline.device).type == "cuda"

    def render(index: int) -> Dict[str, Any]:
        return model.get_outputs_for_camera(dataset.cameras[index : index + 1].to(pipeline.device))

    render(frames[0])  # warm-up, untimed
    results = []
    for entry in sorted(checkpoints, key=lambda e: e["step"]):
        config.load_step = int(entry["step"])
        eval_load_checkpoint(config, pipeline)
        metrics: Dict[str, List[float]] = {"psnr": [], "ssim": [], "lpips": []}
        render_seconds, samples, pixels = 0.0, 0.0, 0
        moving_up, moving_all, static_low, static_all = 0, 0, 0, 0
        for index in frames:
            if cuda:
                torch.cuda.synchronize()
            started = time.perf_counter()
            outputs = render(index)
            if cuda:
                torch.cuda.synchronize()
            render_seconds += time.perf_counter() - started
            image_metrics, _ = model.get_image_metrics_and_images(outputs, dataset[index])
            for name in metrics:
                if name in image_metrics:
                    metrics[name].append(float(image_metrics[name]))
            samples += float(outputs["num_samples"].sum())
            pixels += outputs["num_samples"].numel()
            levels = model.visible_gear_levels(dataset.cameras[index : index + 1], outputs).cpu().numpy()
            frame = int(dataset.metadata["frame_ids"][index])
            truth = moving(frame, int(dataset.metadata["frame_numbers"][frame]))
            moving_up += int((levels[truth] >= 2).sum())
            moving_all += int(truth.sum())
            static_low += int((levels[~truth] == 1).sum())
            static_all += int((~truth).sum())
        total = sum(p.numel() for p in model.parameters())
        unused = sum(p.numel() for p in model.field.parameters()) - model.field.parameters_in_use()
        results.append(
            {
                "step": int(entry["step"]),
                "seconds": float(entry["seconds"]),
                "cpu_seconds": float(entry["cpu_seconds"]),
                "psnr": float(np.mean(metrics["psnr"])),
                "ssim": float(np.mean(metrics["ssim"])),
                "lpips": float(np.mean(metrics["lpips"])) if metrics["lpips"] else None,
                "fps": len(frames) / render_seconds,
                "samples_per_ray": samples / pixels,
                "moving_at_gear_2": moving_up / moving_all if moving_all else None,
                "static_at_gear_1": static_low / static_all,
                "gear_updates": int(pipeline.gear_update_state.num_updates),
                "parameters": int(total),
                "parameters_in_use": int(total - unused),
            }
        )
        print(f"[speed_accuracy]   step {entry['step']:>6}  {entry['seconds']:8.1f} s  PSNR {results[-1]['psnr']:.2f}"
              f"  samples/ray {results[-1]['samples_per_ray']:.1f}  updates {results[-1]['gear_updates']}", flush=True)
    del pipeline, model
    return results


def machine_description(device: str) -> str:
    """CPU model, cores, memory, OS, Python, torch, and the GPU when CUDA is used."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout.splitlines():
            if line.startswith("Model name:"):
                cpu = line.split(":", 1)[1].strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    memory = ""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                memory = f", {int(line.split()[1]) / 1024 ** 2:.0f} GiB RAM"
    except OSError:
        pass
    import torch

    text = (f"{cpu}, {os.cpu_count()} logical CPUs{memory}; {platform.platform()}; Python {platform.python_version()}, "
            f"torch {torch.__version__} with {torch.get_num_threads()} CPU thread(s) per process")
    if device == "cuda" and torch.cuda.is_available():
        properties = torch.cuda.get_device_properties(0)
        text += f"; GPU {properties.name} ({properties.total_memory / 1024 ** 3:.0f} GiB), CUDA {torch.version.cuda}"
    return text


def train_child(timing_path: Path, arguments: List[str]) -> None:
    """Child process: nerfstudio's ``ns-train`` with hooks on ``Trainer.train`` and ``save_checkpoint``.

    Writes to ``timing_path``: per checkpoint, the step and the training time before it, wall clock
    (``seconds``) and CPU time of the process (``cpu_seconds``, all its threads), both from the start of
    ``Trainer.train`` minus earlier checkpoint writes; the totals; the set-up time before the loop; and on
    CUDA ``torch.cuda.max_memory_allocated`` in MiB.
    """
    import torch
    from nerfstudio.engine.trainer import Trainer

    process_start = time.perf_counter()
    state: Dict[str, Any] = {"start": None, "cpu_start": None, "saving": 0.0, "cpu_saving": 0.0, "checkpoints": {}}
    original_train, original_save = Trainer.train, Trainer.save_checkpoint

    def timed_train(self) -> None:
        state["start"], state["cpu_start"] = time.perf_counter(), time.process_time()
        original_train(self)
        checkpoints = [{"step": step, **times} for step, times in sorted(state["checkpoints"].items())]
        timing = {
            "setup_seconds": state["start"] - process_start,
            "train_seconds": checkpoints[-1]["seconds"],
            "train_cpu_seconds": checkpoints[-1]["cpu_seconds"],
            "checkpoints": checkpoints,
            "peak_cuda_mib": torch.cuda.max_memory_allocated() / 1024 ** 2 if torch.cuda.is_initialized() else None,
        }
        timing_path.write_text(json.dumps(timing, indent=1))

    def timed_save(self, step: int) -> None:
        entered, cpu_entered = time.perf_counter(), time.process_time()
        if state["start"] is not None:
            # the final save repeats the last step's save when it falls on steps_per_save: keep the first
            state["checkpoints"].setdefault(
                int(step),
                {
                    "seconds": entered - state["start"] - state["saving"],
                    "cpu_seconds": cpu_entered - state["cpu_start"] - state["cpu_saving"],
                },
            )
        original_save(self, step)
        state["saving"] += time.perf_counter() - entered
        state["cpu_saving"] += time.process_time() - cpu_entered

    Trainer.train, Trainer.save_checkpoint = timed_train, timed_save
    from nerfstudio.scripts.train import entrypoint

    sys.argv = ["ns-train", *arguments]
    entrypoint()


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == TRAIN_CHILD:
        train_child(Path(sys.argv[2]), sys.argv[3:])
    else:
        tyro.cli(SpeedAccuracyBenchmark).main()
