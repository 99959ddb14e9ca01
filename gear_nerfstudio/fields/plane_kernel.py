"""The fields' plane lookups fused in one Warp kernel, forward and backward, for CPU and CUDA alike.

In one pass over the samples, for each sample of gear level p, each plane j and each resolution it writes
h_j(x) ⊙ k_j^p(x, t) (Eq 3), bilinear lookups with ``align_corners=True`` and border padding as in
``planes.bilinear``, into the columns that B = [B_1 B_2 B_3] reads (plane-major, then resolution, then channel), so
f = products @ B^T sums the planes and the resolutions in one matrix product. No feature tensor per plane is made:
the kernel reads the C channels of a corner as one vector (planes channels-last). The backward kernel accumulates the
planes' gradients and, like ``grid_sample``, the positions' and times' (zero where a coordinate is clamped to the
border). The space-time planes are those of ``GearField.stacked_time_planes``, gear p's row at time t being
``first_rows[p - 1] + t (rows[p - 1] - 1)``; the proposal networks' and the gear function's are one gear from row
0. Without gradients a third kernel reads such one-gear products out by a weight per column (the gear function's
sum, Eq 4; a proposal network's linear decoder) and writes one number per sample.
"""

import functools
import itertools
import platform
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Sequence

import torch
import warp as wp
from jaxtyping import Float, Int
from torch import Tensor, nn

wp.config.quiet = True
wp.init()

CPU_OPTIONS = {"cpu_compiler_flags": "-march=native"} if platform.machine() in ("x86_64", "AMD64") else {}
"""Warp's CPU build targets baseline x86-64, where clang leaves the C-channel vector arithmetic scalar; the host's
own instruction set (AVX2, AVX-512) lets it vectorise (docs/decisions.md)."""


@wp.func
def cell(i: float, size: int):
    """Low and high cells, weight of the high cell, and d(clamped i)/di at index i on an axis of ``size`` cells."""
    inner = wp.where(i > 0.0 and i < float(size - 1), 1.0, 0.0)
    i = wp.clamp(i, 0.0, float(size - 1))
    low = wp.min(int(wp.floor(i)), size - 1)
    return low, wp.min(low + 1, size - 1), i - float(low), inner


@wp.func
def unnormalise(u: float, size: int) -> float:
    """Index of coordinate u in [-1, 1] on an axis of ``size`` cells (``align_corners=True``)."""
    return (u + 1.0) * (0.5 * float(size - 1))


@wp.func
def lookup(plane: wp.array(dtype=Any), start: int, size: int, r0: int, r1: int, rw: float, c0: int, c1: int,
           cw: float):
    """Bilinear value (C channels) of a plane of rows of ``size`` cells beginning at ``start`` in a buffer, between
    rows r0, r1 and columns c0, c1 with weights rw, cw of r1, c1."""
    low, high = start + r0 * size, start + r1 * size
    return ((1.0 - rw) * (1.0 - cw)) * plane[low + c0] + ((1.0 - rw) * cw) * plane[low + c1] + (
        (rw * (1.0 - cw)) * plane[high + c0] + (rw * cw) * plane[high + c1]
    )


@wp.func
def scatter(grad: wp.array(dtype=Any), start: int, size: int, r0: int, r1: int, rw: float, c0: int, c1: int,
            cw: float, g: Any):
    """Backward of ``lookup`` with respect to the plane: adds the value's gradient g to the four corners of
    ``grad`` (on the CPU, where Warp runs a launch's samples one after the other, an atomic add is a plain add)."""
    low, high = start + r0 * size, start + r1 * size
    wp.atomic_add(grad, low + c0, ((1.0 - rw) * (1.0 - cw)) * g)
    wp.atomic_add(grad, low + c1, ((1.0 - rw) * cw) * g)
    wp.atomic_add(grad, high + c0, (rw * (1.0 - cw)) * g)
    wp.atomic_add(grad, high + c1, (rw * cw) * g)


