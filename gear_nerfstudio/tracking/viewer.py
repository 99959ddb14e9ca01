"""Free-viewpoint tracking (Gear-NeRF Sec 4.5) inside nerfstudio's viewer.

"Select object" arms one click; the click's ray (from viser, in world coordinates) is traced to the 3D
point where it first meets a surface at the viewer's current time (`click.click_point`). From then on every
render of the viewer adds the output "tracked_mask": the rendered colour with the object's mask highlighted,
for the viewer's own camera and time. The mask comes from the stored point projected into that camera as a
positive prompt on the rendered SAM features at the clicked time, and from the prompts carried frame by frame
to the time slider's time (`propagation.track`, embedding propagation).

Costs: nothing runs for renders that are not the viewer's (training steps, evaluation images, ns-eval,
ns-render) or while no object is selected. The rendered SAM features of the viewer's camera are kept per
time (until the camera moves or a training step changes the model), so moving the time slider renders only
the times not rendered yet, not every frame between the click and the slider.

The pipeline owns this module and hands it the SAM backend; the model only calls its render hook.
"""

from __future__ import annotations

import contextlib
import threading
import weakref
from dataclasses import dataclass
from typing import TYPE_CHECKING, Dict, Optional, Tuple

import numpy as np
import torch
import viser.transforms as vtf
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer_elements import ViewerButton, ViewerClick, ViewerControl, ViewerText
from torch import Tensor

from gear_nerfstudio.sam.interface import Embedding, SamBackend
from gear_nerfstudio.tracking.click import TrackingError, click_point, project_prompt
from gear_nerfstudio.tracking.propagation import render_embedding, track

if TYPE_CHECKING:
    import viser
    from nerfstudio.models.base_model import Model
    from nerfstudio.viewer.viewer import Viewer

HIGHLIGHT = (0.0, 1.0, 0.3)
"""Colour blended into the tracked object's pixels."""
HIGHLIGHT_WEIGHT = 0.6
"""Share of the highlight colour in a masked pixel."""
TIME_DIGITS = 6
"""Decimals of a time as a key of the kept features (float32 camera times and float64 frame times agree)."""


@dataclass
class Selection:
    """A clicked object: the 3D point its click ray meets and the time of the click."""

    point: Float[Tensor, "3"]
    time: float


def in_viewer_render() -> bool:
    """Whether the caller runs in one of the viewer's render threads."""
    from nerfstudio.viewer.render_state_machine import RenderStateMachine

    return isinstance(threading.current_thread(), RenderStateMachine)


def view_key(camera: Cameras) -> Tuple[float, ...]:
    """The pose and intrinsics of a single camera: two renders with the same key see the same image."""
    values = [camera.camera_to_worlds, camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height]
    return tuple(float(v) for value in values for v in value.reshape(-1).tolist())


def ray_camera(origin: Float[Tensor, "3"], direction: Float[Tensor, "3"]) -> Cameras:
    """A one-pixel pinhole camera at `origin` whose only pixel centre (0.5, 0.5) looks along `direction`."""
    back = -torch.nn.functional.normalize(direction.float(), dim=0)
    helper = torch.tensor([0.0, 0.0, 1.0]) if abs(float(back[2])) < 0.9 else torch.tensor([0.0, 1.0, 0.0])
    right = torch.nn.functional.normalize(torch.linalg.cross(helper, back), dim=0)
    up = torch.linalg.cross(back, right)
    c2w = torch.stack([right, up, back, origin.float()], dim=1)
    return Cameras(camera_to_worlds=c2w[None], fx=1.0, fy=1.0, cx=0.5, cy=0.5, width=1, height=1)


def highlight(rgb: Float[Tensor, "H W 3"], mask: np.ndarray) -> Float[Tensor, "H W 3"]:
    """The colour image with the masked pixels blended towards HIGHLIGHT."""
    inside = torch.as_tensor(mask, device=rgb.device)[..., None]
    colour = torch.tensor(HIGHLIGHT, dtype=rgb.dtype, device=rgb.device)
    return torch.where(inside, (1.0 - HIGHLIGHT_WEIGHT) * rgb + HIGHLIGHT_WEIGHT * colour, rgb)


