"""Motion-aware spatial sampling (Gear-NeRF, Sec 4.4): split each sample at gear p into 2^(p-1).

Rays end up with different numbers of samples. They are stored padded: row r holds the sub-samples of
ray r in order along the ray, followed by zero-length segments at the ray's far end. A zero-length
segment has delta = 0, hence alpha = 0 and weight 0 in ``RaySamples.get_weights``, and it leaves the
transmittance of the real samples untouched, so nerfstudio's renderers work unchanged. The field is
evaluated only on the real (packed) sub-samples; ``unpack`` fills each padding slot with the values of
the ray's last real sub-sample, which keeps the ``"last_sample"`` background colour correct.

Padding costs memory and time in proportion to the batch's longest ray: a few upshifted rays make every
row that long. Wide per-sample outputs (SAM embedding, gear level) are therefore summed over the packed
sub-samples with ``accumulate`` instead of being unpacked.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from nerfstudio.cameras.rays import RaySamples

@dataclass
class SplitRaySamples:
    """Split samples, padded per ray, with the maps between padded and packed layouts."""

    ray_samples: RaySamples
    """Padded samples, shape (num_rays, max_samples); padding has start = end = the ray's far end."""
    valid: Bool[Tensor, "num_rays max_samples"]
    """True for real sub-samples, False for padding."""
    sample_index: Int[Tensor, "num_valid"]
    """Flat (row-major) padded index of each real sub-sample: the packed order."""
    packed_index: Int[Tensor, "num_rays max_samples"]
    """Packed index of each padded slot; padding points at the ray's last real sub-sample."""
    parent: Int[Tensor, "num_rays max_samples"]
    """Index, within its ray, of the base sample each slot was split from."""
    num_base_samples: int
    """Base samples per ray, n."""
    num_samples_per_ray: Int[Tensor, "num_rays"]
    """Real sub-samples per ray: sum over the ray's base samples of split_base^(p-1)."""
    ray_index: Int[Tensor, "num_valid"]
    """Ray of each real sub-sample, in packed order."""

    def pack(self, values: Tensor) -> Tensor:
        """(num_rays, max_samples, C) -> (num_valid, C)."""
        return values.reshape(-1, values.shape[-1])[self.sample_index]

    def unpack(self, values: Tensor) -> Tensor:
        """(num_valid, C) -> (num_rays, max_samples, C); padding copies the ray's last real sub-sample."""
        return values[self.packed_index]

    def accumulate(
        self, weights: Float[Tensor, "num_rays max_samples 1"], values: Float[Tensor, "num_valid C"]
    ) -> Float[Tensor, "num_rays C"]:
        """Eq 8: sum_i w_i values_i over each ray's real sub-samples (padding has weight 0 and is skipped)."""
        weighted = self.pack(weights) * values
        return weighted.new_zeros((weights.shape[0], values.shape[-1])).index_add(0, self.ray_index, weighted)

    def to_base(self, weights: Float[Tensor, "num_rays max_samples 1"]) -> Float[Tensor, "num_rays n 1"]:
        """Sum sub-sample weights into their base samples (exact: sub-segments tile the base segment)."""
        base = weights.new_zeros((weights.shape[0], self.num_base_samples, 1))
        return base.scatter_add(1, self.parent[..., None], weights)


def split_ray_samples(
    ray_samples: RaySamples, levels: Int[Tensor, "num_rays n"], split_base: int = 2
) -> SplitRaySamples:
    """Split base sample i of each ray into split_base^(p_i - 1) equal sub-segments of [start_i, end_i].

    Sub-segment j of c has start s + (e - s) * j / c and end s + (e - s) * (j + 1) / c, with the last end
    set to e: starts and ends are exact, consecutive sub-segments share their boundary bit for bit.
    Deltas are clamped at 0: delta in Eq 1 is a length, but nerfstudio's stratified sampler returns
    segments of about -5e-7 when near = far (rounding of x * far + (1 - x) * near), and a negative delta
    makes alpha = 1 - exp(-sigma delta) negative, i.e. weights outside [0, 1].
    """
    num_rays, num_base = levels.shape
    device = levels.device
    counts = split_base ** (levels.long() - 1)
    cumulative = counts.cumsum(dim=1)
    num_samples_per_ray = cumulative[:, -1]
    # the only host sync: the padded width and the packed length, read together
    max_samples, num_valid = (
        torch.stack([num_samples_per_ray.max(), num_samples_per_ray.sum()]).tolist() if num_rays else (0, 0)
    )

    slot = torch.arange(max_samples, device=device).expand(num_rays, max_samples)
    valid = slot < num_samples_per_ray[:, None]
    parent = torch.searchsorted(cumulative, slot.contiguous(), right=True).clamp(max=num_base - 1)
    count = counts.gather(1, parent)
    sub_index = slot - (cumulative.gather(1, parent) - count)

    starts = ray_samples.frustums.starts[..., 0]
    ends = ray_samples.frustums.ends[..., 0]
    parent_start = starts.gather(1, parent)
    parent_end = ends.gather(1, parent)
    length = parent_end - parent_start
    sub_start = parent_start + length * (sub_index / count)
    sub_end = torch.where(sub_index + 1 == count, parent_end, parent_start + length * ((sub_index + 1) / count))
    far_end = ends[:, -1:].expand(num_rays, max_samples)
    sub_start = torch.where(valid, sub_start, far_end)[..., None]
    sub_end = torch.where(valid, sub_end, far_end)[..., None]

    flat_parent = parent + torch.arange(num_rays, device=device)[:, None] * num_base
    gathered = ray_samples.reshape((num_rays * num_base,))[flat_parent]
    split = dataclasses.replace(
        gathered,
        frustums=dataclasses.replace(gathered.frustums, starts=sub_start, ends=sub_end),
        deltas=(sub_end - sub_start).clamp(min=0.0),
        spacing_starts=None,
        spacing_ends=None,
        spacing_to_euclidean_fn=None,
    )
    # packed sub-sample k of ray r sits at slot k - (first packed index of r) of row r
    ray_index = torch.repeat_interleave(
        torch.arange(num_rays, device=device), num_samples_per_ray, output_size=num_valid
    )
    first_packed = num_samples_per_ray.cumsum(0) - num_samples_per_ray
    sample_index = torch.arange(num_valid, device=device) + (ray_index * max_samples - first_packed[ray_index])
    return SplitRaySamples(
        ray_samples=split,
        valid=valid,
        sample_index=sample_index,
        packed_index=(valid.reshape(-1).long().cumsum(0) - 1).reshape(num_rays, max_samples),
        parent=parent,
        num_base_samples=num_base,
        num_samples_per_ray=num_samples_per_ray,
        ray_index=ray_index,
    )
