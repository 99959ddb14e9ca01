"""GPU speed at Neural 3D Video size (21 cameras at 1352 x 1014, synthetic, Technicolor layout): ``gear-nerf``
against its one-gear twin, trained with nerfstudio's own Trainer without viewer, writers or checkpoints. Per method:
pre-training, timed gear updates, host syncs per iteration, windows of timed iterations (ms, rays / s, peak GiB),
full-frame renders, and variants on the same model (chunks, render sample counts, rays per batch, TF32, bfloat16,
torch.compile, profiler, render stages). ``benchmarks/results/gpu_speed.md`` says what each measures."""

from __future__ import annotations

import collections
import contextlib
import copy
import dataclasses
import datetime
import functools
import shlex
import statistics
import sys
import time
import warnings
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, Literal, Optional, Tuple

import torch
from nerfstudio.engine.callbacks import TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer
from torch import Tensor

from benchmarks.common import machine_description, timed
from benchmarks.render_speed import set_render_counts
from gear_nerfstudio.data_parsers.technicolor import TechnicolorDataParserConfig
from gear_nerfstudio.gears.updater import GearUpdater
from gear_nerfstudio.method_configs.gear_nerf import gear_nerf, gear_nerf_baseline
from gear_nerfstudio.model import sampling
from gear_nerfstudio.model.gear_model import evaluating
from gear_nerfstudio.model.metrics import psnr
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene

METHODS = {"gear-nerf": gear_nerf, "gear-nerf-one-gear": gear_nerf, "gear-nerf-baseline": gear_nerf_baseline}
"""``gear-nerf-one-gear``: the gear-nerf preset with N_gear = 1 (K-Planes with the full time axis and uniform
sampling at gear-nerf's sizes, rays and samples): the fair baseline, everything equal but the gears.
``gear-nerf-baseline``: the registered one-gear preset, sized as the small CPU preset."""
HELD_OUT_CAMERA = "10"
"""Held-out camera of the 3 x 7 rig (row 1, column 3: the centre)."""


class Run:
    """One method: its Trainer (set up without viewer, writers or checkpoints) and its measurements."""

    def __init__(self, method: str, args: "GpuSpeed") -> None:
        config = copy.deepcopy(METHODS[method].config)
        config.machine.device_type = args.device
        config.machine.seed = args.seed
        config.vis = "tensorboard"  # no viewer server; no writer is set up either (that happens in Trainer.train)
        config.output_dir = args.output / "runs"
        datamanager = config.pipeline.datamanager
        datamanager.dataparser = TechnicolorDataParserConfig(
            data=args.scene, held_out_camera=HELD_OUT_CAMERA, cache_dir=args.output / "frames"
        )
        datamanager.sam_cache_dir = args.output / "sam"
        if args.model_frames:
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

    def gear_updates(self, count: int) -> List[Dict[str, float]]:
        """Run ``count`` gear updates with the pipeline's own updater; their durations and statistics."""
        (updater,) = [c.func for c in self.trainer.callbacks if isinstance(c.func, GearUpdater)]
        results = []
        for _ in range(count):
            stats: Dict[str, float] = {}
            seconds = self.timed(lambda: stats.update(updater.update(self.step)))
            results.append({"seconds": seconds, **stats})
        return results

    def syncs(self, iterations: int) -> collections.Counter:
        """Host syncs per source line over ``iterations`` training iterations (CUDA's sync debug mode)."""
        counts: collections.Counter = collections.Counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                for _ in range(iterations):
                    self.iteration()
            finally:
                torch.cuda.set_sync_debug_mode("default")
        for warning in caught:
            if "synchronizing" in str(warning.message).lower():
                counts[f"{Path(warning.filename).name}:{warning.lineno}"] += 1
        return counts

    def windows(self, count: int, length: int) -> List[float]:
        """Seconds per iteration of ``count`` windows of ``length`` iterations."""

        def window() -> None:
            for _ in range(length):
                self.iteration()

        return [self.timed(window) / length for _ in range(count)]

    def held_out_camera(self):
        """The first held-out camera, on the model's device."""
        return self.trainer.pipeline.datamanager.eval_dataset.cameras[0:1].to(self.model.device)

    def render(self, count: int) -> Tuple[List[float], Tensor]:
        """Seconds per full-frame render of the held-out camera (after one warm-up render), and the image."""
        camera = self.held_out_camera()
        with evaluating(self.model):
            self.model.get_outputs_for_camera(camera)
            if self.cuda:
                torch.cuda.reset_peak_memory_stats()
            image: Dict[str, Tensor] = {}
            times = [self.timed(lambda: image.update(self.model.get_outputs_for_camera(camera))) for _ in range(count)]
            return times, image["rgb"]

    def profile(self, iterations: int, work: Optional[Callable[[], Any]] = None) -> Tuple[float, float, float, str]:
        """Per call over ``iterations`` profiled calls of ``work`` (a training iteration by default): GPU busy
        milliseconds (the kernels' own time), host milliseconds in operators (the profiler's own overhead included)
        and kernel launches; and the profiler's table of the operators and kernels by their own GPU time."""
        activities = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
        with torch.profiler.profile(activities=activities) as profiler:
            for _ in range(iterations):
                (work or self.iteration)()
            self.synchronize()
        events = profiler.key_averages()
        kernels = [event for event in events if event.device_type == torch.autograd.DeviceType.CUDA]
        busy_ms = sum(event.self_device_time_total for event in kernels) / 1000 / iterations
        host_ms = sum(event.self_cpu_time_total for event in events) / 1000 / iterations
        launches = sum(event.count for event in events if "LaunchKernel" in event.key) / iterations
        return busy_ms, host_ms, launches, events.table(sort_by="self_device_time_total", row_limit=25)

    def render_profile(self) -> Tuple[float, float, float, str]:
        """``profile`` of one full-frame render of the held-out camera (after the renders above warmed it up)."""
        camera = self.held_out_camera()
        with evaluating(self.model):
            return self.profile(1, lambda: self.model.get_outputs_for_camera(camera))


