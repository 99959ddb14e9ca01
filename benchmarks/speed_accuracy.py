"""Speed / accuracy benchmark: Gear-NeRF against its baselines on synthetic scenes with ground truth.

One command trains and evaluates every method on every scene, one after the other on this machine:

    .venv/bin/python benchmarks/speed_accuracy.py --output outputs/speed_accuracy --results benchmarks/results

Scenes (`gear_nerfstudio.synthetic`, Neural 3D Video format, held-out camera cam00): "static" (one static
sphere), "slow" and "fast" (a static and a slow / fast sphere), "mixed" (static background, a static, a
slow and a fast sphere).

Methods, all as `ns-train <preset> <overrides>` on the same base preset (`gear-nerf-small` on the CPU,
the paper preset `gear-nerf` with `--device cuda`), so that everything but the compared setting is equal:

* ``gear-nerf``: the preset itself (N_gear = 4, SAM embedding, gear updates).
* ``kplanes``: N_gear = 1 with uniform sampling at the preset's n (plain K-Planes: the single gear has
  one row per frame); no SAM features (K-Planes has no L_SAM).
* ``uniform-128``: ``kplanes`` with 128 uniform samples per ray.
* ``naive-medium``: "naive temporal sampling" (paper), a single volume with medium temporal resolution:
  ``kplanes`` with ``--pipeline.model.time-resolutions ceil(T / 2)``, so the T frames are interpolated
  between ceil(T / 2) rows of the space-time planes.
* ``naive-dense``: the same with dense temporal resolution, one row per frame (T rows). With N_gear = 1
  this is exactly the ``kplanes`` configuration, so it is not trained twice: its rows reuse that run.
* ``no-embedding``: Gear-NeRF "w/o embedding" (paper): no SAM features (no L_SAM), upshift masks from
  the loss map (``mask_source loss_threshold``) instead of the SAM decoder.

What is measured, and how:

* Training: each run is a child process running nerfstudio's ``ns-train`` entry point, with the evaluation
  inside the training loop turned off (``--steps-per-eval-* 0``) and a checkpoint every
  ``iterations / checkpoints`` steps (all kept). The child records, at each checkpoint, the training time:
  seconds since ``Trainer.train`` started, minus the time spent writing earlier checkpoints (data loading,
  SAM encoding and model set-up before the loop are not counted; gear updates are, being training), in
  wall-clock seconds (the plot, the equal-time budget) and in CPU seconds of the training process (the
  tables; less sensitive to other load on a shared machine).
* Peak memory: peak resident set size of the training process (``os.wait4`` on the child, ``ru_maxrss``)
  and, on CUDA, ``torch.cuda.max_memory_allocated`` in that process.
* Held-out metrics, per checkpoint: every frame of the held-out camera is rendered with
  ``model.get_outputs_for_camera`` and scored with the model's ``get_image_metrics_and_images``; PSNR and
  SSIM are the means over the frames (as ``ns-eval``). LPIPS only when torchvision's AlexNet weights are
  already on disk (``lpips_weights_path``); otherwise the table says "missing". No metric is estimated.
* Render FPS: held-out frames divided by the wall time of their ``get_outputs_for_camera`` calls (after one
  untimed warm-up render per run; CUDA synchronised).
* Samples per ray: mean of the model output ``num_samples`` over all held-out pixels.
* Parameters: all model parameters, and those in use (all but the space-time planes of gears that never
  received a training sample, ``GearField.parameters_in_use``).
* Equal iterations: the last checkpoint of every run (every method trains ``iterations`` steps).
* Equal wall-clock time: per scene, a time budget (``--time-budget``; default: the shortest total
  training time among the methods of that scene); each method is scored at its last checkpoint whose
  training time does not exceed the budget (more checkpoints give a finer match).

Writes `<output>/speed_accuracy.md` (tables, targets, command, machine, date), `<output>/speed_accuracy.png`
(PSNR against training time, one curve per method, one panel per scene) and `<output>/records.json`
(every measurement); with ``--results DIR`` the markdown and the plot are copied there too.
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
from typing import Any, Dict, List, Literal, Optional, Tuple

import tyro

from environment import command_environment

TRAIN_CHILD = "_train"
"""First argument of the child process that runs ``ns-train`` with the timing hooks."""

METHODS: Dict[str, str] = {
    "gear-nerf": "Gear-NeRF",
    "kplanes": "plain K-Planes (N_gear = 1, uniform n)",
    "uniform-128": "uniform, 128 samples (N_gear = 1)",
    "naive-medium": "naive temporal, medium (T/2 rows)",
    "naive-dense": "naive temporal, dense (T rows)",
    "no-embedding": "Gear-NeRF w/o embedding",
}
"""Method keys and their labels in the table and the plot."""

SCENES: Tuple[str, ...] = ("static", "slow", "fast", "mixed")


def method_overrides(method: str, frames: int) -> List[str]:
    """``ns-train`` overrides of a method on top of the base preset."""
    no_sam = ["--pipeline.datamanager.use-sam-features", "False"]
    single = ["--pipeline.model.num-gears", "1", *no_sam]
    if method == "gear-nerf":
        return []
    if method in ("kplanes", "naive-dense"):  # one gear = one row per frame (gear_field.temporal_resolutions)
        return single
    if method == "uniform-128":
        return [*single, "--pipeline.model.num-samples", "128"]
    if method == "naive-medium":
        return [*single, "--pipeline.model.time-resolutions", str(max(1, math.ceil(frames / 2)))]
    if method == "no-embedding":
        return [*no_sam, "--pipeline.model.gear-updates.mask-source", "loss_threshold"]
    raise ValueError(f"unknown method {method!r}; choose from {', '.join(METHODS)}")


@dataclasses.dataclass
class SpeedAccuracyBenchmark:
    """Train and evaluate Gear-NeRF and its baselines on synthetic scenes; write a table and a plot."""

    output: Path = Path("outputs/speed_accuracy")
    """Working folder: scenes, runs, logs, records.json, speed_accuracy.md / .png."""
    results: Optional[Path] = None
    """Also copy speed_accuracy.md and speed_accuracy.png here (e.g. benchmarks/results)."""
    scenes: Tuple[str, ...] = SCENES
    """Motion kinds of the synthetic scenes: static, slow, fast, mixed."""
    methods: Tuple[str, ...] = tuple(METHODS)
    """Methods to run on the mixed scene, where the targets are (see the module docstring)."""
    other_methods: Optional[Tuple[str, ...]] = None
    """Methods to run on the other scenes; None: the same as ``methods``."""
    iterations: int = 2000
    """Training iterations of every method (the cosine schedules end there)."""
    checkpoints: int = 10
    """Evaluated checkpoints per run, evenly spaced (the last is the final one)."""
    width: int = 64
    height: int = 48
    frames: int = 8
    """Frames T of every scene."""
    cameras: int = 8
    """Cameras of every scene (cam00 is held out)."""
    device: Literal["cpu", "cuda"] = "cpu"
    """cpu: the CPU preset gear-nerf-small; cuda: the paper preset gear-nerf."""
    preset: Optional[str] = None
    """Base preset; default gear-nerf-small on cpu, gear-nerf on cuda."""
    time_budget: Optional[float] = None
    """Equal-time budget in seconds; default per scene: the shortest total training time of its methods."""
    reuse_runs: bool = False
    """Skip training a run whose record (same command) is already in the output folder."""

    def main(self) -> None:
        if self.device == "cpu":
            os.environ["CUDA_VISIBLE_DEVICES"] = ""  # the held-out renders run on the CPU as well
        for method in (*self.methods, *(self.other_methods or ())):
            method_overrides(method, self.frames)  # fail early on an unknown name
        self.output.mkdir(parents=True, exist_ok=True)
        started = datetime.datetime.now(datetime.timezone.utc)
        load_before = os.getloadavg()
        records: Dict[str, Dict[str, Dict[str, Any]]] = {}
        for scene in self.scenes:
            scene_dir = self.write_scene(scene)
            records[scene] = {}
            trained: Dict[Tuple[str, ...], str] = {}
            methods = self.methods if scene == "mixed" or self.other_methods is None else self.other_methods
            for method in methods:
                overrides = tuple(method_overrides(method, self.frames))
                if overrides in trained:  # same configuration as a method already run: same run
                    records[scene][method] = {**records[scene][trained[overrides]], "same_run_as": trained[overrides]}
                    continue
                trained[overrides] = method
                records[scene][method] = self.run(scene, scene_dir, method, list(overrides))
                (self.output / "records.json").write_text(json.dumps(records, indent=1))
        finished = datetime.datetime.now(datetime.timezone.utc)
        context = {
            "command": "python benchmarks/speed_accuracy.py " + shlex.join(sys.argv[1:]),
            "started": started.isoformat(timespec="seconds"),
            "finished": finished.isoformat(timespec="seconds"),
            "machine": machine_description(self.device),
            "load": f"1-minute load average {load_before[0]:.2f} at the start, {os.getloadavg()[0]:.2f} at the end",
        }
        markdown = self.report(records, context)
        (self.output / "speed_accuracy.md").write_text(markdown)
        self.plot(records, self.output / "speed_accuracy.png")
        print(markdown)
        if self.results is not None:
            self.results.mkdir(parents=True, exist_ok=True)
            for name in ("speed_accuracy.md", "speed_accuracy.png"):
                shutil.copyfile(self.output / name, self.results / name)
            print(f"[speed_accuracy] wrote {self.results / 'speed_accuracy.md'} and speed_accuracy.png")

    @property
    def base_preset(self) -> str:
        return self.preset or ("gear-nerf" if self.device == "cuda" else "gear-nerf-small")

    def write_scene(self, motion: str) -> Path:
        """The synthetic scene of this motion kind (rewritten unless one of the same size is there)."""
        from gear_nerfstudio.synthetic.writers import SyntheticSpec, write_synthetic_scene

        spec = SyntheticSpec(
            dataset="n3d", width=self.width, height=self.height, frames=self.frames, cameras=self.cameras, motion=motion
        )
        scene = self.output / "scenes" / motion
        info = scene / "ground_truth" / "scene.json"
        if info.is_file() and json.loads(info.read_text())["spec"] == json.loads(json.dumps(spec.__dict__)):
            return scene
        for stale in (scene, self.output / "cache" / motion):
            shutil.rmtree(stale, ignore_errors=True)
        write_synthetic_scene(scene, spec)
        return scene

    def train_command(self, scene: str, scene_dir: Path, method: str, overrides: List[str]) -> List[str]:
        """Arguments of ``ns-train`` for one run."""
        steps_per_save = max(1, self.iterations // max(1, self.checkpoints))
        return [
            self.base_preset,
            "--output-dir", str(self.output / "runs"), "--experiment-name", scene, "--timestamp", method,
            "--max-num-iterations", str(self.iterations),
            "--optimizers.fields.scheduler.max-steps", str(self.iterations),
            "--optimizers.proposal-networks.scheduler.max-steps", str(self.iterations),
            "--steps-per-save", str(steps_per_save), "--save-only-latest-checkpoint", "False",
            "--steps-per-eval-batch", "0", "--steps-per-eval-image", "0", "--steps-per-eval-all-images", "0",
            "--machine.device-type", self.device, "--vis", "tensorboard",
            "--pipeline.datamanager.sam-cache-dir", str(self.output / "sam-cache"),
            *overrides,
            "neural-3d-video-data", "--data", str(scene_dir), "--cache-dir", str(self.output / "cache" / scene),
        ]

    def run(self, scene: str, scene_dir: Path, method: str, overrides: List[str]) -> Dict[str, Any]:
        """Train one method on one scene in a child process, then evaluate its checkpoints."""
        command = self.train_command(scene, scene_dir, method, overrides)
        run_dir = self.output / "runs" / scene / self.base_preset / method
        record_path = run_dir / "benchmark_record.json"
        if self.reuse_runs and record_path.is_file():
            record = json.loads(record_path.read_text())
            if record.get("command") == command:
                print(f"[speed_accuracy] {scene} / {method}: reusing {record_path}", flush=True)
                return record
        shutil.rmtree(run_dir, ignore_errors=True)
        run_dir.mkdir(parents=True)
        timing_path = run_dir / "benchmark_timing.json"
        print(f"[speed_accuracy] {scene} / {method}: ns-train {shlex.join(command)}", flush=True)
        with open(run_dir / "train.log", "w") as log:
            child = subprocess.Popen(
                [sys.executable, str(Path(__file__).resolve()), TRAIN_CHILD, str(timing_path), *command],
                stdout=log, stderr=subprocess.STDOUT, env=command_environment(),
            )
            _, status, usage = os.wait4(child.pid, 0)
            child.returncode = os.waitstatus_to_exitcode(status)
        if child.returncode != 0:
            log_path = run_dir / "train.log"
            raise RuntimeError(f"ns-train failed ({child.returncode}) for {scene} / {method}: see {log_path}")
        timing = json.loads(timing_path.read_text())
        print(f"[speed_accuracy] {scene} / {method}: trained in {timing['train_seconds']:.1f} s; evaluating",
              flush=True)
        record = {
            "command": command,
            "method": method,
            "scene": scene,
            "iterations": self.iterations,
            "train_seconds": timing["train_seconds"],
            "train_cpu_seconds": timing["train_cpu_seconds"],
            "setup_seconds": timing["setup_seconds"],
            "peak_rss_mib": usage.ru_maxrss / 1024.0,  # Linux: KiB
            "peak_cuda_mib": timing.get("peak_cuda_mib"),
            "checkpoints": evaluate_checkpoints(run_dir / "config.yml", timing["checkpoints"]),
        }
        record_path.write_text(json.dumps(record, indent=1))
        return record

    def budget(self, runs: Dict[str, Dict[str, Any]]) -> float:
        """Equal-time budget of a scene in seconds."""
        if self.time_budget is not None:
            return self.time_budget
        return min(run["train_seconds"] for run in runs.values())

    def report(self, records: Dict[str, Dict[str, Dict[str, Any]]], context: Dict[str, str]) -> str:
        """The markdown: equal-iteration table, equal-time table, targets, command, machine, date."""
        lpips_note = "" if has_lpips() else " LPIPS: missing (AlexNet weights not on disk; nothing downloaded)."
        cuda = self.device == "cuda"
        lines = [
            "# Speed / accuracy benchmark",
            "",
            f"Base preset `{self.base_preset}`, {self.iterations} iterations per method, device {self.device}. "
            f"Synthetic N3D scenes {self.width}x{self.height}, {self.frames} frames, {self.cameras} cameras; "
            f"metrics on every frame of the held-out camera cam00.{lpips_note}",
            "",
            "![PSNR against training time](speed_accuracy.png)",
            "",
            "## Equal iterations",
            "",
            "| scene | method | iterations | training time (s) | ms / iteration | PSNR | SSIM | LPIPS | render FPS "
            "| samples / ray | parameters (in use) | peak RSS (MiB) | training CPU time (s) |"
            + (" peak CUDA (MiB) |" if cuda else ""),
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|" + ("---|" if cuda else ""),
        ]
        for scene, runs in records.items():
            for method, run in runs.items():
                last = run["checkpoints"][-1]
                row = [
                    scene, label(method, run), str(last["step"] + 1), f"{last['seconds']:.1f}",
                    f"{1000 * run['train_seconds'] / run['iterations']:.1f}", f"{last['psnr']:.2f}",
                    f"{last['ssim']:.3f}", fmt_lpips(last), f"{last['fps']:.2f}", f"{last['samples_per_ray']:.1f}",
                    f"{last['parameters']:,} ({last['parameters_in_use']:,})", f"{run['peak_rss_mib']:.0f}",
                    f"{run['train_cpu_seconds']:.1f}",
                ]
                if cuda:
                    row.append("n/a" if run.get("peak_cuda_mib") is None else f"{run['peak_cuda_mib']:.0f}")
                lines.append("| " + " | ".join(row) + " |")
        lines += [
            "",
            "## Equal wall-clock time",
            "",
            "Each method at its last checkpoint whose training time is within the budget"
            + (f" ({self.time_budget:.1f} s)." if self.time_budget is not None else
               " (per scene: the shortest total training time among the methods)."),
            "",
            "| scene | budget (s) | method | checkpoint (iteration) | training time (s) | PSNR | SSIM | LPIPS "
            "| samples / ray |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for scene, runs in records.items():
            budget = self.budget(runs)
            for method, run in runs.items():
                point = at_budget(run, budget)
                if point is None:
                    lines.append(
                        f"| {scene} | {budget:.1f} | {label(method, run)} | none within the budget | | | | | |"
                    )
                    continue
                lines.append(
                    f"| {scene} | {budget:.1f} | {label(method, run)} | {point['step'] + 1} | {point['seconds']:.1f} "
                    f"| {point['psnr']:.2f} | {point['ssim']:.3f} | {fmt_lpips(point)} "
                    f"| {point['samples_per_ray']:.1f} |"
                )
        lines += ["", "## Targets (mixed scene)", ""] + self.targets(records) + [
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
            "writing checkpoints and with in-loop evaluation off (training CPU time: the same interval in CPU "
            "seconds of the training process, less sensitive to other load on the machine); "
            "render FPS: held-out frames per second of "
            "`get_outputs_for_camera`; peak RSS: `ru_maxrss` of the training process.",
            "",
        ]
        return "\n".join(lines)

    def targets(self, records: Dict[str, Dict[str, Dict[str, Any]]]) -> List[str]:
        """Issue targets on the mixed scene, with the measured numbers (met or not)."""
        runs = records.get("mixed", {})
        lines = []
        if "gear-nerf" in runs and "kplanes" in runs:
            budget = self.budget(runs)
            gear, kplanes = at_budget(runs["gear-nerf"], budget), at_budget(runs["kplanes"], budget)
            if gear is None or kplanes is None:
                lines.append(
                    f"- gear-nerf vs plain K-Planes at equal time ({budget:.1f} s): "
                    "a method has no checkpoint within the budget."
                )
            else:
                gain = gear["psnr"] - kplanes["psnr"]
                lines.append(
                    f"- gear-nerf at least 1 dB above plain K-Planes at equal wall time ({budget:.1f} s): "
                    f"{gear['psnr']:.2f} vs {kplanes['psnr']:.2f} dB, difference {gain:+.2f} dB "
                    f"-> {'met' if gain >= 1.0 else 'not met'}"
                )
        if "gear-nerf" in runs and "uniform-128" in runs:
            gear, uniform = runs["gear-nerf"], runs["uniform-128"]
            gear_psnr, uniform_psnr = gear["checkpoints"][-1]["psnr"], uniform["checkpoints"][-1]["psnr"]
            gap = uniform_psnr - gear_psnr
            ratio = (gear["train_seconds"] / gear["iterations"]) / (uniform["train_seconds"] / uniform["iterations"])
            lines.append(
                f"- gear-nerf within 0.3 dB of uniform-128 (equal iterations): {gear_psnr:.2f} vs "
                f"{uniform_psnr:.2f} dB, gap {gap:+.2f} dB -> {'met' if gap <= 0.3 else 'not met'}"
            )
            lines.append(
                f"- at no more than 60 % of its time per iteration: {100 * ratio:.0f} % -> "
                f"{'met' if ratio <= 0.6 else 'not met'}"
            )
        return lines or ["- not evaluated (needs the mixed scene with gear-nerf, kplanes and uniform-128)."]

    def plot(self, records: Dict[str, Dict[str, Dict[str, Any]]], path: Path) -> None:
        """PSNR of the held-out camera against training time: one panel per scene, one curve per method."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        scenes = list(records)
        columns = min(2, len(scenes))
        rows = math.ceil(len(scenes) / columns)
        figure, axes = plt.subplots(rows, columns, figsize=(6.0 * columns, 4.2 * rows), squeeze=False)
        for axis, scene in zip(axes.flat, scenes):
            for method, run in records[scene].items():
                if "same_run_as" in run:
                    continue
                points = run["checkpoints"]
                axis.plot([p["seconds"] for p in points], [p["psnr"] for p in points], marker="o", markersize=3,
                          label=label(method, run, with_alias=records[scene]))
            axis.axvline(self.budget(records[scene]), color="grey", linestyle="--", linewidth=0.8)
            axis.set_title(f"{scene} scene")
            axis.set_xlabel("training time (s)")
            axis.set_ylabel("held-out PSNR (dB)")
            axis.grid(alpha=0.3)
            axis.legend(fontsize=7)
        for axis in list(axes.flat)[len(scenes):]:
            axis.set_visible(False)
        figure.suptitle(f"Held-out PSNR vs training time\n{self.base_preset}, {self.device}, {self.iterations} "
                        "iterations; dashed line: equal-time budget", fontsize=9)
        figure.tight_layout()
        figure.savefig(path, dpi=120)
        plt.close(figure)


