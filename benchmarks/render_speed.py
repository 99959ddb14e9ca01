"""Render and training speed of trained Gear-NeRF runs: full-image render time per frame, pixels per second and
samples per ray of the model's render path (``GearNeRFModel.get_outputs_for_camera_ray_bundle``) against nerfstudio's
generic path on the same checkpoint in the same process (``Model.get_outputs_for_camera_ray_bundle``: chunks of
``eval_num_rays_per_chunk`` rays through ``get_outputs``, every output), the image difference between the two, both
images' PSNR against the held-out frames, and training rays per second (nerfstudio's ``Trainer.train_iteration``).

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/render_speed.py <run>/config.yml [<run>/config.yml ...] \\
        --output benchmarks/results/render_speed.md --images benchmarks/results

Each render is timed ``--repeats`` times (median) on ``--frames`` held-out frames evenly spaced over the video; the
training rate is the median of ``--train-windows`` windows of 10 iterations after 5 warm-up iterations, on a copy of
the run's model (the run folder is not written to).

With ``--samples 32,16,12 ...`` it measures instead the model's render at other render sample counts
(``--pipeline.model.render-num-proposal-samples 32 16 --pipeline.model.render-num-samples 12``) against the run's own.
"""

from __future__ import annotations

import argparse
import contextlib
import platform
import statistics
import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch
from nerfstudio.models.base_model import Model
from PIL import Image
from torch import Tensor
from nerfstudio.utils.eval_utils import eval_setup

from gear_nerfstudio.model.metrics import psnr


def timed(function, repeats: int):
    """(median seconds, last result) of ``repeats`` calls."""
    times, result = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def save_strip(path: Path, truth: Tensor, generic: Tensor, rendered: Tensor) -> None:
    """The held-out frame, nerfstudio's render, the model's render and their difference x 100, side by side."""
    difference = ((rendered - generic).abs() * 100).clamp(0, 1)
    strip = torch.cat([truth, generic, rendered, difference], dim=1).clamp(0, 1)
    Image.fromarray((strip.cpu().numpy() * 255).round().astype(np.uint8)).save(path)


def render_rows(config: Path, frames: int, repeats: int, images: Optional[Path]) -> Dict[str, float]:
    """Render measurements of one run, averaged over its held-out frames; the first frame's images saved as
    ``images/<run>.png`` when ``images`` is given."""
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    rows: Dict[str, List[float]] = {}
    for index in np.linspace(0, len(dataset) - 1, frames).round().astype(int):
        camera = dataset.cameras[int(index) : int(index) + 1].to(model.device)
        rays = camera.generate_rays(camera_indices=0, keep_shape=True)
        truth = dataset.get_image_float32(int(index))[..., :3].to(model.device)
        with torch.no_grad():
            generic_s, generic = timed(lambda: Model.get_outputs_for_camera_ray_bundle(model, rays), repeats)
            # code from before the model's own render path (issue 25) has no `rendering`: both columns are then generic
            with getattr(model, "rendering", lambda _: contextlib.nullcontext())("num_samples"):
                model_s, rendered = timed(lambda: model.get_outputs_for_camera_ray_bundle(rays), repeats)
        difference = (rendered["rgb"] - generic["rgb"]).abs()
        if images is not None and not rows:
            images.mkdir(parents=True, exist_ok=True)
            name = "_".join(config.parent.parts[-3:])
            save_strip(images / f"render_speed_{name}.png", truth, generic["rgb"], rendered["rgb"])
        for name, value in {
            "pixels": rays.shape.numel(),
            "generic_s": generic_s,
            "model_s": model_s,
            "samples_per_ray": float(rendered["num_samples"].mean()),
            "generic_psnr": float(psnr(generic["rgb"], truth)),
            "model_psnr": float(psnr(rendered["rgb"], truth)),
            "max_difference": float(difference.max()),
            "difference_psnr": float(psnr(rendered["rgb"], generic["rgb"])),
        }.items():
            rows.setdefault(name, []).append(value)
    return {name: float(np.mean(values)) for name, values in rows.items()}


def set_render_counts(model_config, counts: str) -> None:
    """Set a model config's render sample counts from "P1,P2,N" (the proposal iterations' counts, then n)."""
    *proposal, model_config.render_num_samples = (int(value) for value in counts.split(","))
    model_config.render_num_proposal_samples = tuple(proposal) or None


