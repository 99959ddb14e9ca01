"""Upshift targets and steps (Sec 4.3, Eq 10-11): the levels each sampled point is pulled to, the loss, the
points that take part, and the gradient steps on the gear function."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Optional, Protocol, Sequence, Tuple

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from gear_nerfstudio import distributed
from gear_nerfstudio.fields.gear_function import gear_level
from gear_nerfstudio.gears.config import GearUpdateConfig


class GearFunctionOwner(Protocol):
    """What the Eq 11 steps need: the gear function g (Eq 4) at world positions and times, and N_gear."""

    num_gears: int

    def gear_values(self, positions: Tensor, times: Optional[Tensor]) -> Tensor:
        ...


@dataclass
class UpdatePoints:
    """Points on the rays of a gear update (Eq 10) and the sets they belong to."""

    positions: Float[Tensor, "N 3"]
    """World positions."""
    times: Float[Tensor, "N 1"]
    """Times in [0, 1]."""
    weights: Float[Tensor, "N"]
    """Volume-rendering weights (Eq 1)."""
    upshift: Bool[Tensor, "N"]
    """In S_upshift (else S_stay or S_static)."""
    still: Optional[Bool[Tensor, "N"]] = None
    """On a pixel that does not change around the view's time (motion gate): target level 1 (``level_targets``)."""
    static: Optional[Bool[Tensor, "N"]] = None
    """In S_static (``point_sets``); None: no S_static."""

    def __getitem__(self, index: Tensor) -> UpdatePoints:
        """The points ``index``."""
        values = {item.name: getattr(self, item.name) for item in fields(self)}
        return UpdatePoints(**{name: None if value is None else value[index] for name, value in values.items()})

    @staticmethod
    def cat(parts: Sequence[UpdatePoints]) -> UpdatePoints:
        """The points of ``parts`` in order (each with ``still`` and ``static``)."""
        names = [item.name for item in fields(UpdatePoints)]
        return UpdatePoints(**{name: torch.cat([getattr(part, name) for part in parts]) for name in names})

    def sets(self) -> Tuple[Bool[Tensor, "N"], ...]:
        """Membership of the sets of Eq 10 (``point_sets``)."""
        return point_sets(self.upshift, self.static)


def level_targets(levels: Tensor, upshift: Tensor, num_gears: int, still: Optional[Tensor] = None) -> Tensor:
    """Target levels of Eq 10: p + 1 for S_upshift (never above N_gear), p for S_stay, and 1 for the points of
    S_stay in ``still`` (motion gate: pixels whose ground truth does not change around the view's time)."""
    stay = levels if still is None else torch.where(still, torch.ones_like(levels), levels)
    return torch.where(upshift, (levels + 1).clamp(max=num_gears), stay)


def point_sets(upshift: Tensor, static: Optional[Tensor] = None) -> Tuple[Tensor, ...]:
    """Membership of the sets of Eq 10: S_upshift, S_stay and, when ``static`` is given, S_static (points of other
    cameras' still pixels, held at gear 1 with a weighted mean of their own; ``GearUpdateConfig.static_views``)."""
    if static is None:
        return upshift, ~upshift
    return upshift, ~upshift & ~static, static & ~upshift


def upshift_loss(
    g: Tensor, targets: Tensor, points: UpdatePoints, num_gears: int, config: GearUpdateConfig
) -> Tensor:
    """Eq 10 as a weighted squared hinge: the distance of g from the interval of its target level q,
    [q - 1 + margin, q - margin] (no lower bound for q = 1, no upper bound for q = N_gear), averaged by weight over
    S_upshift, plus ``stay_weight`` (lambda_stay) times that over S_stay, plus ``static_weight`` times that over
    S_static when the points have one."""
    margin, weights = config.margin, points.weights
    low = torch.where(targets > 1, targets - 1 + margin, torch.full_like(g, -torch.inf))
    high = torch.where(targets < num_gears, targets - margin, torch.full_like(g, torch.inf))
    error = (torch.relu(low - g) + torch.relu(g - high)).square() * weights
    means = [error[members].sum() / weights[members].sum().clamp(min=1e-12) for members in points.sets()]
    return sum(factor * mean for factor, mean in zip((1.0, config.stay_weight, config.static_weight), means))


def select_points(points: UpdatePoints, max_points: int, generator: torch.Generator) -> UpdatePoints:
    """The points of S_upshift, S_stay (and S_static, ``point_sets``) that take part in the Eq 11 steps, with their
    weights.

    Only points whose weight is at least 1e-3 of the largest count: the others (most samples of a ray, in the
    empty space before and behind the surface it sees) add almost nothing to Eq 10. A set with more than
    ``max_points`` such points is replaced by ``max_points`` draws with probability proportional to weight, each
    of weight 1: Eq 10 normalises each set by its total weight, so the expected loss is the same, and the cost
    of a step no longer grows with the number of rays and samples.
    """
    weights = points.weights
    counted = weights >= 1e-3 * weights.max().clamp(min=1e-12)
    indices, selected = [], []
    for in_set in points.sets():
        members = torch.nonzero(counted & in_set)[:, 0]
        if len(members) > max_points:
            draws = torch.multinomial(weights[members], max_points, replacement=True, generator=generator)
            indices.append(members[draws])
            selected.append(torch.ones(max_points, device=weights.device))
        else:
            indices.append(members)
            selected.append(weights[members])
    return replace(points[torch.cat(indices)], weights=torch.cat(selected))


def shift_gears(
    field: GearFunctionOwner,
    optimizer: torch.optim.Optimizer,
    points: UpdatePoints,
    targets: Tensor,
    config: GearUpdateConfig,
) -> int:
    """Eq 11 steps of `optimizer` (on the gear function only) until the points sit at their target levels, at
    most ``config.max_steps``; returns the number of steps taken.

    Under DDP each process takes these steps on its own points, as in a training step: the gradients are averaged
    over the processes and the steps end once the points of every process sit at their targets. Every process
    then steps the same gradients the same number of times, so the gear function and the optimizer's state stay
    identical whether or not the processes' points are (their loss maps are rendered from the same model, but the
    points on each ray are jittered per process, and GPU backward passes are not bit-reproducible). This keeps the
    optimizer's state without copying it between processes, which a broadcast of the first process's result
    would need.

    The gradients are taken with ``torch.autograd.grad``, not ``backward``: DDP's hooks on the parameters count
    any backward pass between two training steps as gradient accumulation for the next one, which then fails on
    the gear function's missing gradient.
    """
    parameters = [p for group in optimizer.param_groups for p in group["params"]]
    steps = 0
    while steps < config.max_steps:
        optimizer.zero_grad(set_to_none=True)
        g = field.gear_values(points.positions, points.times)
        if bool(distributed.intersection((gear_level(g.detach(), field.num_gears) == targets).all())):
            break
        loss = upshift_loss(g, targets, points, field.num_gears, config)
        for parameter, gradient in zip(parameters, torch.autograd.grad(loss, parameters, allow_unused=True)):
            parameter.grad = gradient
        distributed.average_gradients(parameters)
        optimizer.step()
        steps += 1
    optimizer.zero_grad(set_to_none=True)
    return steps