@wp.func
def slopes(plane: wp.array(dtype=Any), start: int, size: int, r0: int, r1: int, rw: float, c0: int, c1: int,
           cw: float, g: Any):
    """Backward of ``lookup`` with respect to the column and row indices for the value's gradient g, per channel
    (their sums are the derivatives)."""
    low, high = start + r0 * size, start + r1 * size
    p00, p01, p10, p11 = plane[low + c0], plane[low + c1], plane[high + c0], plane[high + c1]
    d_column = wp.cw_mul(g, (1.0 - rw) * (p01 - p00) + rw * (p11 - p10))
    return d_column, wp.cw_mul(g, (1.0 - cw) * (p10 - p00) + cw * (p11 - p01))


@wp.func
def resolution_products(space: wp.array(dtype=Any), time: wp.array(dtype=Any), layout: wp.array2d(dtype=int), r: int,
                        x: float, y: float, z: float, t0: int, t1: int, tw: float):
    """h_j ⊙ k_j (j = 1, 2, 3) of resolution r at plane coordinates (x, y, z), the space-time planes read between
    rows t0 and t1 with weight tw of t1."""
    size, space_start, time_start, height = layout[r, 0], layout[r, 1], layout[r, 2], layout[r, 3]
    x0, x1, xw, xin = cell(unnormalise(x, size), size)
    y0, y1, yw, yin = cell(unnormalise(y, size), size)
    z0, z1, zw, zin = cell(unnormalise(z, size), size)
    h1 = lookup(space, space_start, size, y0, y1, yw, x0, x1, xw)
    h2 = lookup(space, space_start + size * size, size, z0, z1, zw, x0, x1, xw)
    h3 = lookup(space, space_start + 2 * size * size, size, z0, z1, zw, y0, y1, yw)
    k1 = lookup(time, time_start, size, t0, t1, tw, z0, z1, zw)
    k2 = lookup(time, time_start + height * size, size, t0, t1, tw, y0, y1, yw)
    k3 = lookup(time, time_start + 2 * height * size, size, t0, t1, tw, x0, x1, xw)
    return wp.cw_mul(h1, k1), wp.cw_mul(h2, k2), wp.cw_mul(h3, k3)