@contextlib.contextmanager
def patched(replacements: List[Tuple[Any, str, Callable[[Callable], Callable]]]) -> Iterator[None]:
    """Inside, ``owner.name`` is ``wrap(owner.name)`` for each (owner, name, wrap); restored afterwards."""
    saved = [(owner, name, name in vars(owner), getattr(owner, name)) for owner, name, _ in replacements]
    for owner, name, wrap in replacements:
        setattr(owner, name, wrap(getattr(owner, name)))
    try:
        yield
    finally:
        for owner, name, own, original in reversed(saved):
            if own:
                setattr(owner, name, original)
            else:
                delattr(owner, name)  # an instance attribute over the class's method


def render_stages(run: Run, count: int) -> Dict[str, float]:
    """Seconds per full-frame render spent in each stage of the render path (``GearNeRFModel.get_outputs``), each
    call synchronised at both ends; nested stages (the proposal networks inside the base sampler, the plane features
    inside the field's density) are also counted in their parents."""
    model, field = run.model, run.model.field
    stages = [
        (model.sampler.base, "forward", "base samples (proposal sampler)"),
        *[(net, "density_fn", "  proposal networks' density") for net in model.proposal_networks],
        (field, "gear_levels", "gear levels of the base samples"),
        (sampling, "split_ray_samples", "split sampler (Sec 4.4)"),
        (field.gear_function, "forward", "gear function g (Eq 4), every call (the gear levels' included)"),
        (field, "normalised_density", "field density"),
        (field, "gear_features", "  plane features f (Eq 3, 6-7)"),
        (field, "colour", "colour of the visible samples"),
    ]
    spent = {label: 0.0 for _, _, label in stages}

    def timer(label: str) -> Callable[[Callable], Callable]:
        def wrap(function: Callable) -> Callable:
            def timed_call(*args: Any, **kwargs: Any) -> Any:
                run.synchronize()
                start = time.perf_counter()
                result = function(*args, **kwargs)
                run.synchronize()
                spent[label] += time.perf_counter() - start
                return result

            return timed_call

        return wrap

    with patched([(owner, name, timer(label)) for owner, name, label in stages]):
        times, _ = run.render(count)  # the warm-up render inside is counted too: count + 1 renders
    return {"render": statistics.median(times), **{label: seconds / (count + 1) for label, seconds in spent.items()}}


@contextlib.contextmanager
def compiled_densities(model) -> Iterator[None]:
    """Inside, the proposal networks' ``density_fn`` and the field's ``normalised_density`` run through
    ``torch.compile`` (dynamic shapes: a render's chunks differ in size)."""
    compiled = functools.partial(torch.compile, dynamic=True)
    owners = [*model.proposal_networks, model.field]
    names = ["density_fn"] * len(model.proposal_networks) + ["normalised_density"]
    with patched([(owner, name, compiled) for owner, name in zip(owners, names)]):
        yield


