"""Free-viewpoint tracking (Gear-NeRF Sec 4.5) inside nerfstudio's viewer.

"Select object" arms one click; the click's ray (from viser, in world coordinates) is traced to the 3D
point where it first meets a surface at the viewer's current time (`click.click_point`), and the object's
mask in the clicked view (the point as a positive prompt on the rendered SAM features) tells the user what
was selected. From then on the viewer's renders add the output "tracked_mask": the rendered colour with the
object's mask highlighted, for the viewer's own camera and time. The mask comes from the stored point
projected into that camera as a positive prompt on the rendered SAM features at the clicked time, and from
the prompts carried frame by frame to the time slider's time (`propagation.track`, embedding propagation).

Costs: nothing runs for renders that are not the viewer's (training steps, evaluation images, ns-eval,
ns-render), while no object is selected, or while the viewer shows another output. The SAM features of a
view are rendered at the centres of the backend's grid cells, on the view scaled to grid_size pixels on its longer
side (`sam_view`): grid_size^2 rays at most (64 x 64 for the built-in backend and SAM) per view and time, whatever
the render's resolution ('Max res'), and the same rays at every resolution, so the mask does not change when the
viewer goes from its moving to its still resolution, and at the clicked time it is the click's own. They are kept
per time (until the camera moves or a training step changes the model), so moving the time slider or the
resolution renders only the times not rendered yet.

A click does not wait for the viewer's render in progress: nerfstudio holds the viewer's lock (`train_lock`)
for a whole render, which at the default 'Max res' 512 takes minutes on a CPU, and wraps every GUI callback
in that lock. The buttons here touch no model and take no lock; a click (in one of viser's threads, not the
render thread) interrupts the render in progress as a camera move does, then selects under the lock: one
ray for the point, one feature map and one decoding for the mask in the clicked view, about a second on a
CPU. The status text says "Selecting..." meanwhile, then the selection or why there is none; both go to
the log.

The viewer decodes the rendered SAM features with the depth cue, as `ns-gear-track` does (but without its multi-view
agreement, which renders every training view for the clicked mask: seconds per click on a CPU). In a view as the viewer
renders it (75 degrees, 64 pixels on the longer side, at the held-out camera's pose), one click per object
(3 trained runs each; tracking_real.md) gave the built-in stand-in a mask of mean IoU
9.8 on the features alone and 56.8 with the cue for a person on the real `panoptic` capture (20.5 and 58.0 on the 31
cameras), and 85.3 and 77.6 on the synthetic spheres, where two spheres that touch at one depth are one object to the
cue. The decoder ranks the features alone's candidates beside the cue's (`builtin_backend`); with the cue alone, a
click on a sphere of the browser test's model (400 iterations, 32x24 images) had taken a third of the view.

The pipeline owns this module and hands it the SAM backend; the model only calls its render hook.
"""

from __future__ import annotations

import contextlib
import copy
import math
import threading
import time as clock
import weakref
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Dict, Optional, Tuple

import numpy as np
import torch
import viser.transforms as vtf
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer_elements import ViewerButton, ViewerClick, ViewerControl, ViewerText
from PIL import Image
from torch import Tensor

from gear_nerfstudio.sam.interface import Embedding, SamBackend
from gear_nerfstudio.tracking.click import TrackingError, click_point, project_prompt
from gear_nerfstudio.tracking.propagation import render_embedding, segment, track

if TYPE_CHECKING:
    import viser
    from nerfstudio.models.base_model import Model
    from nerfstudio.viewer.render_state_machine import RenderStateMachine
    from nerfstudio.viewer.viewer import Viewer

OUTPUT = "tracked_mask"
"""Name of the viewer output with the tracked object highlighted."""
HIGHLIGHT = (0.0, 1.0, 0.3)
"""Colour blended into the tracked object's pixels."""
HIGHLIGHT_WEIGHT = 0.6
"""Share of the highlight colour in a masked pixel."""
TIME_DIGITS = 6
"""Decimals of a time as a key of the kept features (float32 camera times and float64 frame times agree)."""


FOV_TOLERANCE = 1e-4
"""Largest difference of vertical field of view (radians) between two renders of one view."""


def sam_view(camera: Cameras, grid_size: int) -> Cameras:
    """A copy of a single camera scaled to grid_size pixels on its longer side (nerfstudio's
    `rescale_output_resolution`): a pixel of it is a cell of SAM's grid, so its SAM features are the same rays at
    any resolution of the camera."""
    view = copy.deepcopy(camera)
    view.rescale_output_resolution(grid_size / max(int(camera.width), int(camera.height)), scale_rounding_mode="round")
    return view


