"""K-Planes regularisers, normalised per plane as in the K-Planes plugin (each plane's term is a mean; they
are summed and divided by the planes of one K-Planes field), so that every plane weighs the same whatever
other planes exist."""

from __future__ import annotations

from typing import List, Sequence

import torch
from torch import Tensor

def per_plane_sum(terms: List[Tensor], triples_per_field: int, like: Tensor) -> Tensor:
    """Sum of per-triple terms (each the mean over its three planes) divided by the triples of one K-Planes
    field: K-Planes' normalisation per plane, so every plane weighs the same whatever other planes exist."""
    total = torch.stack(terms).sum() if terms else like.new_zeros(())
    return total / triples_per_field


def plane_tv(space_triples: Sequence[Tensor], time_triples: Sequence[Tensor], triples_per_field: int) -> Tensor:
    """K-Planes total variation: mean squared difference of neighbouring cells along both axes of each spatial
    plane and along the spatial axis (W) of each space-time plane, normalised per plane (``per_plane_sum``)."""
    terms = [
        (t[..., 1:, :] - t[..., :-1, :]).square().mean() + (t[..., :, 1:] - t[..., :, :-1]).square().mean()
        for t in space_triples
    ]
    terms += [(t[..., :, 1:] - t[..., :, :-1]).square().mean() for t in time_triples]
    return per_plane_sum(terms, triples_per_field, space_triples[0])


def l1_time_planes(time_triples: Sequence[Tensor], triples_per_field: int, like: Tensor) -> Tensor:
    """K-Planes L1 penalty: mean |1 - k| of each space-time plane (1 is static), normalised per plane."""
    return per_plane_sum([(1.0 - t).abs().mean() for t in time_triples], triples_per_field, like)


def time_smoothness(time_triples: Sequence[Tensor], triples_per_field: int, like: Tensor) -> Tensor:
    """K-Planes time smoothness: mean squared second difference along t of each space-time plane (planes with
    fewer than 3 rows have none), normalised per plane."""
    terms = [
        (t[..., 2:, :] - 2.0 * t[..., 1:-1, :] + t[..., :-2, :]).square().mean() for t in time_triples if t.shape[-2] >= 3
    ]
    return per_plane_sum(terms, triples_per_field, like)
