"""Per-camera appearance codes: the cameras of a real rig differ in exposure and white balance.

Each camera of the rig has a learned code that enters the colour MLP (as nerfacto's per-image appearance
embedding, here one code per camera: a rig's cameras keep their settings over the video, and a code per image
could also absorb what moves). A ray carries its camera in ``ray_bundle.metadata["rig_camera"]`` (set by the
dataparsers); a camera that was never trained (the held-out one) or a ray without a camera (the viewer, camera
paths) gets the mean of the trained cameras' codes: the rig's average appearance.
"""

from __future__ import annotations

from typing import Dict, Optional, Sequence

import torch
from jaxtyping import Float, Int
from torch import Tensor, nn

RIG_CAMERA = "rig_camera"
"""Key of the rig camera index (into the dataset's ``camera_names``) in cameras' and rays' metadata."""


class CameraAppearance(nn.Module):
    """Appearance codes of a rig's cameras.

    Args:
        num_cameras: cameras of the rig (the held-out one included).
        dim: channels of a code.
        trained_cameras: indices of the cameras with training images.
    """

    def __init__(self, num_cameras: int, dim: int, trained_cameras: Sequence[int]) -> None:
        super().__init__()
        self.dim = dim
        self.codes = nn.Embedding(max(1, num_cameras), dim)
        nn.init.normal_(self.codes.weight, std=0.01)
        trained = torch.zeros(max(1, num_cameras), dtype=torch.bool)
        trained[torch.as_tensor(list(trained_cameras), dtype=torch.long)] = True
        self.register_buffer("trained", trained)

    def mean_code(self) -> Float[Tensor, "dim"]:
        """The mean code of the trained cameras: the appearance of any other camera."""
        return self.codes.weight[self.trained].mean(dim=0)

    def forward(self, metadata: Dict[str, Tensor], num_rays: int) -> Float[Tensor, "num_rays dim"]:
        """The code of each ray's camera (``metadata[RIG_CAMERA]``, (num_rays, 1)); the mean code for rays of an
        untrained camera or without one."""
        cameras: Optional[Int[Tensor, "num_rays 1"]] = metadata.get(RIG_CAMERA)
        mean = self.mean_code().expand(num_rays, self.dim)
        if cameras is None:
            return mean
        index = cameras.reshape(-1).long().clamp(0, len(self.trained) - 1)
        return torch.where(self.trained[index][:, None], self.codes(index), mean)