def same_view(camera: Cameras, other: Cameras) -> bool:
    """Whether two single cameras show one view at two resolutions: the same pose and vertical field of view
    (within FOV_TOLERANCE), and aspect ratios that differ by no more than the rounding of each image's width to
    whole pixels (1 / height each)."""

    def shape(c: Cameras) -> Tuple[float, float, float]:
        return 2.0 * math.atan(float(c.cy) / float(c.fy)), float(c.cx) / float(c.cy), float(c.height)

    (fov, aspect, height), (other_fov, other_aspect, other_height) = shape(camera), shape(other)
    return (
        torch.equal(camera.camera_to_worlds.cpu(), other.camera_to_worlds.cpu())
        and abs(fov - other_fov) < FOV_TOLERANCE
        and abs(aspect - other_aspect) <= 1.0 / height + 1.0 / other_height
    )


@dataclass
class Selection:
    """A clicked object: the 3D point its click ray meets and the time of the click."""

    point: Float[Tensor, "3"]
    time: float


def viewer_render_thread() -> Optional["RenderStateMachine"]:
    """The viewer's render thread that the caller runs in; None outside the viewer's renders."""
    from nerfstudio.viewer.render_state_machine import RenderStateMachine

    thread = threading.current_thread()
    return thread if isinstance(thread, RenderStateMachine) else None


def shows(thread: "RenderStateMachine", output: str) -> bool:
    """Whether the viewer of a render thread shows `output` (in full or in its split screen)."""
    panel = thread.viewer.control_panel
    return output == panel.output_render or (panel.split and output == panel.split_output_render)


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


def clicked_view(viewer: "Viewer", click: ViewerClick, longer_side: int) -> Optional[Cameras]:
    """The camera of the browser client that clicked (the one whose camera sits at the click ray's origin),
    as the viewer renders it, with `longer_side` pixels along its longer side; None without a client."""
    from nerfstudio.viewer.utils import get_camera
    from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

    clients = list(viewer.viser_server.get_clients().values())
    if not clients:
        return None
    origin = np.asarray(click.origin) * VISER_NERFSTUDIO_SCALE_RATIO
    client = min(clients, key=lambda c: float(np.linalg.norm(np.asarray(c.camera.position) - origin)))
    state = viewer.get_camera_state(client)
    height = max(int(round(longer_side / max(state.aspect, 1.0))), 1)
    return get_camera(state, height, max(int(round(height * state.aspect)), 1))


