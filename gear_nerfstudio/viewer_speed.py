"""The viewer's resolutions chosen from the model's measured render speed. nerfstudio's viewer is made for a GPU: a
still view at 'Max res' 512 (147,000 pixels at 16:9: about 6 s at the 23,000 pixels per second of `gear-nerf-small`
on one CPU core) and 30 frames per second while the camera moves (frames of 30 pixels' height on a CPU).

When the viewer starts, a render of the first held-out camera rescaled to about ``PROBE_PIXELS`` pixels measures the
model's pixels per second p (after a smaller untimed render; repeated at 16 times the pixels when too quick to time).
Then:

- still: 'Max res' = sqrt(p x ``STILL_SECONDS`` x 16 / 9), the largest 16:9 view that renders in ``STILL_SECONDS``,
  rounded down to a multiple of 64 within [128, 2048];
- moving: p / ``MOVING_PIXELS`` frames per second, within [``FEWEST_FRAMES_PER_SECOND``, 30]. nerfstudio sizes a
  frame while the camera moves as its measured rays per second over that rate, so a frame has ``MOVING_PIXELS``
  pixels where the speed allows, fewer on a slower machine, and renders in at most 1 / ``FEWEST_FRAMES_PER_SECOND``
  seconds: a moved camera is redrawn within about a second (issue 25).
"""

from __future__ import annotations

import contextlib
import math
import time
import weakref
from typing import TYPE_CHECKING

import torch
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer_elements import ViewerControl

if TYPE_CHECKING:
    import viser
    from nerfstudio.models.base_model import Model
    from nerfstudio.viewer.viewer import Viewer

PROBE_PIXELS = 4096
"""Pixels of the first timing render."""
STILL_SECONDS = 2.0
"""Render time of a still view at 'Max res'."""
MOVING_PIXELS = 6000
"""Pixels of a frame while the camera moves, where the speed allows (about 103 x 58 at 16:9)."""
MOST_FRAMES_PER_SECOND = 30.0
"""nerfstudio's rate while the camera moves."""
FEWEST_FRAMES_PER_SECOND = 2.0
"""Slowest rate while the camera moves: a frame renders in half a second, which leaves the other half of a second
for the viewer's round trip to the browser."""


def still_resolution(pixels_per_second: float) -> int:
    """'Max res' of a 16:9 still view that renders in ``STILL_SECONDS``."""
    side = math.sqrt(pixels_per_second * STILL_SECONDS * 16 / 9)
    return int(min(2048, max(128, side // 64 * 64)))


def moving_rate(pixels_per_second: float) -> float:
    """Frames per second while the camera moves: frames of ``MOVING_PIXELS`` pixels, unless that takes longer than
    1 / ``FEWEST_FRAMES_PER_SECOND`` seconds."""
    return min(MOST_FRAMES_PER_SECOND, max(FEWEST_FRAMES_PER_SECOND, pixels_per_second / MOVING_PIXELS))


@torch.no_grad()
def render_speed(model: "Model", viewer: "Viewer") -> float:
    """Pixels per second of a full-image render of the first held-out camera, in evaluation mode, under the viewer's
    lock: a browser that connected early waits with its first render instead of sharing the CPU with the timing."""
    cameras = viewer.pipeline.datamanager.eval_dataset.cameras
    pixels = float(cameras.width[0, 0] * cameras.height[0, 0])
    was_training = model.training
    with viewer.train_lock or contextlib.nullcontext():
        model.eval()
        try:
            for scale in (1 / 16, 1, 16):  # the first, untimed, pays for what a model does once
                probe = cameras[0:1].to(model.device)
                probe.rescale_output_resolution(math.sqrt(scale * PROBE_PIXELS / pixels))
                start = time.perf_counter()
                model.get_outputs_for_camera(probe)
                seconds = time.perf_counter() - start
                if scale >= 1 and seconds > 0.1:
                    break
        finally:
            model.train(was_training)
    return float(probe.width[0, 0] * probe.height[0, 0]) / seconds


class ViewerSpeed(ViewerControl):
    """Sets the viewer's 'Max res' and its rate while the camera moves from the measured render speed, when the
    viewer starts; a pipeline attribute, so the viewer finds it.

    Args:
        model: the model whose renders the viewer shows (kept as a weak reference).
    """

    def __init__(self, model: "Model") -> None:
        self._model = weakref.ref(model)

    def _setup(self, viewer: "Viewer") -> None:
        super()._setup(viewer)
        speed = render_speed(self._model(), viewer)
        resolution, rate = still_resolution(speed), moving_rate(speed)
        viewer.control_panel._max_res.value = resolution  # the slider "Max res"; its property is read-only

        def set_rate(client: "viser.ClientHandle") -> None:
            viewer.render_statemachines[client.client_id].target_fps = rate

        viewer.viser_server.on_client_connect(set_rate)
        CONSOLE.print(
            f"Gear-NeRF viewer: {speed:,.0f} pixels per second measured: 'Max res' {resolution} when still, "
            f"{rate:.1f} frames per second while the camera moves.",
            soft_wrap=True,
        )