def variants(run: Run, args: "GpuSpeed", reference: Tensor) -> List[Dict[str, Any]]:
    """The variants of step 6 on ``run``'s trained model, each restored afterwards: the renders first, while the
    model is the one that rendered ``reference``."""
    rows: List[Dict[str, Any]] = []
    config = run.model.config

    def render(variant: str) -> None:
        times, image = run.render(args.renders)
        memory = torch.cuda.max_memory_allocated() if run.cuda else None
        rows.append({"variant": variant, "renders": times, "image": image.float(), "memory": memory})

    if args.render_profile and run.cuda:
        busy_ms, host_ms, launches, table = run.render_profile()
        rows.append({"variant": "render, profiled", "busy_ms": busy_ms, "host_ms": host_ms, "launches": launches})
        args.output.mkdir(parents=True, exist_ok=True)
        (args.output / f"gpu_render_profile_{run.method}.txt").write_text(table)
    if args.render_bf16:
        with torch.autocast(device_type=run.model.device.type, dtype=torch.bfloat16):
            render("render, bfloat16 autocast")
    if args.render_compile:
        with compiled_densities(run.model):
            render("render, density functions compiled (torch.compile, dynamic shapes; compiled in the warm-up)")
    for chunk in args.render_chunks:
        config.render.chunk_samples = chunk
        render(f"render, chunks of {chunk:,} samples")
    config.render.chunk_samples = args.samples_chunk
    for counts in args.render_samples:
        set_render_counts(config, counts)
        chunk = f", chunks of {args.samples_chunk:,} samples" if args.samples_chunk else ""
        render(f"render, samples {counts}{chunk}")
    config.render.num_samples = config.render.num_proposal_samples = config.render.chunk_samples = None
    for row in rows:
        if "image" in row:
            row["psnr"] = float(psnr(row.pop("image"), reference))
    sampler = run.trainer.pipeline.datamanager.train_pixel_sampler
    default_rays = sampler.num_rays_per_batch
    for rays in args.batches:
        sampler.num_rays_per_batch = rays
        run.windows(1, args.window)  # warm-up at the new size
        rows.append({"variant": f"training, {rays} rays / batch", "rays": rays,
                     "windows": run.windows(args.windows // 2, args.window)})  # fmt: skip
    sampler.num_rays_per_batch = default_rays
    if args.tf32:  # windows with and without TF32 in turn, so that both see the same stretch of training
        timings: Dict[bool, List[float]] = {False: [], True: []}
        default_tf32 = torch.backends.cuda.matmul.allow_tf32
        for _ in range(args.windows // 2):
            for tf32 in (False, True):
                torch.backends.cuda.matmul.allow_tf32 = tf32
                timings[tf32] += run.windows(1, args.window)
        torch.backends.cuda.matmul.allow_tf32 = default_tf32
        for tf32, label in ((False, "float32"), (True, "TF32")):
            rows.append({"variant": f"training, {default_rays} rays / batch, {label} (in turn)", "rays": default_rays,
                         "windows": timings[tf32]})  # fmt: skip
    if args.profile and run.cuda:
        busy_ms, host_ms, launches, table = run.profile(args.profile)
        rows.append({"variant": "training, profiled", "busy_ms": busy_ms, "host_ms": host_ms, "launches": launches})
        args.output.mkdir(parents=True, exist_ok=True)
        (args.output / f"gpu_profile_{run.method}.txt").write_text(table)
    return rows


def measure(method: str, args: "GpuSpeed") -> Dict[str, Any]:
    run = Run(method, args)
    for _ in range(args.pretrain):
        run.iteration()
    updates = run.gear_updates(args.updates) if run.model.num_gears > 1 else []
    syncs = run.syncs(args.sync_iterations) if run.cuda else None
    for _ in range(args.warmup):
        run.iteration()
    if run.cuda:
        torch.cuda.reset_peak_memory_stats()
    run.samples_per_ray.clear()
    windows = run.windows(args.windows, args.window)
    train_memory = torch.cuda.max_memory_allocated() if run.cuda else None
    samples_per_ray = float(torch.stack(run.samples_per_ray).mean())
    renders, image = run.render(args.renders)
    render_memory = torch.cuda.max_memory_allocated() if run.cuda else None
    datamanager = run.trainer.pipeline.datamanager
    camera = datamanager.eval_dataset.cameras
    result = {
        "method": method,
        "rays": datamanager.config.train_num_rays_per_batch,
        "base_samples": run.model.config.num_samples,
        "frames": run.model.num_frames,
        "windows": windows,
        "samples_per_ray": samples_per_ray,
        "train_memory": train_memory,
        "renders": renders,
        "render_size": (int(camera.width[0]), int(camera.height[0])),
        "render_memory": render_memory,
        "updates": updates,
        "syncs": syncs,
        "sync_iterations": args.sync_iterations,
        "parameters": sum(p.numel() for p in run.model.parameters()),
        "variants": variants(run, args, image),
        "stages": render_stages(run, args.renders) if args.render_stages else {},
    }
    del run
    if args.device == "cuda":
        torch.cuda.empty_cache()
    return result


def gib(value: Any) -> str:
    return "not measured (CPU)" if value is None else f"{value / 2**30:.2f}"


def markdown(results: List[Dict[str, Any]], args: "GpuSpeed", command: str) -> str:
    lines = [
        "# GPU speed at Neural 3D Video size: gear-nerf and the one-gear baseline",
        "",
        f"Command: `{command}`",
        "",
        f"Machine: {machine_description(args.device)}. Date: {datetime.date.today().isoformat()}.",
        "",
        f"Scene: synthetic (`gear_nerfstudio.tools.synthetic`, mixed motion), Technicolor layout, {args.rows} x "
        f"{args.cols} = {args.rows * args.cols} cameras at {args.width} x {args.height} (N3D's camera count and its "
        f"usual downscale-2 resolution), {args.frames} frames; held-out camera {HELD_OUT_CAMERA}. "
        + (
            f"The models' planes are sized for {args.model_frames} frames (model `num_frames`), as for a "
            f"{args.model_frames}-frame N3D video; the images span {args.frames} frames."
            if args.model_frames
            else "The models' planes are sized for the scene's frames."
        ),
        "",
        f"Per method: {args.pretrain} training iterations, then (gear-nerf) {args.updates} gear updates by the "
        f"pipeline's `GearUpdater`, then {args.warmup} warm-up iterations and {args.windows} windows of {args.window} "
        f"timed iterations (`torch.cuda.synchronize` at window edges only). Seed {args.seed}.",
        "",
        "| method | rays / batch | base samples n | samples / ray (mean) | iteration ms: median [quartiles] (range) "
        "| rays / s | peak train GiB | render ms / frame (FPS) | peak render GiB | parameters |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in results:
        ms = [1000 * w for w in r["windows"]]
        q1, _, q3 = statistics.quantiles(ms, n=4)
        median = statistics.median(ms)
        render_ms = 1000 * statistics.median(r["renders"])
        lines.append(
            f"| {r['method']} | {r['rays']} | {r['base_samples']} | {r['samples_per_ray']:.1f} | {median:.1f} "
            f"[{q1:.1f}, {q3:.1f}] ({min(ms):.1f}-{max(ms):.1f}) | {r['rays'] / median * 1000:,.0f} "
            f"| {gib(r['train_memory'])} | {render_ms:.0f} ({1000 / render_ms:.2f}) | {gib(r['render_memory'])} "
            f"| {r['parameters']:,} |"
        )
    width, height = results[0]["render_size"]
    lines += ["", f"Render: one full {width} x {height} frame, median of {args.renders}.", ""]
    if any(r["variants"] for r in results):
        lines += [
            "Variants on the same trained model (training: median of the windows; renders: median, and PSNR against "
            "the render of the row above):",
            "",
            "| method | variant | iteration ms: median (range) or render ms | rays / s or FPS | PSNR vs row above (dB) "
            "| peak render GiB | profiled: GPU busy ms, host ms, kernel launches / iteration |",
            "| --- | --- | --- | --- | --- | --- | --- |",
        ]
        for r in results:
            for v in r["variants"]:
                cells = [""] * 5
                if "windows" in v:
                    ms = [1000 * w for w in v["windows"]]
                    median = statistics.median(ms)
                    cells[:2] = f"{median:.1f} ({min(ms):.1f}-{max(ms):.1f})", f"{v['rays'] / median * 1000:,.0f}"
                elif "renders" in v:
                    ms = 1000 * statistics.median(v["renders"])
                    cells[:4] = f"{ms:.0f}", f"{1000 / ms:.2f}", f"{v['psnr']:.1f}", gib(v["memory"])
                else:
                    cells[4] = f"{v['busy_ms']:.1f}, {v['host_ms']:.1f}, {v['launches']:.0f}"
                lines.append("| " + " | ".join([r["method"], v["variant"], *cells]) + " |")
        lines.append("")
    for r in results:
        if r["stages"]:
            lines += [
                f"Render stages of {r['method']} (seconds per frame, every stage synchronised at both ends, so the "
                f"render takes {r['stages']['render']:.2f} s here; an indented stage is counted in the one above it "
                "too):",
                "",
                *[f"- {label}: {seconds:.3f}" for label, seconds in r["stages"].items() if label != "render"],
                "",
            ]
    for r in results:
        if r["updates"]:
            lines.append(
                f"Gear updates of {r['method']} (seconds each; gear shares of the views' visible surface after it):"
            )
            lines.append("")
            for k, update in enumerate(r["updates"], start=1):
                shares = " ".join(f"{update[key]:.2f}" for key in sorted(update) if key.startswith("gear_"))
                lines.append(
                    f"- update {k}: {update['seconds']:.2f} s, upshift mask area "
                    f"{update.get('upshift_mask_area', float('nan')):.2f}, gears 1-{len(shares.split())}: {shares}"
                )
            lines.append("")
    for r in results:
        if r["syncs"] is None:
            lines.append(f"Host syncs of {r['method']}: not measured (sync debug mode needs CUDA).")
            continue
        total = sum(r["syncs"].values()) / r["sync_iterations"]
        where = ", ".join(f"{place} x{count / r['sync_iterations']:g}" for place, count in r["syncs"].most_common())
        lines.append(f"Host syncs of {r['method']} per training iteration: {total:g} ({where or 'none'}).")
        lines.append("")
    return "\n".join(lines) + "\n"


@dataclasses.dataclass
class GpuSpeed:
    """Train both methods at N3D size and time iterations, gear updates and renders; write ``gpu_speed.md``."""

    methods: Tuple[Literal["gear-nerf", "gear-nerf-one-gear", "gear-nerf-baseline"], ...] = tuple(METHODS)  # type: ignore
    device: Literal["cuda", "cpu"] = "cuda"
    scene: Path = Path("outputs/gpu_speed/scene")
    """Synthetic scene folder, written if missing."""
    width: int = 1352
    height: int = 1014
    rows: int = 3
    cols: int = 7
    frames: int = 6
    model_frames: int = 300
    """The model's num_frames (planes' rows); 0: the scene's."""
    pretrain: int = 300
    updates: int = 2
    sync_iterations: int = 5
    warmup: int = 20
    window: int = 10
    windows: int = 20
    renders: int = 3
    seed: int = 42
    batches: Tuple[int, ...] = ()
    """Also train at these rays per batch."""
    tf32: bool = False
    """Also train with and without TF32 products in turn."""
    render_chunks: Tuple[int, ...] = ()
    """Also render at these chunk sizes (field samples)."""
    render_samples: Tuple[str, ...] = ()
    """Also render at these sample counts, "P1,P2,N" each."""
    samples_chunk: Optional[int] = None
    """Chunk size of the --render-samples renders."""
    profile: int = 0
    """Profile this many training iterations (CUDA)."""
    render_profile: bool = False
    render_bf16: bool = False
    render_compile: bool = False
    render_stages: bool = False
    output: Path = Path("outputs/gpu_speed")
    results: Optional[Path] = None
    """Also write gpu_speed.md here."""

    def main(self) -> None:
        command = "python -m benchmarks " + shlex.join(sys.argv[1:])
        if not (self.scene / "cameras_parameters.txt").is_file():
            spec = SyntheticSpec(dataset="technicolor", width=self.width, height=self.height, frames=self.frames,
                                 rows=self.rows, cols=self.cols)  # fmt: skip
            write_synthetic_scene(self.scene, spec)
        results = []
        for method in self.methods:
            results.append(measure(method, self))
            print(markdown(results, self, command), flush=True)
        for folder in [self.output] + ([self.results] if self.results else []):
            folder.mkdir(parents=True, exist_ok=True)
            (folder / "gpu_speed.md").write_text(markdown(results, self, command))