def label(method: str, run: Dict[str, Any], with_alias: Optional[Dict[str, Dict[str, Any]]] = None) -> str:
    """Table / legend label; notes a reused run, or (legend) the methods that share this run."""
    text = METHODS.get(method, method)
    if "same_run_as" in run:
        return f"{text} (same configuration and run as {run['same_run_as']})"
    if with_alias:
        aliases = [METHODS.get(m, m) for m, r in with_alias.items() if r.get("same_run_as") == method]
        if aliases:
            text += " = " + " = ".join(aliases)
    return text


def fmt_lpips(point: Dict[str, Any]) -> str:
    return "missing" if point.get("lpips") is None else f"{point['lpips']:.3f}"


def at_budget(run: Dict[str, Any], budget: float) -> Optional[Dict[str, Any]]:
    """The last checkpoint of a run whose training time is within the budget (1 ms tolerance)."""
    within = [p for p in run["checkpoints"] if p["seconds"] <= budget + 1e-3]
    return within[-1] if within else None


def has_lpips() -> bool:
    from gear_nerfstudio.gear_model import lpips_weights_path

    return lpips_weights_path().is_file()


def evaluate_checkpoints(config_path: Path, checkpoints: List[Dict[str, float]]) -> List[Dict[str, Any]]:
    """Held-out metrics, render speed, samples per ray and parameters of each checkpoint of a run.

    The pipeline is set up once (nerfstudio's ``eval_setup``, test split = held-out camera, SAM features
    off: the metrics do not use them); each checkpoint is then loaded into it with nerfstudio's
    ``eval_load_checkpoint``.
    """
    import torch
    from nerfstudio.utils.eval_utils import eval_load_checkpoint, eval_setup

    def no_sam(config):
        config.pipeline.datamanager.use_sam_features = False
        return config

    config, pipeline, _, _ = eval_setup(config_path, test_mode="test", update_config_callback=no_sam)
    model = pipeline.model
    dataset = pipeline.datamanager.eval_dataset
    cuda = torch.device(pipeline.device).type == "cuda"

    def render(index: int) -> Dict[str, Any]:
        return model.get_outputs_for_camera(dataset.cameras[index : index + 1].to(pipeline.device))

    render(0)  # warm-up, untimed
    results = []
    for entry in sorted(checkpoints, key=lambda e: e["step"]):
        config.load_step = int(entry["step"])
        eval_load_checkpoint(config, pipeline)
        metrics: Dict[str, List[float]] = {"psnr": [], "ssim": [], "lpips": []}
        render_seconds = 0.0
        samples, pixels = 0.0, 0
        for index in range(len(dataset)):
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
        total = sum(p.numel() for p in model.parameters())
        unused = sum(p.numel() for p in model.field.parameters()) - model.field.parameters_in_use()
        results.append(
            {
                "step": int(entry["step"]),
                "seconds": float(entry["seconds"]),
                "psnr": mean(metrics["psnr"]),
                "ssim": mean(metrics["ssim"]),
                "lpips": mean(metrics["lpips"]) if metrics["lpips"] else None,
                "fps": len(dataset) / render_seconds,
                "samples_per_ray": samples / pixels,
                "parameters": int(total),
                "parameters_in_use": int(total - unused),
            }
        )
        print(f"[speed_accuracy]   step {entry['step']:>6}  {entry['seconds']:8.1f} s  PSNR {results[-1]['psnr']:.2f}"
              f"  samples/ray {results[-1]['samples_per_ray']:.1f}", flush=True)
    del pipeline, model
    return results


def mean(values: List[float]) -> float:
    return sum(values) / len(values)


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
            f"torch {torch.__version__}")
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