class TrackingViewerControl(ViewerControl):
    """The viewer's control handle; new browser clients start at the first training camera, where a
    forward-facing capture is defined and its objects can be clicked (nerfstudio's default view sits
    at the scene origin)."""

    def _setup(self, viewer: "Viewer") -> None:
        super()._setup(viewer)
        cameras = viewer.pipeline.datamanager.train_dataset.cameras
        c2w = cameras.camera_to_worlds[0].cpu().numpy()
        rotation = vtf.SO3.from_matrix(c2w[:3, :3]) @ vtf.SO3.from_x_radians(np.pi)
        from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

        position = c2w[:3, 3] * VISER_NERFSTUDIO_SCALE_RATIO

        def start_at_training_camera(client: "viser.ClientHandle") -> None:
            with client.atomic():
                client.camera.position = position
                client.camera.wxyz = rotation.wxyz

        viewer.viser_server.on_client_connect(start_at_training_camera)


class ViewerTracking(torch.nn.Module):
    """Viewer controls and click state of Sec 4.5 tracking; a pipeline attribute, so the viewer shows its
    elements. It has no parameters and adds nothing to checkpoints.

    Args:
        model: the model whose renders are tracked (kept as a weak reference).
        backend: the SAM decoder.
    """

    def __init__(self, model: "Model", backend: SamBackend) -> None:
        super().__init__()
        self._model = weakref.ref(model)  # a plain reference would make the model a submodule
        self.backend = backend
        self.selection: Optional[Selection] = None
        self.embeddings: Dict[float, Embedding] = {}
        """Rendered SAM features of the viewer camera ``self.view`` by time."""
        self.view: Optional[Tuple[float, ...]] = None
        self.viewer_control = TrackingViewerControl()
        self.select_button = ViewerButton("Select object (then click it)", cb_hook=self._arm)
        self.clear_button = ViewerButton("Clear selection", cb_hook=self._clear)
        self.status = ViewerText("Tracked", "nothing selected", disabled=True)

    def _arm(self, _: ViewerButton) -> None:
        self.viewer_control.register_pointer_cb("click", self._on_click)

    def _clear(self, _: ViewerButton) -> None:
        self.selection = None
        self.status.value = "nothing selected"

    def _on_click(self, click: ViewerClick) -> None:
        """Viewer click: one click selects; the time is the viewer's time slider's."""
        self.viewer_control.unregister_pointer_cb()
        viewer = self.viewer_control.viewer
        time = float(viewer.control_panel.time) if viewer.include_time else 0.0
        with viewer.train_lock if viewer.train_lock is not None else contextlib.nullcontext():
            self.select(click, time)

    def select(self, click: ViewerClick, time: float) -> None:
        """Store the 3D point that the click's ray meets at `time` (Sec 4.5); a miss clears the
        selection. The status text tells the user either way (and makes the viewer render again)."""
        camera = ray_camera(torch.tensor(click.origin), torch.tensor(click.direction))
        try:
            point = click_point(self._model(), camera, (0.5, 0.5), time)
        except TrackingError as error:
            self.selection = None
            CONSOLE.log(f"[yellow]Tracking: {error}")
            self.status.value = f"nothing selected: {error}"
            return
        self.selection = Selection(point=point, time=time)
        x, y, z = point.tolist()
        self.status.value = f"point ({x:.3f}, {y:.3f}, {z:.3f}) at time {time:.2f}; output 'tracked_mask'"

    def forget(self, step: int = 0) -> None:
        """Drop the kept features (a training step changed the model)."""
        self.embeddings = {}

    def render_hook(self, camera: Cameras, outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """The model's render hook: "tracked_mask" for the viewer's renders while an object is selected."""
        if self.selection is None or not in_viewer_render():
            return {}
        return {"tracked_mask": self.overlay(camera, outputs["rgb"])}

    def overlay(self, camera: Cameras, rgb: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
        """The colour image of a rendered camera with the selected object's mask highlighted; unchanged when
        nothing is selected or the selected point is behind or outside the camera."""
        selection = self.selection
        if selection is None:
            return rgb
        model = self._model()
        time = 0.0 if camera.times is None else float(camera.times.reshape(-1)[0])
        try:
            pixel = project_prompt(camera, selection.point)
        except TrackingError:
            return rgb
        view = view_key(camera)
        if view != self.view:
            self.view, self.embeddings = view, {}

        def embedding_at(time_: float) -> Embedding:
            key = round(time_, TIME_DIGITS)  # the slider's float32 time and the frames' times meet
            if key not in self.embeddings:
                self.embeddings[key] = render_embedding(model, camera, time_, self.backend)
            return self.embeddings[key]

        masks = track(self.backend, embedding_at, np.array([pixel]), np.array([1]), selection.time, [time], model.num_frames)
        return highlight(rgb, next(m.mask for m in masks if m.time == time))
