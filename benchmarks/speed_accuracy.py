"""Speed / accuracy benchmark: Gear-NeRF against its baselines and ablations, at several scene sizes and on
real multi-view video, with seeds.

One command trains and evaluates every (scene, method, seed), one run after the other on this machine:

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/speed_accuracy.py --output outputs/speed_accuracy --results benchmarks/results

Scenes (``SCENES``): synthetic scenes with ground truth (``gear_nerfstudio.tools.synthetic``, Neural 3D Video format,
held-out camera cam00; moving pixels from the ground-truth motion) at two sizes, and real captures
(``../shared/data/real/SOURCES.md``): ``panoptic`` (``panoptic_basketball``, Technicolor layout, held-out camera
06, which has foreground masks of the moving people) and ``panoptic-video`` (``panoptic_basketball_video``, Neural
3D Video layout at downscale 2, frames 0-29, held-out cam00; ``panoptic-video-full``: the same at full size, all 90
frames, for a GPU, ``gpu_real_capture.md``), and one forward-facing time step, ``flame-steak``
(``n3d_flame_steak_frame0``, downscale 2, held-out cam00). The committed results
(``benchmarks/results/speed_accuracy.md``) are of the two real scenes, run as invocations side by side
(``--scenes panoptic-video`` and ``--scenes panoptic --iterations 2250``, both with ``--ablations`` and nothing
after it, ``--checkpoints 4 --eval-frames 4``; the results file lists the exact commands), then one
``--report-only`` over both.

Methods (``METHODS``), all ``ns-train <preset> <overrides>`` on the same base preset (``gear-nerf-small`` on
the CPU, ``gear-nerf`` with ``--device cuda``) with the same data, iterations, batch and losses, except the one
thing each changes:

* ``gear-nerf``: the preset (N_gear = 4, gear updates, split sampling, L_SAM).
* ``kplanes``: N_gear = 1 (plain K-Planes: one volume with one row per frame, the preset's base sampler), with L_SAM as
  Gear-NeRF: the main baseline.
* ablations: ``no-split`` (gears and updates, but no extra samples: split base 1), ``no-updates`` (no gear
  update: every point stays in gear 1), ``gear-nerf-no-sam`` and ``kplanes-no-sam`` (no L_SAM; the upshift
  masks still come from the SAM decoder on the ground-truth frames' embeddings), and the paper's
  baselines ``uniform-128``, ``naive-medium`` and ``no-embedding``; for real captures ``no-appearance``,
  ``uniform`` (the paper's n uniform base samples instead of the presets' proposal networks) and
  ``random-background`` (nerfstudio's random background colour in training; see ``method_overrides``); for the
  budget ``lr-0.01`` (every parameter group), ``rays-2048`` (with ``--iterations`` halved: equal rays), and
  cheaper iterations ``samples-16`` and ``samples-16-rays-768``; ``proposal-warmup`` (the proposal networks'
  update warm-up at a sixth of the run, K-Planes' 5,000 of 30,000, instead of a fixed 5,000 steps); the field's
  untrained density ``initial-density``; for forward-facing rigs ``contraction`` (nerfacto's scene contraction
  beyond the box and its far plane); and the later levers of ``real_capture_causes.md``: ``gear-rows-1`` and
  ``gear-rows-4``, ``resolutions-64-128``, ``time-smoothness-1e-4``, ``gear-1-static`` (the paper's gear 1 of one
  row in time),
  ``gear-rows-all`` (every gear T rows),
  ``views-every-frame`` (each gear update renders a view at every frame, at loss maps of 64 pixels), and
  ``lr-half-decay`` (the cosine schedule of a run twice as long, ending at about half the rate).

Seeds: ``--seeds`` seeds (``--machine.seed`` 42, 43, ...; ``--first-seed``) for ``--main-methods``, one seed for
the others.

What is measured, and how:

* Training: each run is a child process running nerfstudio's ``ns-train`` entry point, with the evaluation
  inside the training loop turned off and a checkpoint every ``iterations / checkpoints`` steps. The child
  records, at each checkpoint, the training time since ``Trainer.train`` started, minus the time spent
  writing earlier checkpoints (data loading, SAM encoding and set-up are not counted; gear updates are), in
  wall-clock seconds and in CPU seconds of the training process.
* Held-out metrics, per checkpoint: ``--eval-frames`` frames of the held-out camera, evenly spaced over the
  video, rendered with ``model.get_outputs_for_camera`` and scored with the model's
  ``get_image_metrics_and_images`` (PSNR, SSIM; LPIPS only when its weights are on disk, else "missing").
* Moving region, per checkpoint (``gear_nerfstudio.model.moving_region``, as ns-eval): PSNR over the moving pixels
  of the scored frames and over the rest, and with ``model.visible_gear_levels`` (Eq 5 at the surface each pixel
  sees) the share of moving pixels at gear >= 2 and of the rest at gear 1. The moving pixels are the person masks
  where a scene passes ``--moving-masks`` (``panoptic``, ``panoptic-video-full-30``), else the held-out pixels whose
  colour changes over the window.
* Render FPS, samples per ray, parameters (all, and in use), gear updates run (from the checkpoint), peak RSS.
* Equal iterations: the last checkpoint. Equal training time (the headline): per scene, a time budget (the
  shortest mean total training time of the main methods, or ``--time-budget``); each run is scored at its
  last checkpoint within the budget. On the CPU the headline clock is the CPU time of the training process
  (run it single-threaded, ``OMP_NUM_THREADS=1``: then it equals the wall-clock time of an idle machine; it
  depends much less on what else the machine runs than the wall-clock time does, but it still rose by 20-30 %
  per iteration when every core was busy, so the runs compared should share the machine alike;
  ``real_capture_causes.md``); the wall-clock table follows. On CUDA the headline is the
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
import re
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Dict, List, Literal, Optional, Tuple

import numpy as np
import tyro

from compare_views import contact_sheet
from environment import command_environment
from gear_nerfstudio.method_configs.gear_nerf import schedule_options
from gear_nerfstudio.model.moving_region import mask_path

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
    "no-appearance": "Gear-NeRF w/o per-camera appearance codes",
    "uniform": "Gear-NeRF with n uniform base samples (the paper's sampler)",
    "random-background": "Gear-NeRF trained on a random background colour (transparency costs loss)",
    "lr-0.01": "Gear-NeRF at learning rate 0.01 (K-Planes') instead of 0.02",
    "rays-2048": "Gear-NeRF on 2,048 rays per batch instead of 1,024",
    "initial-density": "Gear-NeRF starting from density 2 per scene unit instead of about 0.37",
    "contraction": "Gear-NeRF with space beyond the scene box contracted (far plane 1,000, as nerfacto)",
    "samples-16": "Gear-NeRF with 16 base samples per ray instead of 24",
    "samples-16-rays-768": "Gear-NeRF with 16 base samples per ray and 768 rays per batch",
    "proposal-warmup": "Gear-NeRF with the proposal networks' update warm-up at 1/6 of the run (K-Planes' ratio)",
    "gear-rows-1": "Gear-NeRF with a gear function constant in time (k' of 1 row)",
    "gear-rows-4": "Gear-NeRF with a gear function of 4 rows in time (k')",
    "gear-1-static": "Gear-NeRF whose gear 1 has one row in time (Sec 4.4, the paper) instead of the presets' T/4",
    "gear-rows-all": "Gear-NeRF whose every gear has T rows in time (no gear is static) instead of T/4 to T",
    "lr-half-decay": "Gear-NeRF whose learning rates follow the cosine schedule of a run twice as long (end at half)",
    "views-every-frame": "Gear-NeRF whose updates render a view at every frame (loss maps of 64 pixels) instead of 4",
    "resolutions-64-128": "Gear-NeRF with planes of 64 and 128 cells instead of 32 and 64",
    "time-smoothness-1e-4": "Gear-NeRF with the time-smoothness weight at 1e-4 instead of 1e-3",
}
"""Method keys and their labels in the tables and the plot."""


def method_overrides(method: str, frames: int, iterations: int) -> List[str]:
    """``ns-train`` overrides of a method on top of the base preset, for a run of ``iterations``."""
    no_sam = ["--pipeline.datamanager.use-sam-features", "False", "--pipeline.gear-updates.sam-loss-weight", "0"]
    single = ["--pipeline.model.num-gears", "1"]
    uniform = ["--pipeline.model.base-sampler", "uniform"]
    samples_16 = ["--pipeline.model.num-samples", "16"]
    rays_768 = ["--pipeline.datamanager.train-num-rays-per-batch", "768"]
    overrides = {
        "gear-nerf": [],
        "kplanes": single,
        "no-split": ["--pipeline.model.split-base", "1"],
        "no-updates": ["--pipeline.gear-updates.enabled", "False"],
        "gear-nerf-no-sam": no_sam,
        "kplanes-no-sam": [*single, *no_sam],
        "uniform-128": [*single, *uniform, "--pipeline.model.num-samples", "128"],
        "naive-medium": [*single, "--pipeline.model.time-resolutions", str(max(1, math.ceil(frames / 2)))],
        "no-embedding": [*no_sam, "--pipeline.gear-updates.mask-source", "loss_threshold"],
        "no-appearance": ["--pipeline.model.appearance-dim", "0"],
        "uniform": uniform,
        "random-background": ["--pipeline.model.background-color", "random"],
        "lr-0.01": [arg for group in ("fields", "proposal-networks", "gear-field")
                    for arg in (f"--optimizers.{group}.optimizer.lr", "0.01")],  # fmt: skip
        "rays-2048": ["--pipeline.datamanager.train-num-rays-per-batch", "2048"],
        "initial-density": ["--pipeline.model.initial-density", "2"],
        "contraction": ["--pipeline.model.unbounded", "True", "--pipeline.model.far-plane", "1000"],
        "samples-16": samples_16,
        "samples-16-rays-768": [*samples_16, *rays_768],
        "proposal-warmup": ["--pipeline.model.proposal-warmup", str(max(1, iterations // 6))],
        "gear-rows-1": ["--pipeline.model.gear-time-resolution", "1"],
        "gear-rows-4": ["--pipeline.model.gear-time-resolution", "4"],
        "gear-1-static": ["--pipeline.model.gear1-row-fraction", "0"],
        "gear-rows-all": ["--pipeline.model.gear1-row-fraction", "1"],
        "lr-half-decay": decay_over(2 * iterations),
        "views-every-frame": ["--pipeline.gear-updates.views-per-update", str(frames),
                              "--pipeline.gear-updates.loss-map-size", "64", "--pipeline.gear-updates.patch-size", "4"],
        "resolutions-64-128": ["--pipeline.model.resolutions", "64", "128"],
        "time-smoothness-1e-4": ["--pipeline.model.time-smoothness-mult", "1e-4"],
    }
    if method not in overrides:
        raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    return overrides[method]


def decay_over(steps: int) -> List[str]:
    """``ns-train`` overrides that spread the radiance fields' cosine learning-rate decay over ``steps``."""
    return [arg for group in ("fields", "proposal-networks")
            for arg in (f"--optimizers.{group}.scheduler.max-steps", str(steps))]  # fmt: skip


