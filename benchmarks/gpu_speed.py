"""GPU speed at Neural 3D Video size (21 cameras at 1352 x 1014, synthetic): ``gear-nerf`` against its one-gear twin in
nerfstudio's own Trainer; ``benchmarks/results/gpu_speed.md`` says what each column measures."""

from __future__ import annotations

import copy
import dataclasses
import statistics
from pathlib import Path
from typing import Any, Callable, Dict, List, Literal, Optional, Tuple

import torch
from nerfstudio.engine.callbacks import TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer
from torch import Tensor

from benchmarks.common import page, table, timed, write_report
from gear_nerfstudio.data_parsers.technicolor import TechnicolorDataParserConfig
from gear_nerfstudio.gears.updater import GearUpdater
from gear_nerfstudio.method_configs.gear_nerf import gear_nerf
from gear_nerfstudio.model.gear_model import evaluating
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene

METHODS = ("gear-nerf", "gear-nerf-one-gear")
"""``gear-nerf-one-gear``: the gear-nerf preset with N_gear = 1 (K-Planes with the full time axis and uniform
sampling at gear-nerf's sizes, rays and samples): the fair baseline, everything equal but the gears."""
HELD_OUT_CAMERA = "10"
"""Held-out camera of the 3 x 7 rig (row 1, column 3: the centre)."""


