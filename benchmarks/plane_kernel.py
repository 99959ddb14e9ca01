"""The field's plane lookups, full-frame renders and training iterations with the torch path and the Warp kernel
side by side on one checkpoint, interleaved; times are this process's CPU seconds (or wall seconds), best of
``--repeats``."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import torch
import tyro
from nerfstudio.utils.eval_utils import eval_setup

from gear_nerfstudio.model.metrics import psnr

KINDS = ("torch", "warp")


def best(function, model: torch.nn.Module, repeats: int, clock=time.process_time):
    """{kind: (best seconds on ``clock``, last result)} of ``function`` with each plane kernel in the model's fields
    (radiance field, gear function and proposal networks), the kinds interleaved."""
    results = {}
    for _ in range(repeats):
        for kind in KINDS:
            for module in model.modules():
                if hasattr(module, "plane_kernel"):
                    module.plane_kernel = kind
            start = clock()
            result = function()
            seconds = clock() - start
            results[kind] = (min(seconds, results.get(kind, (seconds,))[0]), result)
    return results


@dataclasses.dataclass
class PlaneKernel:
    """The torch path against the Warp kernel on one trained run (lookups, a full frame, training iterations)."""

    config: tyro.conf.Positional[Path]
    """config.yml of a trained run."""
    repeats: int = 5
    """Timings per path (the best is kept)."""
    frame: int = 0
    """Held-out frame to render."""
    train_iterations: int = 10
    """Training iterations per timing."""
    wall_time: bool = False
    """Time by the wall clock, for runs on several threads (``OMP_NUM_THREADS``), instead of the process's CPU time."""

    def main(self) -> None:
        trainer_config, pipeline, _, _ = eval_setup(self.config, test_mode="test")
        model, dataset = pipeline.model, pipeline.datamanager.eval_dataset
        field = model.field
        camera = dataset.cameras[self.frame : self.frame + 1].to(model.device)
        rays = camera.generate_rays(camera_indices=0, keep_shape=True)
        truth = dataset.get_image_float32(self.frame)[..., :3]

        # the inputs of the field's lookups in the first chunk of the render
        chunk, lookups = [], field.gear_features
        field.gear_features = lambda *inputs: chunk.append(inputs) or lookups(*inputs)
        model.get_outputs_for_camera_ray_bundle(rays)
        field.gear_features = lookups
        x, t, levels = chunk[0]

        def forward_backward():
            field.gear_features(x, t, levels).sum().backward()

        clock = time.perf_counter if self.wall_time else time.process_time
        with torch.no_grad():
            forward = best(lambda: field.gear_features(x, t, levels), field, self.repeats, clock)
        backward = best(forward_backward, field, self.repeats, clock)
        renders = best(lambda: model.get_outputs_for_camera_ray_bundle(rays)["rgb"], model, self.repeats, clock)
        print(f"radiance field lookups of one chunk: {len(x)} samples; frame {self.frame}: {rays.shape.numel()} pixels; "
              f"{torch.get_num_threads()} threads, {'wall' if self.wall_time else 'CPU'} seconds")
        print("| path | field lookups forward ms | forward + backward ms | frame s | pixels / s | PSNR (dB) |")
        print("| --- | --- | --- | --- | --- | --- |")
        for kind in KINDS:
            seconds, image = renders[kind]
            print(f"| {kind} | {forward[kind][0] * 1e3:.2f} | {backward[kind][0] * 1e3:.2f} | {seconds:.2f} | "
                  f"{rays.shape.numel() / seconds:,.0f} | {float(psnr(image, truth)):.3f} |")
        warp, reference = renders["warp"][1], renders["torch"][1]
        print(f"PSNR of the kernel's frame against the torch path's: {float(psnr(warp, reference)):.1f} dB, largest "
              f"difference {float((warp - reference).abs().max()):.2e}")

        trainer_config.load_dir = self.config.parent / "nerfstudio_models"
        trainer_config.output_dir = Path("/tmp/plane_kernel_speed")  # the run folder is never written
        trainer_config.vis = "tensorboard"
        trainer = trainer_config.setup(local_rank=0, world_size=1)
        trainer.setup()
        step = trainer._start_step

        def train():
            nonlocal step
            for _ in range(self.train_iterations):
                trainer.train_iteration(step)
                step += 1

        train()  # warm-up
        rates = best(train, trainer.pipeline.model, self.repeats, clock)
        print("| path | training iterations / s |\n| --- | --- |")
        for kind in KINDS:
            print(f"| {kind} | {self.train_iterations / rates[kind][0]:.2f} |")
