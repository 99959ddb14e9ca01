"""Plane lookups of a preset's field, forward and backward: the model's ``planes.bilinear`` (``grid_sample`` on
channels-first planes) against a candidate for issue 25, measured and rejected (``results/gpu_speed.md``): a
channels-last lookup through ``F.embedding_bag`` (each sample a weighted sum of its four corner rows; its backward
sums rows by index instead of scattering channels).

Per resolution r of the preset: three spatial planes (C x r x r) and three space-time planes (C x T x r), at N
samples uniform in [-1, 1]^3 whose times are drawn from ``--frames`` distinct frames of the T rows (a 2-frame
benchmark scene puts all of a batch's time-plane gradients on two rows). Median over ``--repeats`` calls after one
warm-up; the two lookups' largest difference is printed.

    python benchmarks/plane_lookup.py --device cuda --preset gear-nerf --samples 300000 --frames 2 300
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Callable, List, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from gear_nerfstudio.fields.planes import bilinear, space_coords, time_coords
from gear_nerfstudio.method_configs.gear_nerf import gear_nerf, gear_nerf_small


def corner_lookup(planes: Tensor, width: int, coords: Tensor) -> Tensor:
    """The bilinear lookup of ``bilinear`` (corners aligned, border-clamped) on channels-last planes (3, H * W, C) of
    W = ``width``, as ``F.embedding_bag`` sums of the four corner rows weighted by their bilinear weights; (3, N, C)."""
    height = planes.shape[1] // width
    u = (coords[..., 0].clamp(-1, 1) + 1) * 0.5 * (width - 1)
    v = (coords[..., 1].clamp(-1, 1) + 1) * 0.5 * (height - 1)
    u0 = u.floor().clamp(0, max(width - 2, 0))
    v0 = v.floor().clamp(0, max(height - 2, 0))
    fu, fv = u - u0, v - v0
    corner = v0.long() * width + u0.long()
    du, dv = int(width > 1), width * int(height > 1)
    index = torch.stack([corner, corner + du, corner + dv, corner + dv + du], dim=-1)
    weight = torch.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], dim=-1)
    return torch.stack(
        [F.embedding_bag(index[j], planes[j], per_sample_weights=weight[j], mode="sum") for j in range(3)]
    )


def channels_last(plane: Tensor) -> Tensor:
    """(3, C, H, W) as a (3, H * W, C) leaf."""
    return plane.detach().permute(0, 2, 3, 1).reshape(plane.shape[0], -1, plane.shape[1]).contiguous().requires_grad_()


def median_ms(function: Callable[[], None], repeats: int, device: torch.device) -> float:
    function()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        function()
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append(1000 * (time.perf_counter() - start))
    return statistics.median(times)


def measure(channels: int, resolutions: Sequence[int], rows: int, samples: int, frames: int, repeats: int,
            device: torch.device) -> List[str]:  # fmt: skip
    generator = torch.Generator().manual_seed(0)
    x = (torch.rand(samples, 3, generator=generator) * 2 - 1).to(device)
    frame = torch.randint(0, frames, (samples, 1), generator=generator).float()
    t = (frame * (rows - 1) // max(frames - 1, 1) / max(rows - 1, 1)).to(device)
    coords = [space_coords(x), time_coords(x, t)]
    planes = []
    for r in resolutions:
        planes += [torch.rand(3, channels, r, r, device=device), torch.rand(3, channels, rows, r, device=device)]
    planes = [p.requires_grad_(True) for p in planes]
    flat = [channels_last(p) for p in planes]

    def gather(i: int, coords: Tensor) -> Tensor:
        return corner_lookup(flat[i], planes[i].shape[-1], coords)

    def grid(i: int, coords: Tensor) -> Tensor:
        return bilinear(planes[i], coords)

    with torch.no_grad():
        difference = max(
            float((grid(i, coords[i % 2]).transpose(1, 2) - gather(i, coords[i % 2])).abs().max())
            for i in range(len(planes))
        )

    def run(lookup: Callable[[int, Tensor], Tensor], tables: List[Tensor], backward: bool) -> Callable[[], None]:
        def call() -> None:
            with torch.set_grad_enabled(backward):
                total = sum(lookup(i, coords[i % 2]).square().sum() for i in range(len(tables)))
            if backward:
                total.backward()
                for p in tables:
                    p.grad = None

        return call

    lines = []
    for name, lookup, tables in (("grid_sample", grid, planes), ("embedding_bag", gather, flat)):
        forward = median_ms(run(lookup, tables, False), repeats, device)
        both = median_ms(run(lookup, tables, True), repeats, device)
        lines.append(f"| {samples:,} | {frames} of {rows} | {name} | {forward:.2f} | {both:.2f} | {difference:.1e} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--preset", default="gear-nerf", choices=["gear-nerf", "gear-nerf-small"])
    parser.add_argument("--rows", type=int, default=300, help="rows T of the space-time planes (frames)")
    parser.add_argument("--samples", type=int, nargs="+", default=[300000])
    parser.add_argument("--frames", type=int, nargs="+", default=[2, 300])
    parser.add_argument("--repeats", type=int, default=10)
    args = parser.parse_args()
    model = (gear_nerf if args.preset == "gear-nerf" else gear_nerf_small).config.pipeline.model
    device = torch.device(args.device)
    print(f"{args.preset}: C = {model.feature_dim}, resolutions {tuple(model.resolutions)}, T = {args.rows}, "
          f"{device}, torch {torch.__version__}, {torch.get_num_threads()} threads")  # fmt: skip
    print("\n| samples | times from | lookup | forward ms | forward + backward ms | largest difference |")
    print("| --- | --- | --- | --- | --- | --- |")
    for samples in args.samples:
        for frames in args.frames:
            for line in measure(model.feature_dim, model.resolutions, args.rows, samples, frames, args.repeats, device):
                print(line, flush=True)


if __name__ == "__main__":
    main()