class Run:
    """One method: its Trainer (set up without viewer, writers or checkpoints) and its measurements."""

    def __init__(self, method: str, args: "GpuSpeed") -> None:
        config = copy.deepcopy(gear_nerf.config)
        config.machine.device_type = args.device
        config.machine.seed = args.seed
        config.vis = "tensorboard"  # no viewer server; no writer is set up either (that happens in Trainer.train)
        config.output_dir = args.output / "runs"
        datamanager = config.pipeline.datamanager
        datamanager.dataparser = TechnicolorDataParserConfig(
            data=args.scene, held_out_camera=HELD_OUT_CAMERA, cache_dir=args.output / "frames"
        )
        datamanager.sam_cache_dir = args.output / "sam"
        config.pipeline.model.num_frames = args.model_frames
        if method == "gear-nerf-one-gear":
            config.pipeline.model.num_gears = 1
        self.method = method
        self.cuda = args.device == "cuda"
        self.trainer: Trainer = config.setup(local_rank=0, world_size=1)
        self.trainer.setup()
        self.step = 0
        self.samples_per_ray: List[Tensor] = []

    @property
    def model(self):
        return self.trainer.pipeline.model

    def synchronize(self) -> None:
        if self.cuda:
            torch.cuda.synchronize()

    def iteration(self) -> None:
        """One training iteration as ``Trainer.train`` runs it."""
        for callback in self.trainer.callbacks:
            callback.run_callback_at_location(self.step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        _, _, metrics = self.trainer.train_iteration(self.step)
        for callback in self.trainer.callbacks:
            callback.run_callback_at_location(self.step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
        self.samples_per_ray.append(metrics["samples_per_ray"].detach())
        self.step += 1

    def timed(self, function: Callable[[], Any]) -> float:
        """Seconds of ``function()``, with the device synchronised at both ends."""
        return timed(function, 1, self.synchronize)[0]

    def gear_updates(self, count: int) -> None:
        """Run ``count`` gear updates with the pipeline's own updater."""
        (updater,) = [c.func for c in self.trainer.callbacks if isinstance(c.func, GearUpdater)]
        for _ in range(count):
            updater.update(self.step)

    def windows(self, count: int, length: int) -> List[float]:
        """Seconds per iteration of ``count`` windows of ``length`` iterations."""

        def window() -> None:
            for _ in range(length):
                self.iteration()

        return [self.timed(window) / length for _ in range(count)]

    def render(self, count: int) -> List[float]:
        """Seconds per full-frame render of the held-out camera (after one warm-up render)."""
        camera = self.trainer.pipeline.datamanager.eval_dataset.cameras[0:1].to(self.model.device)
        with evaluating(self.model):
            self.model.get_outputs_for_camera(camera)
            if self.cuda:
                torch.cuda.reset_peak_memory_stats()
            return [self.timed(lambda: self.model.get_outputs_for_camera(camera)) for _ in range(count)]

    def profile(self, iterations: int) -> Dict[str, float]:
        """Per training iteration, over ``iterations`` profiled ones: GPU busy ms (the kernels' own time), host ms
        in operators (the profiler's overhead included) and kernel launches."""
        activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
        with torch.profiler.profile(activities=activities) as profiler:
            for _ in range(iterations):
                self.iteration()
            self.synchronize()
        events = profiler.key_averages()
        kernels = [event for event in events if event.device_type == torch.autograd.DeviceType.CUDA]
        return {
            "busy_ms": sum(event.self_device_time_total for event in kernels) / 1000 / iterations,
            "host_ms": sum(event.self_cpu_time_total for event in events) / 1000 / iterations,
            "launches": sum(event.count for event in events if "LaunchKernel" in event.key) / iterations,
        }


def measure(method: str, args: "GpuSpeed") -> Dict[str, Any]:
    """Pre-training, gear updates, timed windows, renders and profiled iterations of one method."""
    run = Run(method, args)
    for _ in range(args.pretrain):
        run.iteration()
    if run.model.num_gears > 1:
        run.gear_updates(args.updates)
    for _ in range(args.warmup):
        run.iteration()
    if run.cuda:
        torch.cuda.reset_peak_memory_stats()
    run.samples_per_ray.clear()
    windows = run.windows(args.windows, args.window)
    train_memory = torch.cuda.max_memory_allocated() if run.cuda else None
    renders = run.render(args.renders)
    datamanager = run.trainer.pipeline.datamanager
    camera = datamanager.eval_dataset.cameras
    result = {
        "method": method, "rays": datamanager.config.train_num_rays_per_batch,
        "base_samples": run.model.config.num_samples, "windows": windows,
        "samples_per_ray": float(torch.stack(run.samples_per_ray).mean()), "train_memory": train_memory,
        "renders": renders, "render_size": (int(camera.width[0]), int(camera.height[0])),
        "render_memory": torch.cuda.max_memory_allocated() if run.cuda else None,
        "parameters": sum(p.numel() for p in run.model.parameters()),
        "profile": run.profile(args.profile) if args.profile and run.cuda else None,
    }  # fmt: skip
    del run
    if args.device == "cuda":
        torch.cuda.empty_cache()
    return result


def gib(value: Any) -> str:
    return "not measured (CPU)" if value is None else f"{value / 2**30:.2f}"


def iteration_ms(windows: List[float], rays: int) -> Tuple[str, str]:
    """Median ms per iteration [quartiles] (range), and rays per second, of timed windows."""
    ms = [1000 * w for w in windows]
    median, (q1, _, q3) = statistics.median(ms), statistics.quantiles(ms, n=4)
    return f"{median:.1f} [{q1:.1f}, {q3:.1f}] ({min(ms):.1f}-{max(ms):.1f})", f"{rays / median * 1000:,.0f}"


def markdown(results: List[Dict[str, Any]], args: "GpuSpeed") -> str:
    rows, lines = [], []
    for r in results:
        render_ms = 1000 * statistics.median(r["renders"])
        rows.append([r["method"], r["rays"], r["base_samples"], f"{r['samples_per_ray']:.1f}",
                     *iteration_ms(r["windows"], r["rays"]), gib(r["train_memory"]),
                     f"{render_ms:.0f} ({1000 / render_ms:.2f})", gib(r["render_memory"]), f"{r['parameters']:,}"])
        if r["profile"] is not None:
            p = r["profile"]
            lines += ["", f"{r['method']}, {args.profile} training iterations profiled, per iteration: GPU busy "
                      f"{p['busy_ms']:.1f} ms, host {p['host_ms']:.1f} ms, {p['launches']:.0f} kernel launches."]
    header = ["method", "rays / batch", "base samples n", "samples / ray (mean)",
              "iteration ms: median [quartiles] (range)", "rays / s", "peak train GiB", "render ms / frame (FPS)",
              "peak render GiB", "parameters"]  # fmt: skip
    width, height = results[0]["render_size"]
    return page("GPU speed at Neural 3D Video size: gear-nerf and the one-gear baseline", [
        f"Scene: synthetic (mixed motion), Technicolor layout, {args.rows} x {args.cols} cameras at {args.width} x "
        f"{args.height}, {args.frames} frames, held-out camera {HELD_OUT_CAMERA}; planes sized for {args.model_frames} "
        f"frames. Per method: {args.pretrain} training iterations, {args.updates} gear updates (gear-nerf), "
        f"{args.warmup} warm-up iterations, {args.windows} timed windows of {args.window} iterations. Renders: one "
        f"full {width} x {height} frame, median of {args.renders}. Seed {args.seed}.",
        "", *table(header, rows), *lines,
    ], args.device)  # fmt: skip


@dataclasses.dataclass
class GpuSpeed:
    """Train both methods at N3D size and time iterations and renders; write ``gpu_speed.md``."""

    methods: Tuple[Literal["gear-nerf", "gear-nerf-one-gear"], ...] = METHODS
    device: Literal["cuda", "cpu"] = "cuda"
    scene: Path = Path("outputs/gpu_speed/scene")
    """Synthetic scene folder, written if missing."""
    width: int = 1352
    height: int = 1014
    rows: int = 3
    cols: int = 7
    frames: int = 6
    model_frames: int = 300
    """The model's num_frames (planes' rows)."""
    pretrain: int = 300
    updates: int = 2
    warmup: int = 20
    window: int = 10
    windows: int = 20
    renders: int = 3
    seed: int = 42
    profile: int = 0
    """Also profile this many training iterations (CUDA): GPU busy ms, host ms and kernel launches per iteration."""
    output: Path = Path("outputs/gpu_speed")
    results: Optional[Path] = None
    """Also write gpu_speed.md here."""

    def main(self) -> None:
        if not (self.scene / "cameras_parameters.txt").is_file():
            spec = SyntheticSpec(dataset="technicolor", width=self.width, height=self.height, frames=self.frames,
                                 rows=self.rows, cols=self.cols)  # fmt: skip
            write_synthetic_scene(self.scene, spec)
        results = []
        for method in self.methods:
            results.append(measure(method, self))
            print(markdown(results, self), flush=True)
        paths = [folder / "gpu_speed.md" for folder in (self.output, self.results) if folder is not None]
        write_report(markdown(results, self), *paths)
