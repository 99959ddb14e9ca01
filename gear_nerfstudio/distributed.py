"""Agreement between the processes of a multi-GPU run (nerfstudio's ``--machine.num-devices``, DistributedDataParallel).

DDP averages the gradients of the training step, so the optimizers keep every process's parameters equal. Whatever
changes the model outside that step must agree by itself: the plane columns a gear claims and inherits during the
forward pass (Sec 4.4, ``GearField.claim_columns``) and the gear-assignment updates (Sec 4.3, ``shift_gears``). Every
function here is a collective, so every process must call it at the same point; in a single process (no
initialised process group) each returns its input.
"""

from __future__ import annotations

from typing import Iterable

import torch
import torch.distributed as dist
from torch import Tensor


def world_size() -> int:
    """Processes of the run: 1 without an initialised process group."""
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def _reduce_flags(flags: Tensor, op: "dist.ReduceOp") -> Tensor:
    """Boolean flags all-reduced with ``op`` (as uint8: gloo and NCCL reduce no bools)."""
    if world_size() == 1:
        return flags
    values = flags.to(torch.uint8)
    dist.all_reduce(values, op=op)
    return values.bool()


def union(flags: Tensor) -> Tensor:
    """Boolean flags set on any process (all-reduce max)."""
    return _reduce_flags(flags, dist.ReduceOp.MAX)


def intersection(flags: Tensor) -> Tensor:
    """Boolean flags set on every process (all-reduce min)."""
    return _reduce_flags(flags, dist.ReduceOp.MIN)


def average(values: Tensor) -> Tensor:
    """The mean over processes, the same on every process (all-reduce sum / world size)."""
    if world_size() == 1:
        return values
    total = values.clone()
    dist.all_reduce(total)
    return total / world_size()


def average_gradients(parameters: Iterable[Tensor]) -> None:
    """Replace each gradient by its mean over processes, as DDP does in the training step. With several processes a
    missing gradient counts as zero, so that every process steps the same parameters."""
    if world_size() == 1:
        return
    for parameter in parameters:
        if parameter.grad is None:
            parameter.grad = torch.zeros_like(parameter)
        parameter.grad.copy_(average(parameter.grad))