@functools.lru_cache(maxsize=None)
def kernels(channels: int):
    """Forward, backward and weighted-sum kernels for planes of ``channels`` channels (one compiled module each).

    Per resolution r (``layout[r]``: size, first rows of its planes in the space and time buffers, rows of the
    space-time planes), plane j of a buffer begins j * rows * size rows after the resolution's first row; h_1, h_2,
    h_3 are over (x, y), (x, z), (y, z) and k_1, k_2, k_3 over (z, t), (y, t), (x, t), the first axis along columns
    (``planes.SPACE_PLANE_AXES``, ``planes.TIME_PLANE_AXES``)."""
    vec = wp.types.vector(length=channels, dtype=float)

    @wp.kernel(enable_backward=False, module="unique", module_options=CPU_OPTIONS)
    def forward(
        x: wp.array2d(dtype=float),
        t: wp.array(dtype=float),
        levels: wp.array(dtype=int),
        space: wp.array(dtype=vec),
        time: wp.array(dtype=vec),
        layout: wp.array2d(dtype=int),
        first_rows: wp.array(dtype=float),
        rows: wp.array(dtype=float),
        out: wp.array2d(dtype=vec),
    ):
        n = wp.tid()
        gear = levels[n] - 1
        t0, t1, tw, tin = cell(first_rows[gear] + t[n] * (rows[gear] - 1.0), layout[0, 3])
        num_resolutions = layout.shape[0]
        for r in range(num_resolutions):
            p1, p2, p3 = resolution_products(space, time, layout, r, x[n, 0], x[n, 1], x[n, 2], t0, t1, tw)
            out[n, r] = p1
            out[n, num_resolutions + r] = p2
            out[n, 2 * num_resolutions + r] = p3

    @wp.kernel(enable_backward=False, module="unique", module_options=CPU_OPTIONS)
    def sums(
        x: wp.array2d(dtype=float),
        t: wp.array(dtype=float),
        space: wp.array(dtype=vec),
        time: wp.array(dtype=vec),
        layout: wp.array2d(dtype=int),
        weights: wp.array(dtype=vec),
        out: wp.array(dtype=float),
    ):
        n = wp.tid()
        t0, t1, tw, tin = cell(t[n] * float(layout[0, 3] - 1), layout[0, 3])
        num_resolutions = layout.shape[0]
        total = float(0.0)
        for r in range(num_resolutions):
            p1, p2, p3 = resolution_products(space, time, layout, r, x[n, 0], x[n, 1], x[n, 2], t0, t1, tw)
            total += wp.dot(p1, weights[r]) + wp.dot(p2, weights[num_resolutions + r])
            total += wp.dot(p3, weights[2 * num_resolutions + r])
        out[n] = total

    @wp.kernel(enable_backward=False, module="unique", module_options=CPU_OPTIONS)
    def backward(
        x: wp.array2d(dtype=float),
        t: wp.array(dtype=float),
        levels: wp.array(dtype=int),
        space: wp.array(dtype=vec),
        time: wp.array(dtype=vec),
        layout: wp.array2d(dtype=int),
        first_rows: wp.array(dtype=float),
        rows: wp.array(dtype=float),
        grad_out: wp.array2d(dtype=vec),
        grad_space: wp.array(dtype=vec),
        grad_time: wp.array(dtype=vec),
        coordinates: int,
        grad_x: wp.array2d(dtype=float),
        grad_t: wp.array(dtype=float),
    ):
        n = wp.tid()
        gear = levels[n] - 1
        height = layout[0, 3]
        t0, t1, tw, tin = cell(first_rows[gear] + t[n] * (rows[gear] - 1.0), height)
        num_resolutions = layout.shape[0]
        d_x, d_y, d_z, d_t = vec(), vec(), vec(), vec()
        for r in range(num_resolutions):
            size, space_start, time_start = layout[r, 0], layout[r, 1], layout[r, 2]
            x0, x1, xw, xin = cell(unnormalise(x[n, 0], size), size)
            y0, y1, yw, yin = cell(unnormalise(x[n, 1], size), size)
            z0, z1, zw, zin = cell(unnormalise(x[n, 2], size), size)
            h2_start, h3_start = space_start + size * size, space_start + 2 * size * size
            k2_start, k3_start = time_start + height * size, time_start + 2 * height * size
            h1 = lookup(space, space_start, size, y0, y1, yw, x0, x1, xw)
            h2 = lookup(space, h2_start, size, z0, z1, zw, x0, x1, xw)
            h3 = lookup(space, h3_start, size, z0, z1, zw, y0, y1, yw)
            k1 = lookup(time, time_start, size, t0, t1, tw, z0, z1, zw)
            k2 = lookup(time, k2_start, size, t0, t1, tw, y0, y1, yw)
            k3 = lookup(time, k3_start, size, t0, t1, tw, x0, x1, xw)
            g1, g2, g3 = grad_out[n, r], grad_out[n, num_resolutions + r], grad_out[n, 2 * num_resolutions + r]
            gh1, gh2, gh3 = wp.cw_mul(g1, k1), wp.cw_mul(g2, k2), wp.cw_mul(g3, k3)
            gk1, gk2, gk3 = wp.cw_mul(g1, h1), wp.cw_mul(g2, h2), wp.cw_mul(g3, h3)
            scatter(grad_space, space_start, size, y0, y1, yw, x0, x1, xw, gh1)
            scatter(grad_space, h2_start, size, z0, z1, zw, x0, x1, xw, gh2)
            scatter(grad_space, h3_start, size, z0, z1, zw, y0, y1, yw, gh3)
            scatter(grad_time, time_start, size, t0, t1, tw, z0, z1, zw, gk1)
            scatter(grad_time, k2_start, size, t0, t1, tw, y0, y1, yw, gk2)
            scatter(grad_time, k3_start, size, t0, t1, tw, x0, x1, xw, gk3)
            if coordinates != 0:
                scale = 0.5 * float(size - 1)
                dx1, dy1 = slopes(space, space_start, size, y0, y1, yw, x0, x1, xw, gh1)
                dx2, dz2 = slopes(space, h2_start, size, z0, z1, zw, x0, x1, xw, gh2)
                dy3, dz3 = slopes(space, h3_start, size, z0, z1, zw, y0, y1, yw, gh3)
                dz1, dt1 = slopes(time, time_start, size, t0, t1, tw, z0, z1, zw, gk1)
                dy2, dt2 = slopes(time, k2_start, size, t0, t1, tw, y0, y1, yw, gk2)
                dx3, dt3 = slopes(time, k3_start, size, t0, t1, tw, x0, x1, xw, gk3)
                d_x += (xin * scale) * (dx1 + dx2 + dx3)
                d_y += (yin * scale) * (dy1 + dy2 + dy3)
                d_z += (zin * scale) * (dz1 + dz2 + dz3)
                d_t += dt1 + dt2 + dt3
        if coordinates != 0:
            ones = vec(1.0)
            grad_x[n, 0] = wp.dot(d_x, ones)
            grad_x[n, 1] = wp.dot(d_y, ones)
            grad_x[n, 2] = wp.dot(d_z, ones)
            grad_t[n] = wp.dot(d_t, ones) * tin * (rows[gear] - 1.0)

    return forward, backward, sums