def read_mask(masks: Path, camera: str, number: int) -> np.ndarray:
    """A real capture's foreground mask (``mask_path``) as an (H, W) bool map."""
    from PIL import Image

    return np.array(Image.open(mask_path(masks, camera, number)).convert("L")) > 127


def gear_mask_counts(levels: np.ndarray, moving: np.ndarray) -> np.ndarray:
    """A gear map (Eq 5 levels, H x W) against a map of moving pixels: [moving pixels at gear >= 2, moving pixels,
    other pixels at gear 1, other pixels]."""
    return np.array([(levels[moving] >= 2).sum(), moving.sum(), (levels[~moving] == 1).sum(), (~moving).sum()])


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
    """A real capture, read by ``parser``."""
    parser: str = "technicolor-data"
    """The dataparser of a real capture (synthetic scenes are written in the Neural 3D Video layout)."""
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
        parser = "neural-3d-video-data" if self.synthetic else self.parser
        return [
            parser, "--data", str(self.folder(output)), "--held-out-camera", self.held_out,
            "--cache-dir", str(output / "cache" / self.name), *self.parser_options,
        ]


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
        data=REAL / "panoptic_basketball",
        parser_options=("--near", "0.3", "--far", "7", "--moving-masks", str(REAL / "panoptic_basketball_masks")),
    ),
    "panoptic-video": Scene(
        "panoptic-video", "real: CMU Panoptic basketball in the Neural 3D Video layout, 304x168 (downscale 2), 31 cameras "
        "(30 trained), frames 0-29", 30, "cam00", data=REAL / "panoptic_basketball_video", parser="neural-3d-video-data",
        parser_options=("--downscale-factor", "2", "--frame-count", "30"),
    ),
    "panoptic-video-60": Scene(
        "panoptic-video-60", "real: CMU Panoptic basketball in the Neural 3D Video layout, 304x168 (downscale 2), 31 "
        "cameras (30 trained), frames 60-89 (no default was chosen on them), held-out cam20 with person masks", 30,
        "cam20", data=REAL / "panoptic_basketball_video", parser="neural-3d-video-data",
        parser_options=("--downscale-factor", "2", "--frame-start", "60", "--frame-count", "30",
                        "--moving-masks", str(REAL / "panoptic_basketball_video_masks")),
    ),
    "panoptic-video-full": Scene(
        "panoptic-video-full", "real: CMU Panoptic basketball in the Neural 3D Video layout at full size, 608x336, 31 "
        "cameras (30 trained), all 90 frames (for the GPU)", 90, "cam00", data=REAL / "panoptic_basketball_video",
        parser="neural-3d-video-data",
    ),
    "panoptic-video-full-30": Scene(
        "panoptic-video-full-30", "real: CMU Panoptic basketball in the Neural 3D Video layout at full size, 608x336, "
        "31 cameras (30 trained), frames 0-29, held-out cam20 with person masks (for the GPU)", 30, "cam20",
        data=REAL / "panoptic_basketball_video", parser="neural-3d-video-data",
        parser_options=("--frame-count", "30", "--moving-masks", str(REAL / "panoptic_basketball_video_masks")),
    ),
    "flame-steak": Scene(
        "flame-steak", "real: Neural 3D Video flame_steak, frame 0 only, 336x252 (downscale 2), 21 forward-facing "
        "cameras (20 trained)", 1, "cam00", data=REAL / "n3d_flame_steak_frame0", parser="neural-3d-video-data",
        parser_options=("--downscale-factor", "2"),
    ),
}
"""Scenes by name. ``panoptic`` holds out camera 06 (not the usual 10) because 10 has no masks; ``panoptic-video``
holds out cam00, the parser's default and the view published methods hold out, which has none (its moving region
is the held-out view's colour change); ``panoptic-video-60`` is the window of the same capture that no default was
chosen on, held out at cam20, which has masks."""


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
                method_overrides(method, SCENES[name].frames, self.preset_iterations())  # fail early on an unknown name
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
                seeds = self.seeds if method in self.main_methods else 1
                for seed in range(self.first_seed, self.first_seed + seeds):
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
        report = Report(self, records)
        pictures = report.pictures(self.output)
        markdown = report.markdown(context, pictures)
        (self.output / "speed_accuracy.md").write_text(markdown)
        report.plot(self.output / "speed_accuracy.png")
        print(markdown)
        if self.results is not None:
            self.results.mkdir(parents=True, exist_ok=True)
            for path in (self.output / "speed_accuracy.md", self.output / "speed_accuracy.png", *pictures):
                shutil.copyfile(path, self.results / path.name)
            print(f"[speed_accuracy] wrote speed_accuracy.md, speed_accuracy.png and the pictures to {self.results}")

    @property
    def base_preset(self) -> str:
        return self.preset or ("gear-nerf" if self.device == "cuda" else "gear-nerf-small")

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
            *decay_over(iterations),
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
            "before_first_update": timing.get("before_first_update"),
            "update_reviews": update_reviews((run_dir / "train.log").read_text()),
            "checkpoints": evaluate_checkpoints(
                run_dir / "config.yml", timing["checkpoints"], self.eval_frames, run_dir
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

    def iterations(self, scene: str) -> List[int]:
        """The iteration counts of a scene's runs."""
        return sorted({r["iterations"] for m in self.methods(scene) for r in self.runs(scene, m)})

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
            "| scene | budget (s) | method | n | iteration reached | PSNR | PSNR moving | PSNR rest | SSIM | LPIPS |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for scene in self.scenes:
            budget = self.budget(scene, clock)
            for method in self.methods(scene):
                points = self.at_budget(scene, method, clock)
                if any(p is None for p in points):
                    lines.append(f"| {scene} | {budget:.0f} | {METHODS[method]} | {len(points)} | "
                                 "a run has no checkpoint within the budget | | | | | |")
                    continue
                lines.append(
                    f"| {scene} | {budget:.0f} | {METHODS[method]} | {len(points)} | "
                    f"{spread([p['step'] + 1 for p in points], 0)} | {spread([p['psnr'] for p in points])} | "
                    f"{scores(points, 'psnr_moving')} | {scores(points, 'psnr_static')} | "
                    f"{spread([p['ssim'] for p in points], 3)} | {lpips_of(points)} |"
                )
        return lines

    def finals(self, scene: str, method: str) -> List[Dict[str, Any]]:
        return [r["checkpoints"][-1] for r in self.runs(scene, method)]

    def markdown(self, context: Dict[str, str], pictures: List[Path]) -> str:
        b = self.benchmark
        lpips_note = "" if has_lpips() else " LPIPS: missing (AlexNet weights not on disk; nothing downloaded)."
        lines = [
            "# Speed / accuracy benchmark",
            "",
            f"Base preset `{b.base_preset}` with its own defaults (gear-update schedule included, scaled to the "
            f"iterations of each scene), device {b.device}. Held-out metrics on {b.eval_frames} frames of the held-out "
            f"camera, evenly spaced over the video.{lpips_note} Mean ± sample standard deviation over seeds; `n` is "
            f"the number of seeds ({b.seeds} for {', '.join(METHODS[m] for m in b.main_methods)}"
            + (f", 1 for the ablations, which ran on {', '.join(b.ablation_scenes)} only)." if b.ablations else ")."),
            "",
            "Scenes:",
            "",
        ]
        for name in self.scenes:
            iterations = self.iterations(name)
            lines.append(
                f"- `{name}`: {SCENES[name].description}; held-out camera {SCENES[name].held_out}; "
                f"{', '.join(map(str, iterations))} iterations per run."
            )
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
            "| scene | method | n | training time (s) | ms / iteration | PSNR | PSNR moving | PSNR rest | SSIM | LPIPS "
            "| accumulation | near layer | gear updates "
            "| moving px at gear >= 2 | static px at gear 1 | samples / ray | render FPS | parameters (in use) "
            "| peak RSS (MiB) | training CPU time (s) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for scene in self.scenes:
            for method in self.methods(scene):
                runs, finals = self.runs(scene, method), self.finals(scene, method)
                lines.append(
                    f"| {scene} | {METHODS[method]} | {len(runs)} | {spread([r['train_seconds'] for r in runs], 0)} | "
                    f"{spread([1000 * r['train_seconds'] / r['iterations'] for r in runs], 0)} | "
                    f"{spread([p['psnr'] for p in finals])} | {scores(finals, 'psnr_moving')} | "
                    f"{scores(finals, 'psnr_static')} | {spread([p['ssim'] for p in finals], 3)} | "
                    f"{lpips_of(finals)} | {spread([p['accumulation'] for p in finals], 3)} | "
                    f"{share(finals, 'near_layer')} | {spread([p['gear_updates'] for p in finals], 0)} | "
                    f"{share(finals, 'moving_at_gear_2')} | {share(finals, 'static_at_gear_1')} | "
                    f"{spread([p['samples_per_ray'] for p in finals], 1)} | {spread([p['fps'] for p in finals])} | "
                    f"{finals[0]['parameters']:,} ({finals[0]['parameters_in_use']:,}) | "
                    f"{spread([r['peak_rss_mib'] for r in runs], 0)} | "
                    f"{spread([r['train_cpu_seconds'] for r in runs], 0)} |"
                )
        lines += [
            "",
            "Accumulation: the mean opacity of the held-out renders (1: every ray ends in the model's volume, nothing "
            "comes from the background term). Near layer: the share of held-out pixels whose depth is below a quarter "
            "of the training rays' median depth (`GearNeRFModel.near_layer`).",
            "",
            "## What each gear update did",
            "",
            "Measured by the guard at each update's review, L epochs after it (`GearUpdater.review`): the PSNR of "
            "the update's own training views, and of the held-out camera at the same times (at the loss maps' size), "
            "at the review minus just before the update (mean ± spread over seeds); an update is undone when its views "
            "end more than `guard-tolerance` worse.",
            "",
            *self.reviews_table(),
        ]
        lines += ["", "## Pictures", "", "The held-out view at two of the scored times, first seed, last checkpoint.", ""]
        lines += [f"![{path.stem}]({path.name})" for path in pictures]
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
        """The issues' targets, with the measured numbers (met or not)."""
        lines = []
        clock = "CPU" if self.headline_clock == "cpu_seconds" else "wall-clock"
        for scene in self.scenes:
            gear, kplanes = self.at_budget(scene, "gear-nerf"), self.at_budget(scene, "kplanes")
            finals = self.finals(scene, "gear-nerf")
            if not gear or not kplanes or any(p is None for p in (*gear, *kplanes)):
                lines.append(f"- {scene}: not evaluated (needs gear-nerf and kplanes runs within the budget).")
                continue
            gains = [g["psnr"] - k["psnr"] for g, k in zip(gear, kplanes)]  # paired by seed
            gain, gain_spread = float(np.mean(gains)), float(np.std(gains, ddof=1)) if len(gains) > 1 else 0.0
            required = {"panoptic": 0.0, "panoptic-video": 0.5}.get(scene, 0.5)
            margin = gain - gain_spread if scene == "panoptic-video" else gain
            rule = "mean minus spread" if scene == "panoptic-video" else "mean"
            updates = min(p["gear_updates"] for p in finals)
            parts = [
                f"Gear-NeRF {gain:+.2f} ± {gain_spread:.2f} dB against plain K-Planes with L_SAM at equal {clock} time, "
                f"paired by seed (target: {rule} >= {required:+.1f}: {'met' if margin >= required else 'not met'})",
                f"at least {updates} gear updates per run (target >= 2: {'met' if updates >= 2 else 'not met'})",
            ]
            if scene == "panoptic-video":
                psnr, accumulation = np.mean([p["psnr"] for p in finals]), np.mean([p["accumulation"] for p in finals])
                parts += [
                    f"Gear-NeRF at its defaults {psnr:.2f} dB held-out PSNR (target >= 25: {'met' if psnr >= 25 else 'not met'})",
                    f"held-out accumulation {accumulation:.3f} (target > 0.95: {'met' if accumulation > 0.95 else 'not met'})",
                ]
            moving = [p["moving_at_gear_2"] for p in finals if p["moving_at_gear_2"] is not None]
            static = [p["static_at_gear_1"] for p in finals if p["static_at_gear_1"] is not None]
            if moving:
                moving_target = 0.5 if scene == "panoptic" else 0.8
                parts.append(
                    f"{100 * np.mean(moving):.0f} % of moving pixels at gear >= 2 (target >= {100 * moving_target:.0f} %: "
                    f"{'met' if np.mean(moving) >= moving_target else 'not met'})"
                )
            if static:
                parts.append(
                    f"{100 * np.mean(static):.0f} % of static pixels at gear 1 (target >= 90 %: "
                    f"{'met' if np.mean(static) >= 0.9 else 'not met'})"
                )
            lines.append(f"- {scene}: " + "; ".join(parts) + ".")
        below = [
            f"{r['scene']} / {METHODS[r['method']]} / seed {r['seed']}" for r in self.records if ends_below_first_update(r)
        ]
        checked = sum(r.get("before_first_update") is not None for r in self.records)
        lines.append(
            f"- Every run ends at or above its own held-out PSNR just before its first gear update ({checked} runs with "
            f"updates): {'met' if not below else 'not met: ' + ', '.join(below)}."
        )
        return lines

    def reviews_table(self) -> List[str]:
        """What each gear update did, as the guard measured it at its review (L epochs later): the change of its
        training views' PSNR and of the held-out view's at the same times, and how many were undone."""
        lines = [
            "| scene | method | n | update | reviewed at step | its views (dB) | held-out view (dB) | undone |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for scene in self.scenes:
            for method in self.methods(scene):
                runs = [r for r in self.runs(scene, method) if r.get("update_reviews")]
                for update in sorted({v["update"] for r in runs for v in r["update_reviews"]}):
                    reviews = [v for r in runs for v in r["update_reviews"] if v["update"] == update]
                    views = [v["views_after"] - v["views_before"] for v in reviews]
                    held = [v["held_out_after"] - v["held_out_before"] for v in reviews if v["held_out_after"] is not None]
                    lines.append(
                        f"| {scene} | {METHODS[method]} | {len(reviews)} | {update} | "
                        f"{spread([v['step'] for v in reviews], 0)} | {spread(views, 2, signed=True)} | "
                        f"{spread(held, 2, signed=True) if held else 'n/a'} | {sum(not v['kept'] for v in reviews)} |"
                    )
        return lines

    def pictures(self, folder: Path) -> List[Path]:
        """Per scene, the held-out view at two times (rows): ground truth, Gear-NeRF, plain K-Planes and Gear-NeRF's
        gear map, from the first seed's last checkpoint; one PNG per scene."""
        from PIL import Image

        written = []
        for scene in self.scenes:
            runs = {m: self.runs(scene, m) for m in ("gear-nerf", "kplanes")}
            if not all(runs.values()):
                continue
            folders = {m: self.benchmark.run_dir(scene, m, min(r["seed"] for r in rs)) for m, rs in runs.items()}
            stems = sorted({f.name.rsplit("_", 1)[0] for f in folders["gear-nerf"].glob("held_out_*_truth.png")})
            columns = [("ground truth", "gear-nerf", "truth"), ("Gear-NeRF", "gear-nerf", "render"),
                       ("plain K-Planes (one gear)", "kplanes", "render"), ("Gear-NeRF gear map", "gear-nerf", "gear")]
            tiles = [[Image.open(folders[m] / f"{stem}_{kind}.png") for _, m, kind in columns] for stem in stems]
            sheet = contact_sheet([label for label, _, _ in columns], tiles)
            path = folder / f"speed_accuracy_{scene}.png"
            sheet.save(path)
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
                seconds = np.mean([[p[self.headline_clock] for p in r["checkpoints"]] for r in runs], axis=0)
                psnrs = np.array([[p["psnr"] for p in r["checkpoints"]] for r in runs])
                line = axis.plot(seconds, psnrs.mean(axis=0), marker="o", markersize=3,
                                 label=f"{METHODS[method]} (n={len(runs)})")[0]
                if len(runs) > 1:
                    axis.fill_between(seconds, psnrs.min(axis=0), psnrs.max(axis=0), color=line.get_color(), alpha=0.15)
            axis.axvline(self.budget(scene), color="grey", linestyle="--", linewidth=0.8)
            iterations = self.iterations(scene)
            axis.set_title(f"{scene} ({', '.join(map(str, iterations))} iterations)")
            axis.set_xlabel("training CPU time (s)" if self.headline_clock == "cpu_seconds" else "training time (s)")
            axis.set_ylabel("held-out PSNR (dB)")
            axis.grid(alpha=0.3)
            axis.legend(fontsize=6)
        for axis in list(axes.flat)[len(self.scenes):]:
            axis.set_visible(False)
        b = self.benchmark
        figure.suptitle(f"Held-out PSNR vs training time ({b.base_preset}, {b.device})\nmean over seeds, band: min-max; "
                        "dashed: equal-time budget", fontsize=9)  # two lines: one scene's figure is narrow
        figure.tight_layout()
        figure.savefig(path, dpi=120)
        plt.close(figure)


def spread(values: List[float], digits: int = 2, signed: bool = False) -> str:
    """Mean ± sample standard deviation (just the value for one); ``signed``: with the mean's sign."""
    sign = "+" if signed else ""
    if len(values) == 1:
        return f"{values[0]:{sign}.{digits}f}"
    return f"{np.mean(values):{sign}.{digits}f} ± {np.std(values, ddof=1):.{digits}f}"


def ends_below_first_update(record: Dict[str, Any]) -> bool:
    """Whether a run's last checkpoint scores a lower held-out PSNR than its checkpoint just before its first gear
    update (False for a run without updates)."""
    step = record.get("before_first_update")
    if step is None:
        return False
    before = next(p for p in record["checkpoints"] if p["step"] == step)
    return record["checkpoints"][-1]["psnr"] < before["psnr"]


def scores(points: List[Dict[str, Any]], key: str) -> str:
    """Mean ± spread of a score over runs, "missing" where a run could not compute it."""
    values = [p.get(key) for p in points]
    return "missing" if None in values else spread(values)


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
    from gear_nerfstudio.model.metrics import lpips_weights_path

    return lpips_weights_path().is_file()


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
            for name in SUMS:
                sums[name] += image_metrics[name]
            samples += float(outputs["num_samples"].sum())
            pixels += outputs["num_samples"].numel()
            if last and index in (frames[0], frames[len(frames) // 2]):
                for name, image in (
                    ("truth", dataset[index]["image"][..., :3]), ("render", outputs["rgb"]), ("gear", outputs["gear"]),
                ):  # fmt: skip
                    pixels_uint8 = (image.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
                    Image.fromarray(pixels_uint8).save(pictures / f"held_out_{index:04d}_{name}.png")
        scores = region_scores(sums, MIN_MSE)
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
                "accumulation": float(np.mean(metrics["accumulation"])),
                "near_layer": float(np.mean(metrics["near_layer"])),
                "fps": len(frames) / render_seconds,
                "samples_per_ray": samples / pixels,
                **{name: scores.get(name) for name in ("psnr_moving", "psnr_static", "moving_at_gear_2", "static_at_gear_1")},
                "gear_updates": int(pipeline.gear_update_state.num_updates),
                "parameters": int(total),
                "parameters_in_use": int(total - unused),
            }
        )
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
    CUDA ``torch.cuda.max_memory_allocated`` in MiB. A checkpoint is also saved right before the first gear update
    (its step in ``before_first_update``): the state every run is compared with at its end.
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
            "before_first_update": state.get("before_first_update"),
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

    from gear_nerfstudio.gears.updater import GearUpdater

    original_update = GearUpdater.update

    def update_after_checkpoint(self, step: int) -> Dict[str, float]:
        if "before_first_update" not in state:
            state["before_first_update"] = int(step)
            state["trainer"].save_checkpoint(step)
        return original_update(self, step)

    def trainer_train(self) -> None:
        state["trainer"] = self
        timed_train(self)

    Trainer.train, Trainer.save_checkpoint, GearUpdater.update = trainer_train, timed_save, update_after_checkpoint
    from nerfstudio.scripts.train import entrypoint

    sys.argv = ["ns-train", *arguments]
    entrypoint()


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == TRAIN_CHILD:
        train_child(Path(sys.argv[2]), sys.argv[3:])
    else:
        tyro.cli(SpeedAccuracyBenchmark).main()
