"""Is the low-dimensional SAM head (sam_head_dim, lifted to 256 after rendering) faster at equal quality?

Trains the gear-nerf-small preset on a synthetic Neural 3D Video scene once per head setting, with the
built-in SAM backend, the same iterations and seed, then reports the time per training iteration and,
on the held-out camera (all frames), the SAM-feature MSE against the cached encoder features (Eq 9)
and the RGB PSNR. The settings train in lockstep (one iteration each, in turn), so that a change in
machine load affects them alike; each keeps its own random state, so both see the same ray batches.

    .venv/bin/python benchmarks/sam_head.py [--iterations 300] [--heads 32 none] [--seeds 0] [--device cpu]
"""

from __future__ import annotations

import argparse
import copy
import functools
import random
import statistics
import tempfile
import time
from pathlib import Path
from typing import Dict, List, Optional

import numpy as np
import torch

from nerfstudio.engine.callbacks import TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.engine.optimizers import Optimizers

from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from gear_nerfstudio.method_configs.gear_nerf import gear_nerf_small
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene

SPEC = SyntheticSpec(dataset="n3d", width=64, height=48, frames=4, cameras=6)


class Run:
    """One head setting: its pipeline, optimisers, callbacks and iteration times."""

    def __init__(self, head: Optional[int], scene: Path, work: Path, device: str, seed: int):
        config = copy.deepcopy(gear_nerf_small.config)
        config.pipeline.datamanager.dataparser = Neural3DVideoDataParserConfig(data=scene, cache_dir=work / "frames")
        config.pipeline.datamanager.sam_cache_dir = work / "sam"
        config.pipeline.model.sam_head_dim = head
        torch.manual_seed(seed)
        random.seed(seed)
        np.random.seed(seed)
        self.random_state = (torch.get_rng_state(), random.getstate())
        self.head = head
        self.pipeline = config.pipeline.setup(device=device, test_mode="val")
        self.pipeline.train()
        self.optimizers = Optimizers(config.optimizers, self.pipeline.get_param_groups())
        attributes = TrainingCallbackAttributes(self.optimizers, None, self.pipeline, None)
        self.callbacks = self.pipeline.get_training_callbacks(attributes)
        self.times: List[float] = []

    def step(self, step: int) -> None:
        """One training iteration as nerfstudio's Trainer runs it (callbacks, losses, optimiser steps)."""
        torch.set_rng_state(self.random_state[0])
        random.setstate(self.random_state[1])
        synchronise = torch.cuda.synchronize if self.pipeline.device.type == "cuda" else lambda: None
        synchronise()
        start = time.perf_counter()
        for callback in self.callbacks:
            callback.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        self.optimizers.zero_grad_all()
        _, loss_dict, _ = self.pipeline.get_train_loss_dict(step)
        functools.reduce(torch.add, loss_dict.values()).backward()
        self.optimizers.optimizer_step_all()
        self.optimizers.scheduler_step_all(step)
        for callback in self.callbacks:
            callback.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
        synchronise()
        self.times.append(time.perf_counter() - start)
        self.random_state = (torch.get_rng_state(), random.getstate())

    @torch.no_grad()
    def held_out(self) -> Dict[str, float]:
        """SAM-feature MSE (Eq 9 per ray), the MSE of predicting the mean feature (for scale) and PSNR,
        over every pixel of every held-out image."""
        self.pipeline.eval()
        datamanager, model = self.pipeline.datamanager, self.pipeline.model
        dataset = datamanager.eval_dataset
        sam_errors, targets, rgb_errors = [], [], []
        for index in range(len(dataset)):
            camera = dataset.cameras[index : index + 1].to(model.device)
            with model.rendering("sam"):
                outputs = model.get_outputs_for_camera(camera)
            height, width = outputs["rgb"].shape[:2]
            ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
            pixels = torch.stack([xs, ys], dim=-1).reshape(-1, 2).float() + 0.5
            target = datamanager.eval_feature_cache.features_at(torch.full((len(pixels),), index), pixels)
            sam_errors.append(((outputs["sam"].reshape(-1, target.shape[1]).cpu() - target) ** 2).mean(dim=1))
            targets.append(target)
            image = dataset[index]["image"][..., :3]
            rgb_errors.append(((outputs["rgb"].cpu() - image) ** 2).reshape(-1))
        targets = torch.cat(targets)
        return {
            "sam_mse": float(torch.cat(sam_errors).mean()),
            "mean_feature_mse": float(((targets - targets.mean(dim=0)) ** 2).mean()),
            "psnr": float(-10 * torch.log10(torch.cat(rgb_errors).mean())),
        }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--heads", nargs="+", default=["32", "none"], help="sam_head_dim values; 'none' = 256/sample")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    args = parser.parse_args()
    heads = [None if h.lower() == "none" else int(h) for h in args.heads]

    rows = []
    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder)
        scene = write_synthetic_scene(work / "scene", SPEC)
        for seed in args.seeds:
            runs = [Run(head, scene, work, args.device, seed) for head in heads]
            for step in range(args.iterations):
                for run in runs:
                    run.step(step)
            baseline = statistics.median(runs[0].times[5:])  # medians leave out the first iterations' warm-up
            for run in runs:
                field = run.pipeline.model.field
                params = sum(p.numel() for p in field.sam_net.parameters())
                if field.sam_lift is not None:
                    params += sum(p.numel() for p in field.sam_lift.parameters())
                median = statistics.median(run.times[5:])
                result = run.held_out()
                rows.append(
                    f"| {seed} | {run.head or 'none (256)'} | {params} "
                    f"| {1000 * median:.1f} ({median / baseline:.2f}x) | {result['sam_mse']:.3e} "
                    f"| {result['mean_feature_mse']:.3e} | {result['psnr']:.2f} |"
                )

    print(
        f"\n{args.iterations} iterations of gear-nerf-small, {SPEC.width}x{SPEC.height} N3D synthetic scene "
        f"({SPEC.cameras} cameras, {SPEC.frames} frames), builtin SAM backend, device {args.device}, "
        f"{torch.get_num_threads()} threads\n"
    )
    print(
        "| seed | sam_head_dim | SAM head params | ms / iteration (median) | held-out SAM MSE "
        "| MSE of the mean feature | held-out PSNR |"
    )
    print("|---|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