class PlaneProducts(torch.autograd.Function):
    """``plane_products`` with the backward kernel as its gradient. The planes of all resolutions come as two
    channels-last buffers, ``space`` (rows of C) and ``time``, where ``layout`` places them: per resolution its size,
    its first row in each buffer and the space-time planes' rows."""

    @staticmethod
    def forward(ctx, x, t, levels, first_rows, rows, layout, space, time):
        forward = kernels(space.shape[-1])[0]
        out = x.new_empty(x.shape[0], 3 * layout.shape[0], space.shape[-1])
        launch(forward, x, t, levels, space, time, layout, first_rows, rows, out)
        ctx.save_for_backward(x, t, levels, first_rows, rows, layout, space, time)
        return out.flatten(1)

    @staticmethod
    def backward(ctx, grad_out):
        x, t, levels, first_rows, rows, layout, space, time = ctx.saved_tensors
        backward = kernels(space.shape[-1])[1]
        grad_out = grad_out.contiguous().view(x.shape[0], 3 * layout.shape[0], space.shape[-1])
        grad_space, grad_time = torch.zeros_like(space), torch.zeros_like(time)
        grad_x, grad_t = torch.zeros_like(x), torch.zeros_like(t)
        coordinates = int(ctx.needs_input_grad[0] or ctx.needs_input_grad[1])
        launch(backward, x, t, levels, space, time, layout, first_rows, rows, grad_out, grad_space, grad_time,
               coordinates, grad_x, grad_t)
        return grad_x, grad_t, None, None, None, None, grad_space, grad_time


def launch(kernel: wp.Kernel, x: Tensor, *args) -> None:
    """Launch ``kernel`` over the samples of x on x's device (on CUDA in torch's current stream), the tensors as Warp
    views (no copy) of the kernel's argument types."""
    inputs = [
        wp.from_torch(value, dtype=arg.type.dtype, requires_grad=False) if isinstance(value, Tensor) else value
        for arg, value in zip(kernel.adj.args, (x, *args))
    ]
    stream = wp.stream_from_torch(x.device) if x.is_cuda else None
    wp.launch(kernel, dim=x.shape[0], inputs=inputs, device=wp.device_from_torch(x.device), stream=stream)


@dataclass(frozen=True)
class PackedPlanes:
    """Planes of every resolution as the kernels read them: two channels-last buffers, ``space`` (rows of C) and
    ``time``, and ``layout``, per resolution its size, its first row in each buffer and the space-time planes' rows."""

    layout: Int[Tensor, "R 4"]
    space: Float[Tensor, "S C"]
    time: Float[Tensor, "T C"]


