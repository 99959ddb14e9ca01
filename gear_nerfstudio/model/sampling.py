"""Sampling of a Gear-NeRF ray batch: base samples (stratified uniform, n = 64 in the paper, or a proposal network
as in K-Planes), the gear level p of each (Eq 5), and the split sampler (Sec 4.4)."""

from __future__ import annotations

import contextlib
import functools
from dataclasses import dataclass
from typing import Callable, Iterator, List, Optional, Sequence, Tuple

import numpy as np
from jaxtyping import Float, Int
from torch import Tensor, nn

from nerfstudio.cameras.rays import RayBundle, RaySamples
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.model_components.ray_samplers import (
    ProposalNetworkSampler,
    UniformLinDispPiecewiseSampler,
    UniformSampler,
)

from gear_nerfstudio.errors import InputError
from gear_nerfstudio.fields.proposal_field import ProposalDensityField
from gear_nerfstudio.model.split_sampler import SplitRaySamples, split_ray_samples

GearLevelFn = Callable[[Float[Tensor, "*bs 3"], Optional[Float[Tensor, "*bs 1"]]], Int[Tensor, "*bs"]]
"""Eq 5: the gear level p at world positions and times."""


@dataclass
class GearSamples:
    """The samples of a batch of rays: base samples, their gear levels and their split (Sec 4.4)."""

    base: RaySamples
    """Base samples, (num_rays, n)."""
    levels: Int[Tensor, "num_rays n"]
    """Gear level p of each base sample (Eq 5)."""
    split: SplitRaySamples
    """Each base sample at gear p split into split_base^(p-1) samples."""
    proposal_weights: List[Tensor]
    """Weights of each proposal iteration's samples (proposal base sampler; empty otherwise)."""
    proposal_samples: List[RaySamples]
    """Samples of each proposal iteration (proposal base sampler; empty otherwise)."""


@dataclass
class SampleCounts:
    """Samples per ray: n base samples and, for the proposal base sampler, those of each proposal iteration."""

    num_samples: int
    """n."""
    num_proposal_samples: Tuple[int, ...] = ()
    """Samples of each proposal iteration."""


@dataclass
class ProposalConfig:
    """The proposal networks of the proposal base sampler (K-Planes): samples, planes, update schedule."""

    num_samples: Tuple[int, ...] = (256, 128)
    """Samples per ray of each proposal iteration."""
    resolutions: Tuple[int, ...] = (128, 256)
    """Spatial resolution of each proposal network's planes."""
    feature_dim: int = 8
    """Plane channels of the proposal networks."""
    time_resolution: Optional[int] = None
    """Temporal resolution of the proposal networks; None uses half the frames (K-Planes)."""
    warmup: int = 5000
    """Steps over which the update interval grows from 1 to ``update_every``."""
    update_every: int = 5
    """Update the proposal networks every this many steps after the warmup."""
    weight_anneal: bool = True
    """Anneal the proposal weights before PDF sampling (Mip-NeRF 360, Eq 18)."""
    anneal_slope: float = 10.0
    """Slope of the annealing function."""
    anneal_iterations: int = 1000
    """Iterations over which the annealing reaches 1."""


class GearSampler(nn.Module):
    """Base sampler, then the split sampler (Sec 4.4): each base sample at gear p becomes split_base^(p-1) samples.

    Args:
        counts: samples per ray in training (and the forward pass).
        render_counts: samples per ray of full-image renders (``rendering``), where they differ.
        split_base: 2 in the paper.
        proposal_networks: the proposal density fields (owned by the model); none: stratified uniform base samples.
        schedule: the proposal networks' update schedule and annealing (with proposal networks).
        unbounded: the proposal sampler starts from samples uniform in disparity far away.
    """

    def __init__(
        self,
        counts: SampleCounts,
        render_counts: SampleCounts,
        split_base: int,
        proposal_networks: Sequence[ProposalDensityField] = (),
        schedule: Optional[ProposalConfig] = None,
        unbounded: bool = False,
    ) -> None:
        super().__init__()
        self.split_base = split_base
        self.render_counts = render_counts
        self.proposal_networks = tuple(proposal_networks)
        self.schedule = schedule
        if not self.proposal_networks:
            self.base: nn.Module = UniformSampler(num_samples=counts.num_samples)
            return
        assert schedule is not None
        if len(render_counts.num_proposal_samples) != len(self.proposal_networks):
            raise InputError(
                f"--pipeline.model.render.num-proposal-samples has {len(render_counts.num_proposal_samples)} values "
                f"but the model has {len(self.proposal_networks)} proposal iterations "
                "(--pipeline.model.proposal.num-samples)"
            )

        def update_schedule(step: int) -> float:
            return np.clip(np.interp(step, [0, schedule.warmup], [0, schedule.update_every]), 1, schedule.update_every)

        self.base = ProposalNetworkSampler(
            num_proposal_samples_per_ray=counts.num_proposal_samples,
            num_nerf_samples_per_ray=counts.num_samples,
            num_proposal_network_iterations=len(counts.num_proposal_samples),
            update_sched=update_schedule,
            initial_sampler=UniformLinDispPiecewiseSampler() if unbounded else UniformSampler(),
        )

    def forward(self, rays: RayBundle, gear_levels: GearLevelFn) -> GearSamples:
        """Base samples of ``rays``, their levels ``gear_levels(positions, times)`` and their split."""
        if self.proposal_networks:
            density_fns = [functools.partial(net.density_fn, times=rays.times) for net in self.proposal_networks]
            base, weights, samples = self.base(rays, density_fns=density_fns)
        else:
            base, weights, samples = self.base(rays), [], []
        levels = gear_levels(base.frustums.get_positions(), base.times)
        return GearSamples(base, levels, split_ray_samples(base, levels, self.split_base), weights, samples)

    @contextlib.contextmanager
    def rendering(self) -> Iterator[int]:
        """Inside, the base sampler draws the samples per ray of full-image renders (``render_counts``); yields n."""
        sampler, counts = self.base, self.render_counts
        if isinstance(sampler, ProposalNetworkSampler):
            settings = {
                "num_nerf_samples_per_ray": counts.num_samples,
                "num_proposal_samples_per_ray": counts.num_proposal_samples,
            }
        else:
            settings = {"num_samples": counts.num_samples}
        before = {name: getattr(sampler, name) for name in settings}
        for name, value in settings.items():
            setattr(sampler, name, value)
        try:
            yield counts.num_samples
        finally:
            for name, value in before.items():
                setattr(sampler, name, value)

    def training_callbacks(self) -> List[TrainingCallback]:
        """Proposal weight annealing (Mip-NeRF 360, Eq 18) and the proposal networks' update schedule, when the
        proposal base sampler anneals; none otherwise."""
        sampler, schedule = self.base, self.schedule
        if not isinstance(sampler, ProposalNetworkSampler) or schedule is None or not schedule.weight_anneal:
            return []

        def set_anneal(step: int) -> None:
            fraction = np.clip(step / schedule.anneal_iterations, 0, 1)
            slope = schedule.anneal_slope
            sampler.set_anneal((slope * fraction) / ((slope - 1) * fraction + 1))

        return [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], set_anneal, update_every_num_iters=1),
            TrainingCallback(
                [TrainingCallbackLocation.AFTER_TRAIN_ITERATION], sampler.step_cb, update_every_num_iters=1
            ),
        ]