def sample_rows(config: Path, frames: int, repeats: int, variants: List[str]) -> List[str]:
    """Table rows of the model's render path at other render sample counts (``render_num_proposal_samples`` and
    ``render_num_samples``, given as "64,32,24": the proposal iterations' counts, then n) against the run's own:
    seconds per frame, pixels per second, PSNR against the held-out frames and against the render at the run's
    counts, averaged over the held-out frames."""
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
    indices = np.linspace(0, len(dataset) - 1, frames).round().astype(int)
    cameras = [dataset.cameras[int(i) : int(i) + 1].to(model.device) for i in indices]
    bundles = [camera.generate_rays(camera_indices=0, keep_shape=True) for camera in cameras]
    truths = [dataset.get_image_float32(int(i))[..., :3].to(model.device) for i in indices]
    own = ",".join(str(n) for n in (*model.config.num_proposal_samples, model.config.num_samples))
    model.get_outputs_for_camera_ray_bundle(bundles[0])  # warm-up: the first render of a process is slower
    references, rows = None, []
    for variant in [own, *variants]:
        set_render_counts(model.config, variant)
        seconds, psnrs, renders = [], [], []
        for rays, truth in zip(bundles, truths):
            time_s, rendered = timed(lambda: model.get_outputs_for_camera_ray_bundle(rays)["rgb"], repeats)
            seconds.append(time_s)
            psnrs.append(float(psnr(rendered, truth)))
            renders.append(rendered)
        references = references or renders
        differences = [float(psnr(rendered, reference)) for rendered, reference in zip(renders, references)]
        pixels = bundles[0].shape.numel()
        label = f"{variant} (the run's)" if variant == own else variant
        rows.append(
            f"| {config.parent} | {label} | "
            f"{np.mean(seconds):.2f} | {pixels / np.mean(seconds):,.0f} | {np.mean(psnrs):.3f} | "
            f"{np.mean(differences):.1f} |"
        )
        print(rows[-1], flush=True)
    return rows


def training_rate(config: Path, windows: int) -> float:
    """Median training rays per second of ``Trainer.train_iteration`` on the run's checkpoint."""
    trainer_config, _, _, _ = eval_setup(config, test_mode="test")
    trainer_config.load_dir = config.parent / "nerfstudio_models"
    trainer_config.output_dir = Path("/tmp/render_speed")  # the run folder is never written
    trainer_config.vis = "tensorboard"
    trainer = trainer_config.setup(local_rank=0, world_size=1)
    trainer.setup()
    rays = trainer.pipeline.datamanager.config.train_num_rays_per_batch
    step = trainer._start_step
    for _ in range(5):
        trainer.train_iteration(step)
        step += 1
    rates = []
    for _ in range(windows):
        start = time.perf_counter()
        for _ in range(10):
            trainer.train_iteration(step)
            step += 1
        rates.append(10 * rays / (time.perf_counter() - start))
    return statistics.median(rates)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("configs", nargs="+", type=Path, help="config.yml of trained runs")
    parser.add_argument("--frames", type=int, default=3, help="held-out frames per run")
    parser.add_argument("--repeats", type=int, default=3, help="timings per render (median)")
    parser.add_argument("--train-windows", type=int, default=5, help="windows of 10 training iterations (median)")
    parser.add_argument("--output", type=Path, default=None, help="append the table to this Markdown file")
    parser.add_argument("--images", type=Path, default=None, help="save each run's first frame side by side here")
    parser.add_argument(
        "--samples", nargs="+", default=None, metavar="P1,P2,N",
        help="instead: the render at these render sample counts (proposal iterations' counts, then n) against the "
        "run's own",
    )  # fmt: skip
    args = parser.parse_args()
    if args.samples is not None:
        header = (
            "| run | render samples: proposal iterations, n | render s / frame | pixels / s | PSNR (dB) | "
            "PSNR against the run's own counts (dB) |"
        )
        lines = [machine_line(), "", header, "|" + " --- |" * (header.count("|") - 1)]
        for config in args.configs:
            lines += sample_rows(config, args.frames, args.repeats, args.samples)
        write(lines, args.output)
        return
    header = (
        "| run | pixels | render s / frame: generic -> model (speed-up) | pixels / s (model) | samples / ray | "
        "PSNR generic / model (dB) | model vs generic: max abs diff, PSNR (dB) | training rays / s |"
    )
    lines = [machine_line(), "", header, "|" + " --- |" * (header.count("|") - 1)]
    for config in args.configs:
        row = render_rows(config, args.frames, args.repeats, args.images)
        rate = training_rate(config, args.train_windows)
        speed_up = row["generic_s"] / row["model_s"]
        lines.append(
            f"| {config.parent} | {row['pixels']:.0f} | "
            f"{row['generic_s']:.2f} -> {row['model_s']:.2f} ({speed_up:.2f}x) | "
            f"{row['pixels'] / row['model_s']:,.0f} | {row['samples_per_ray']:.1f} | "
            f"{row['generic_psnr']:.3f} / {row['model_psnr']:.3f} | "
            f"{row['max_difference']:.2g}, {row['difference_psnr']:.1f} | {rate:,.0f} |"
        )
        print(lines[-1], flush=True)
    write(lines, args.output)


def machine_line() -> str:
    """The machine, torch and device, for the tables."""
    device = f"cuda {torch.cuda.get_device_name()}" if torch.cuda.is_available() else "cpu"
    return (
        f"Machine: {platform.machine()} {platform.processor() or ''}, {torch.get_num_threads()} torch threads, "
        f"torch {torch.__version__}, device {device}."
    )


def write(lines: List[str], output: Optional[Path]) -> None:
    """Print the table and append it to ``output`` (Markdown) when given."""
    text = "\n".join(lines) + "\n"
    print(text)
    if output is not None:
        with output.open("a") as handle:
            handle.write(text + "\n")


if __name__ == "__main__":
    main()