def pack_planes(
    space_planes: Sequence[Float[Tensor, "3 C R R"]], time_planes: Sequence[Float[Tensor, "3 C H R"]]
) -> PackedPlanes:
    """The spatial and space-time planes of each resolution (one of each per resolution) packed for the kernels."""
    if len(space_planes) != len(time_planes):
        raise ValueError(f"the plane kernel needs one space-time plane per spatial plane, got {len(time_planes)} "
                         f"for {len(space_planes)}")
    channels, height = space_planes[0].shape[1], time_planes[0].shape[2]
    sizes = [p.shape[-1] for p in space_planes]
    space_starts = [0] + [3 * size * size for size in sizes[:-1]]
    time_starts = [0] + [3 * height * size for size in sizes[:-1]]
    layout = torch.tensor(
        [[size, s, t, height] for size, s, t in zip(sizes, itertools.accumulate(space_starts),
                                                     itertools.accumulate(time_starts))],
        dtype=torch.int32, device=space_planes[0].device,
    )
    space, time = (
        torch.cat([p.float().permute(0, 2, 3, 1).reshape(-1, channels) for p in planes])
        for planes in (space_planes, time_planes)
    )
    return PackedPlanes(layout, space, time)


def packed_once(owner: nn.Module, parameters: Iterable[Tensor], pack: Callable[[], PackedPlanes]) -> PackedPlanes:
    """``pack()``, kept on ``owner`` while no gradient is taken and ``parameters`` are unchanged, so that the chunks
    of a render pack the planes once; with gradients it is packed anew each call and the kept copy is dropped."""
    if torch.is_grad_enabled():
        owner.packed_planes = None
        return pack()
    key = tuple((p.data_ptr(), p._version) for p in parameters)
    kept = getattr(owner, "packed_planes", None)
    if kept is None or kept[0] != key:
        kept = owner.packed_planes = (key, pack())
    return kept[1]


def plane_products(
    x: Float[Tensor, "N 3"],
    t: Float[Tensor, "N"],
    levels: Int[Tensor, "N"],
    planes: PackedPlanes,
    first_rows: Float[Tensor, "G"],
    rows: Float[Tensor, "G"],
) -> Float[Tensor, "N F"]:
    """Eq 3's products h_j ⊙ k_j^p of every plane j and resolution, F = 3 x resolutions x C columns (plane-major),
    at normalised positions x, times t in [0, 1] and gear levels p (1-based); the space-time planes stacked by gear,
    gear p's first row and its number of rows in ``first_rows`` and ``rows``."""
    return PlaneProducts.apply(
        x.float().contiguous(), t.float().contiguous(), levels.to(torch.int32).contiguous(),
        first_rows.float().contiguous(), rows.float().contiguous(), planes.layout, planes.space, planes.time,
    )


def one_gear_sums(
    owner: nn.Module,
    x: Float[Tensor, "N 3"],
    t: Float[Tensor, "N"],
    space_planes: Sequence[Float[Tensor, "3 C R R"]],
    time_planes: Sequence[Float[Tensor, "3 C H R"]],
    weights: Float[Tensor, "F"],
) -> Float[Tensor, "N"]:
    """The products of ``owner``'s planes without gears (the gear function's and the proposal networks';
    ``plane_products`` with every sample reading the space-time planes from their first row) read out by
    ``weights``: the sum over the F columns of weights ⊙ products. Without gradients one kernel writes the sums only,
    the planes packed once per render (``packed_once``)."""
    planes = packed_once(owner, [*space_planes, *time_planes], lambda: pack_planes(space_planes, time_planes))
    if torch.is_grad_enabled():
        rows = planes.layout[:1, 3].float()
        levels = torch.ones(len(x), dtype=torch.int32, device=x.device)
        return plane_products(x, t, levels, planes, torch.zeros_like(rows), rows) @ weights
    out = x.new_empty(len(x))
    weights = weights.float().contiguous().view(-1, planes.space.shape[-1])
    launch(kernels(planes.space.shape[-1])[2], x.float().contiguous(), t.float().contiguous(), planes.space,
           planes.time, planes.layout, weights, out)
    return out