class TrackingViewerControl(ViewerControl):
    """The viewer's control handle. New browser clients start at the held-out camera (nerfstudio's default
    view sits at the scene origin, where a forward-facing capture is not defined; at a training camera the
    frustum the viewer draws for its image covers the view). `on_setup` runs once the viewer has installed
    the GUI elements."""

    def __init__(self, on_setup: Callable[["Viewer"], None]) -> None:
        self.on_setup = on_setup

    def _setup(self, viewer: "Viewer") -> None:
        from nerfstudio.viewer.viewer import VISER_NERFSTUDIO_SCALE_RATIO

        super()._setup(viewer)
        c2w = viewer.pipeline.datamanager.eval_dataset.cameras.camera_to_worlds[0].cpu().numpy()
        rotation = vtf.SO3.from_matrix(c2w[:3, :3]) @ vtf.SO3.from_x_radians(np.pi)
        position = c2w[:3, 3] * VISER_NERFSTUDIO_SCALE_RATIO

        def start_at_camera(client: "viser.ClientHandle") -> None:
            with client.atomic():
                client.camera.position = position
                client.camera.wxyz = rotation.wxyz

        viewer.viser_server.on_client_connect(start_at_camera)
        self.on_setup(viewer)


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
        self.view: Optional[Cameras] = None
        """The last clicked or rendered view (`sam_view`) whose features are kept."""
        self.viewer_control = TrackingViewerControl(self._without_lock)
        self.select_button = ViewerButton("Select object (then click it)", cb_hook=self._arm)
        self.clear_button = ViewerButton("Clear selection", cb_hook=self._clear)
        self.status = ViewerText("Tracked", "nothing selected", disabled=True)

    def _without_lock(self, viewer: "Viewer") -> None:
        """Undo the viewer's wrapping of these elements' callbacks in its lock (and a render after each): the
        buttons touch no model, and the status is only written here."""
        self.select_button.cb_hook = self._arm
        self.clear_button.cb_hook = self._clear
        self.status.cb_hook = lambda _: None

    def _arm(self, _: ViewerButton) -> None:
        self.viewer_control.register_pointer_cb("click", self._on_click)
        self.status.value = "click the object in the view"

    def _clear(self, _: ViewerButton) -> None:
        self.selection = None
        self.status.value = "nothing selected"
        self.viewer_control.viewer._trigger_rerender()

    def _on_click(self, click: ViewerClick) -> None:
        """Viewer click (in one of viser's threads): one click selects; the time is the viewer's time slider's.
        The render in progress is interrupted, so that the selection waits for the viewer's lock for at most a
        low-resolution render."""
        self.viewer_control.unregister_pointer_cb()
        viewer = self.viewer_control.viewer
        time = float(viewer.control_panel.time) if viewer.include_time else 0.0
        self.status.value = "Selecting..."
        CONSOLE.log(f"Tracking: selecting the object under the click at time {time:.2f}")
        start = clock.perf_counter()
        try:
            viewer._trigger_rerender()  # interrupts a render in progress, which holds the lock
            with viewer.train_lock if viewer.train_lock is not None else contextlib.nullcontext():
                self.select(click, time, clicked_view(viewer, click, self.backend.grid_size))
        except Exception as error:
            self.selection = None
            self.status.value = f"nothing selected: {type(error).__name__}: {error}"
            raise
        finally:
            CONSOLE.log(f"Tracking: {self.status.value} ({clock.perf_counter() - start:.1f} s)")
        viewer._trigger_rerender()

    def select(self, click: ViewerClick, time: float, view: Optional[Cameras] = None) -> None:
        """Store the 3D point that the click's ray meets at `time` (Sec 4.5); with the clicked `view`, also
        segment the object there. A miss, or an empty mask, clears the selection; the status text says which,
        or how much of the view the object's mask covers."""
        try:
            ray = ray_camera(torch.tensor(click.origin), torch.tensor(click.direction))
            point = click_point(self._model(), ray, (0.5, 0.5), time)
            share = None if view is None else self.mask_share(view, point, time)
        except TrackingError as error:
            self.selection = None
            self.status.value = f"nothing selected: {error}"
            return
        self.selection = Selection(point=point, time=time)
        x, y, z = point.tolist()
        covers = "" if share is None else f", its mask {100 * share:.1f}% of the view"
        self.status.value = f"point ({x:.3f}, {y:.3f}, {z:.3f}) at time {time:.2f}{covers}; output '{OUTPUT}'"

    def mask_share(self, view: Cameras, point: Float[Tensor, "3"], time: float) -> float:
        """Share of `view` that the mask prompted by `point` at `time` covers (its SAM features: at most
        grid_size^2 rays); a TrackingError when the mask is empty."""
        view = self._see(view)
        mask = segment(self.backend, self._embedding(time), np.array([project_prompt(view, point)]), np.array([1]))
        if not mask.any():
            raise TrackingError("the decoder's mask for the clicked point is empty")
        return float(mask.mean())

    def forget(self, step: int = 0) -> None:
        """Drop the kept features (a training step changed the model)."""
        self.embeddings = {}

    def render_hook(self, camera: Cameras, outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """The model's render hook: "tracked_mask" for the viewer's renders while an object is selected; while
        the viewer shows another output, the colour image itself (the viewer lists the outputs it is given)."""
        thread = viewer_render_thread()
        if self.selection is None or thread is None:
            return {}
        return {OUTPUT: self.overlay(camera, outputs["rgb"]) if shows(thread, OUTPUT) else outputs["rgb"]}

    def overlay(self, camera: Cameras, rgb: Float[Tensor, "H W 3"]) -> Float[Tensor, "H W 3"]:
        """The colour image of a rendered camera with the selected object's mask highlighted; unchanged when
        nothing is selected or the selected point is behind or outside the camera."""
        selection = self.selection
        if selection is None:
            return rgb
        view = self._see(camera)
        try:
            pixel = project_prompt(view, selection.point)
        except TrackingError:
            return rgb
        time = 0.0 if camera.times is None else float(camera.times.reshape(-1)[0])
        masks = track(
            self.backend, self._embedding, np.array([pixel]), np.array([1]), selection.time, [time], self._model().num_frames
        )
        mask = next(m.mask for m in masks if m.time == time)
        height, width = rgb.shape[:2]
        if mask.shape != (height, width):
            mask = np.array(Image.fromarray(mask).resize((width, height), Image.NEAREST))
        return highlight(rgb, mask)

    def _see(self, camera: Cameras) -> Cameras:
        """The kept view when `camera` shows it (`same_view`); else `camera` at SAM's grid (`sam_view`), kept from now
        on in place of the last, whose features are dropped."""
        if self.view is None or not same_view(camera, self.view):
            self.view, self.embeddings = sam_view(camera, self.backend.grid_size), {}
        return self.view

    def _embedding(self, time: float) -> Embedding:
        """The SAM features (and depth cue) of the kept view at a time, rendered once."""
        key = round(time, TIME_DIGITS)  # the slider's float32 time and the frames' times meet
        if key not in self.embeddings:
            self.embeddings[key] = render_embedding(self._model(), self.view, time, self.backend)
        return self.embeddings[key]
