"""Tracking in the viewer (Sec 4.5) on a model trained with the real `ns-train` on a tiny synthetic N3D scene
with a fast sphere: the "tracked_mask" output of a selected object follows the viewer's camera and time;
the real `ns-viewer` in a real headless Chromium, at its default resolution, shows the scene at its first
view, its time slider shows the motion, and a click in the page selects the object under it within a minute
on a CPU."""

from __future__ import annotations

import io
import json
import math
import os
import re
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np
import pytest
import torch
from nerfstudio.cameras.cameras import CameraType
from PIL import Image
from scipy import ndimage

from gear_nerfstudio.tools.synthetic.scene import RigCamera, SyntheticScene, scene_objects
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene
from gear_nerfstudio.tracking.click import project_prompt
from gear_nerfstudio.tracking.propagation import render_embedding, track
from gear_nerfstudio.tracking.viewer import OUTPUT, Selection, highlight
from gear_nerfstudio.viewer_speed import STILL_SECONDS, moving_rate, still_resolution
from tests.conftest import BIN, ns

pytestmark = pytest.mark.cost(290)

STATIC_SPHERE, FAST_SPHERE = 1, 3
SPEC = SyntheticSpec(dataset="n3d", width=32, height=24, frames=4, cameras=5, motion="fast")
CHROMIUM, CHROMEDRIVER = shutil.which("chromium"), shutil.which("chromedriver")
CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync", "--window-size=1200,800",
)
VIEWER_FOV = math.radians(75.0)
"""Vertical field of view of viser's browser camera (three.js default), which the viewer renders with."""


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """400 iterations of the single-gear preset without learning-rate warm-up: every point has the full
    temporal resolution, so motion shows after a short run (the gears of gear-nerf-small only get it
    through the Sec 4.3 updates, which need a longer run)."""
    root = tmp_path_factory.mktemp("viewer")
    scene = write_synthetic_scene(root / "scene", SPEC)
    ns(
        "ns-train", "gear-nerf-baseline", "--output-dir", str(root / "runs"),
        "--experiment-name", "tiny", "--timestamp", "run", "--machine.device-type", "cpu", "--vis", "tensorboard",
        "--max-num-iterations", "400", "--steps-per-eval-all-images", "100000",
        "--pipeline.datamanager.train-num-rays-per-batch", "512", "--optimizers.fields.scheduler.warm-up-end", "0",
        "neural-3d-video-data", "--data", str(scene), "--cache-dir", str(root / "cache"), cwd=root,
    )
    return root, scene, root / "runs" / "tiny" / "gear-nerf-baseline" / "run" / "config.yml"


def rig_camera(scene: Path, name: str) -> dict:
    cameras = json.loads((scene / "ground_truth" / "scene.json").read_text())["cameras"]
    return next(c for c in cameras if c["name"] == name)


def ground_truth_view(scene: Path, name: str, frame: int, width: int, height: int, fov: float):
    """The synthetic scene rendered from rig camera `name`'s pose with a viewer's pinhole intrinsics."""
    camera = rig_camera(scene, name)
    focal = height / 2 / math.tan(fov / 2)
    view = RigCamera(
        name="viewer", rotation=np.array(camera["rotation_world_to_camera_opencv"]), centre=np.array(camera["centre"]),
        fx=focal, fy=focal, cx=width / 2, cy=height / 2, width=width, height=height,
    )
    return SyntheticScene(motion=SPEC.motion, supersample=1).render(view, frame)


def highlighted(outputs) -> np.ndarray:
    """Pixels that the tracked-mask overlay changed."""
    return (outputs["tracked_mask"] - outputs["rgb"]).abs().amax(dim=-1).numpy() > 1e-6


# --- the viewer's click callback and the model output, without a browser ----------------------------


@pytest.fixture(scope="module")
def loaded(trained):
    from nerfstudio.utils.eval_utils import eval_setup

    _, pipeline, _, _ = eval_setup(trained[2], test_mode="test")
    return pipeline


def surface_point(pipeline, scene: Path, object_id: int, frame: int, facing: str) -> torch.Tensor:
    """The point of a sphere's surface that faces rig camera `facing`, in the model's world coordinates."""
    sphere = next(o for o in scene_objects(SPEC.motion) if o.object_id == object_id)
    centre = sphere.centre(frame)
    towards = np.array(rig_camera(scene, facing)["centre"]) - centre
    point = torch.tensor(centre + sphere.radius * towards / np.linalg.norm(towards), dtype=torch.float32)
    outputs = pipeline.datamanager.train_dataparser_outputs
    transform = outputs.dataparser_transform
    return outputs.dataparser_scale * (transform[:, :3] @ point + transform[:, 3])


def viewer_render(model, camera, shown: str = OUTPUT):
    """``model.get_outputs_for_camera`` as the viewer calls it: in one of its render threads, with the output
    `shown` picked in the viewer's control panel."""
    from types import SimpleNamespace

    from nerfstudio.viewer.render_state_machine import RenderStateMachine

    class RenderThread(RenderStateMachine):
        def __init__(self) -> None:
            threading.Thread.__init__(self)
            panel = SimpleNamespace(output_render=shown, split=False, split_output_render=shown)
            self.viewer = SimpleNamespace(control_panel=panel)
            self.outputs = None

        def run(self) -> None:
            self.outputs = model.get_outputs_for_camera(camera)

    thread = RenderThread()
    thread.start()
    thread.join()
    return thread.outputs


def viewer_camera(pipeline, time_: float, width: int = 64, height: int = 48, x_shift: float = 0.0):
    """A camera as the viewer builds it, at cam00's pose (moved sideways by x_shift) with the viewer's
    intrinsics."""
    from nerfstudio.viewer.utils import CameraState, get_camera

    c2w = pipeline.datamanager.eval_dataset.cameras.camera_to_worlds[0].clone()
    c2w[:, 3] += x_shift * c2w[:, 0]
    state = CameraState(
        fov=math.radians(60.0), aspect=width / height, c2w=c2w, camera_type=CameraType.PERSPECTIVE, time=time_
    )
    return get_camera(state, height, width)


def test_a_selection_gives_a_tracked_mask_at_the_viewer_camera_and_time(trained, loaded):
    """The "tracked_mask" output of a viewer render highlights the selected object, at the clicked time and
    after the time slider moved; renders that are not the viewer's (training, evaluation) never get it, and
    while the viewer shows another output it is the colour image (no tracking work)."""
    from nerfstudio.viewer.viewer_elements import ViewerClick

    _, scene, _ = trained
    model, tracking = loaded.model, loaded.viewer_tracking
    held_out = loaded.datamanager.eval_dataset.cameras[0:1]
    width, height, fov = 64, 48, math.radians(60.0)

    tracking.selection = None
    assert "tracked_mask" not in viewer_render(model, viewer_camera(loaded, 0.0))  # nothing selected, no work

    # A click whose ray leaves the scene selects nothing and says why.
    centre = held_out.camera_to_worlds[0, :, 3]
    away = ViewerClick(tuple(centre.tolist()), tuple(held_out.camera_to_worlds[0, :, 2].tolist()), (0.5, 0.5))
    tracking.select(away, 0.0)
    assert tracking.selection is None and "hits nothing" in tracking.status.value
    assert "tracked_mask" not in viewer_render(model, viewer_camera(loaded, 0.0))

    # The static sphere selected at time 0 (as a click on it would store it), seen at times 0 and 1: at the
    # clicked time the mask is the object's; at every time the viewer shows exactly the mask that tracking
    # (ns-gear-track's propagation) gives for the viewer's camera and time.
    tracking.selection = Selection(point=surface_point(loaded, scene, STATIC_SPHERE, 0, "cam00"), time=0.0)
    for frame in (0, SPEC.frames - 1):
        time = frame / (SPEC.frames - 1)
        camera = viewer_camera(loaded, time)
        outputs = viewer_render(model, camera)
        x, y = project_prompt(camera, tracking.selection.point)
        backend = loaded.sam_backend
        tracked = track(backend, lambda t: render_embedding(model, camera, t, backend), np.array([[x, y]]), np.array([1]),
                        0.0, [time], SPEC.frames)  # fmt: skip
        expected = next(m.mask for m in tracked if m.time == time)
        assert expected.any() and torch.equal(outputs["tracked_mask"], highlight(outputs["rgb"], expected)), frame
        assert "tracked_mask" not in model.get_outputs_for_camera(camera)  # not a viewer render
        if frame == 0:
            mask = highlighted(outputs)
            truth = ground_truth_view(scene, "cam00", frame, width, height, fov).object_ids == STATIC_SPHERE
            near_prompt = np.zeros_like(mask)
            near_prompt[max(int(y) - 2, 0) : int(y) + 3, max(int(x) - 2, 0) : int(x) + 3] = True
            assert truth[int(y), int(x)], "the selected point does not project onto the object"
            assert (mask & near_prompt).any(), "the mask misses the selected point"
            assert (mask & truth).sum() > 0.3 * truth.sum(), "the mask misses the object"
            assert mask.sum() < 0.5 * mask.size, "the mask covers half the view"
    assert tracking.embeddings and all(e.depth is not None for e in tracking.embeddings.values())  # with the cue
    shows_rgb = viewer_render(model, camera, shown="rgb")
    assert shows_rgb["tracked_mask"] is shows_rgb["rgb"]
    tracking.selection = None


def test_moving_the_time_slider_renders_each_new_time_once(trained, loaded, monkeypatch):
    """With an object selected, the viewer's SAM features are rendered once per (view, time): sweeping the
    slider over the T frames renders T feature maps (without the cache: 1 + 2 + ... + T, every frame between the
    click and the slider at every step); the same view at another resolution (the viewer's still render after its
    moving one) renders none and highlights the same mask; a moved camera, or a training step, renders again."""
    import gear_nerfstudio.tracking.viewer as viewer_module

    _, scene, _ = trained
    tracking = loaded.viewer_tracking
    rendered = []

    def counting(model, camera, time_, backend):
        rendered.append(time_)
        return render_embedding(model, camera, time_, backend)

    monkeypatch.setattr(viewer_module, "render_embedding", counting)
    tracking.forget()
    tracking.selection = Selection(point=surface_point(loaded, scene, STATIC_SPHERE, 0, "cam00"), time=0.0)
    times = [frame / (SPEC.frames - 1) for frame in range(SPEC.frames)]
    for time_ in times:  # the slider moves forward one frame at a time
        before = len(rendered)
        camera = viewer_camera(loaded, time_)
        tracking.overlay(camera, torch.zeros(int(camera.height), int(camera.width), 3))
        assert len(rendered) - before == 1, f"time {time_}: {len(rendered) - before} renders"
    for time_ in reversed(times):  # and back: nothing new to render
        camera = viewer_camera(loaded, time_)
        tracking.overlay(camera, torch.zeros(int(camera.height), int(camera.width), 3))
    assert sorted(rendered) == times
    small = viewer_camera(loaded, times[1])
    large = viewer_camera(loaded, times[1], width=3 * int(small.width), height=3 * int(small.height))
    mask = highlighted({"tracked_mask": tracking.overlay(small, torch.zeros(int(small.height), int(small.width), 3)),
                        "rgb": torch.zeros(1)})  # fmt: skip
    larger = highlighted({"tracked_mask": tracking.overlay(large, torch.zeros(int(large.height), int(large.width), 3)),
                          "rgb": torch.zeros(1)})  # fmt: skip
    assert mask.any() and len(rendered) == len(times)
    assert np.array_equal(larger, mask.repeat(3, axis=0).repeat(3, axis=1))
    moved = viewer_camera(loaded, times[1], x_shift=0.01)
    tracking.overlay(moved, torch.zeros(int(moved.height), int(moved.width), 3))
    assert len(rendered) == len(times) + 2  # a new view: the click time and the slider's time
    tracking.forget()  # a training step
    tracking.overlay(moved, torch.zeros(int(moved.height), int(moved.width), 3))
    assert len(rendered) == len(times) + 4
    tracking.selection = None


# --- the real viewer in a real browser --------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_for(condition, timeout: float, what: str, interval: float = 0.5, last: Optional[dict] = None):
    """Poll `condition` until it returns something truthy; fail after `timeout` seconds (with what the condition
    last saw, when it records that in `last`)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if isinstance(value, np.ndarray) or value:
            return value
        time.sleep(interval)
    pytest.fail(f"timed out after {timeout:.0f} s waiting for {what}" + (f"; last seen: {last}" if last else ""))


@pytest.fixture()
def viewer(trained, tmp_path):
    """`ns-viewer` on the trained run, on a free local port; stopped at teardown."""
    port = free_port()
    log = open(tmp_path / "viewer.log", "w")
    process = subprocess.Popen(
        [
            str(BIN / "ns-viewer"), "--load-config", str(trained[2]), "--viewer.websocket-port", str(port),
            "--viewer.websocket-host", "127.0.0.1",
        ],
        stdout=log, stderr=subprocess.STDOUT, cwd=trained[0], env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )

    def listening() -> bool:
        assert process.poll() is None, (tmp_path / "viewer.log").read_text()[-3000:]
        with socket.socket() as sock:
            return sock.connect_ex(("127.0.0.1", port)) == 0

    try:
        wait_for(listening, 180, "ns-viewer to listen")
        yield f"http://127.0.0.1:{port}"
    finally:
        process.terminate()
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=20)
        log.close()


@pytest.fixture()
def browser(tmp_path):
    """Headless Chromium under chromedriver (Debian packages); quit at teardown."""
    if CHROMIUM is None or CHROMEDRIVER is None:
        pytest.skip("needs the Debian packages chromium and chromium-driver (scripts/test.sh installs them)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={tempfile.mkdtemp(dir=tmp_path)}"):
        options.add_argument(flag)
    service = Service(CHROMEDRIVER)
    driver = webdriver.Chrome(service=service, options=options)
    try:
        driver.set_page_load_timeout(60)
        driver.set_script_timeout(30)
        yield driver
    finally:
        driver.quit()
        service.stop()


def block_means(shot: np.ndarray, box, size: int = 32) -> np.ndarray:
    """Mean colour of each size x size block of a screenshot's box: blind to the render's resolution."""
    x0, y0, x1, y1 = box
    view = shot[y0 : y0 + (y1 - y0) // size * size, x0 : x0 + (x1 - x0) // size * size]
    return view.reshape(view.shape[0] // size, size, view.shape[1] // size, size, 3).mean(axis=(1, 3))


def screenshot(driver) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(driver.get_screenshot_as_png())).convert("RGB")).astype(np.float32)


def by_label(driver, label: str, what: str):
    """The first element matching XPath step `what` after the GUI label with this text."""
    from selenium.webdriver.common.by import By

    return driver.find_element(By.XPATH, f"//label[normalize-space()='{label}']/following::{what}[1]")


def press(driver, element, key: str) -> None:
    """Focus a GUI element and press a key, as a keyboard user does (sliders: Home, End, arrows)."""
    from selenium.webdriver.common.action_chains import ActionChains

    driver.execute_script("arguments[0].focus();", element)
    ActionChains(driver).send_keys(key).perform()


SETTLED = 2 * STILL_SECONDS + 1.5
"""Seconds between two equal screenshots of a settled view: the viewer shows its frame at the moving resolution
until the still view ('Max res', about STILL_SECONDS to render, more under load, plus the tracked mask) replaces it."""


CHANGED_LEVELS, CHANGED_PIXELS = 16.0, 200
"""A view differs from another where at least CHANGED_PIXELS of its pixels changed by more than CHANGED_LEVELS grey
levels in a channel: a highlighted object of 1 % of the view changes far fewer than 1 grey level on average."""


def changed_pixels(shot: np.ndarray, other: np.ndarray, box) -> int:
    x0, y0, x1, y1 = box
    return int((np.abs(shot[y0:y1, x0:x1] - other[y0:y1, x0:x1]).max(axis=-1) > CHANGED_LEVELS).sum())


def settled_view(driver, box, timeout: float, differs_from=None) -> np.ndarray:
    """A screenshot whose scene area is no longer blank, differs from `differs_from` (when given) and is
    the same in two screenshots ``SETTLED`` s apart (fewer than CHANGED_PIXELS changed), i.e. the viewer has sent
    its final render."""
    x0, y0, x1, y1 = box
    previous, seen = [None], {}

    def ready():
        shot = screenshot(driver)
        seen["spread"] = shot[y0:y1, x0:x1].std()
        seen["changed since the last"] = None if previous[0] is None else changed_pixels(shot, previous[0], box)
        seen["changed from the given"] = None if differs_from is None else changed_pixels(shot, differs_from, box)
        previous[0] = shot
        if seen["spread"] < 5.0:  # blank canvas
            return None
        if differs_from is not None and seen["changed from the given"] < CHANGED_PIXELS:
            return None
        still = seen["changed since the last"] is not None and seen["changed since the last"] < CHANGED_PIXELS
        return shot if still else None

    return wait_for(ready, timeout, "a rendered frame", interval=SETTLED, last=seen)


def test_moving_frames_render_in_half_a_second_at_most():
    """While the camera moves, nerfstudio renders frames of (pixels per second / rate) pixels: 6,000 where the measured
    speed allows, smaller on a slower machine so that a frame takes at most half a second; never above its 30 frames
    per second."""
    assert moving_rate(60_000) == pytest.approx(10.0)
    assert moving_rate(4_703) == 2.0
    assert moving_rate(10_000_000) == 30.0
    for speed in (300, 4_703, 11_999, 12_001, 60_000, 10_000_000):
        assert 1 / moving_rate(speed) <= 0.5


def test_viewer_in_a_browser_renders_scrubs_time_and_tracks_a_click(trained, browser, viewer, tmp_path):
    """At the viewer's defaults (its resolutions chosen from the measured render speed, `viewer_speed`): the first
    view shows the scene, the time slider shows the motion, a click selects the object under it, and a moved
    camera is redrawn."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys

    _, scene, _ = trained
    driver = browser
    driver.get(viewer)
    wait_for(lambda: driver.find_elements(By.XPATH, "//*[normalize-space()='Connected']"), 60, "the websocket")
    wait_for(lambda: driver.find_elements(By.XPATH, "//button[normalize-space()='Hide Train Cams']"), 30, "the GUI")
    pattern = r"([\d,]+) pixels per second measured: 'Max res' (\d+) when still, ([\d.]+) frames per"
    # the viewer measures its render speed after it has installed the GUI
    chosen = wait_for(lambda: re.search(pattern, (tmp_path / "viewer.log").read_text()), 60, "the measured speed")
    speed, max_res, rate = float(chosen.group(1).replace(",", "")), int(chosen.group(2)), float(chosen.group(3))
    assert max_res == still_resolution(speed) and rate == round(moving_rate(speed), 1), chosen.group(0)
    assert by_label(driver, "Max res", "input").get_attribute("value") == str(max_res)  # not nerfstudio's 512
    # The rate follows the speed measured under this machine's load (the browser's software WebGL shares the CPU):
    # printed, not asserted, as speed is measured by the benchmark (python -m benchmarks render-speed).
    print(f"measured {speed:,.0f} pixels per second: 'Max res' {max_res}, {rate} frames per second while moving")

    # The 3D view's canvas: the narrowest large one (the GUI panel sits beside it).
    canvas_element = min(
        (c for c in driver.find_elements(By.TAG_NAME, "canvas") if c.rect["width"] > 100), key=lambda c: c.rect["width"]
    )
    canvas = canvas_element.rect
    left, top, width, height = (int(round(canvas[k])) for k in ("x", "y", "width", "height"))
    box = (left + 4, top + 4, left + width - 4, top + height - 4)
    first = settled_view(driver, box, 120)
    Image.fromarray(first.astype(np.uint8)).save(tmp_path / "time_0.png")

    # The first view shows the scene: the viewer opens at the held-out camera, so no training camera's
    # frustum (drawn with its image) covers the render, and hiding them changes the view by little (at the
    # first training camera its frustum covers the middle: 13 grey levels on 32-px block means).
    # Under load the still render can come after a screenshot settled on the moving frame: then the two views are
    # taken again, frusta shown and hidden, until they hold the same render (three tries).
    for _ in range(3):
        driver.find_element(By.XPATH, "//button[normalize-space()='Hide Train Cams']").click()
        hidden = settled_view(driver, box, 60)
        covered = np.abs(block_means(hidden, box) - block_means(first, box)).mean()
        if covered < 4.0:
            break
        driver.find_element(By.XPATH, "//button[normalize-space()='Show Train Cams']").click()
        first = settled_view(driver, box, 60)
    assert covered < 4.0, f"the training cameras' frusta cover the first view ({covered:.1f} grey levels)"

    press(driver, by_label(driver, "Time", "*[@role='slider']"), Keys.END)  # time 1.0, the last frame
    last = settled_view(driver, box, 120, differs_from=hidden)
    Image.fromarray(last.astype(np.uint8)).save(tmp_path / "time_1.png")

    # Where the fast sphere moves (ground truth at the viewer's camera, the held-out cam00) the screenshots
    # differ more than on the static background.
    truth = [ground_truth_view(scene, "cam00", f, width, height, VIEWER_FOV).object_ids for f in (0, SPEC.frames - 1)]
    region = np.zeros((first.shape[0], first.shape[1]), dtype=bool)
    x0, y0, x1, y1 = box
    region[y0:y1, x0:x1] = True
    moving = np.zeros_like(region)
    moving[top : top + height, left : left + width] = (truth[0] == FAST_SPHERE) | (truth[1] == FAST_SPHERE)
    still = np.zeros_like(region)
    still[top : top + height, left : left + width] = (truth[0] == truth[1]) & (truth[0] != FAST_SPHERE)
    still &= ~ndimage.binary_dilation(moving, iterations=25)
    change = np.abs(last - hidden).mean(axis=-1)
    moving_change, still_change = change[moving & region].mean(), change[still & region].mean()
    assert moving_change > 2.0 * still_change, (moving_change, still_change)

    # "Select object", then a click on the static sphere, while the viewer renders at its 'Max res': the
    # click's ray reaches the model's tracking (Sec 4.5), which selects the sphere: its mask in the clicked
    # view covers about as much of the view as the sphere does.
    status = by_label(driver, "Tracked", "input")
    driver.find_element(By.XPATH, "//button[normalize-space()='Select object (then click it)']").click()
    wait_for(lambda: "click the object" in (status.get_attribute("value") or ""), 10, "the button to arm a click")
    rows, cols = np.nonzero(truth[1] == STATIC_SPHERE)
    x, y = float(cols.mean()), float(rows.mean())
    offset = int(x - width / 2), int(y - height / 2)
    ActionChains(driver).move_to_element_with_offset(canvas_element, *offset).click().perform()
    clicked = time.monotonic()
    wait_for(lambda: re.match(r"point \(|nothing selected", status.get_attribute("value") or ""), 60, "a selection")
    value = status.get_attribute("value")
    print(f"click to selection: {time.monotonic() - clicked:.1f} s: {value}")
    share = re.search(r"its mask ([0-9.]+)% of the view", value)
    assert share is not None, f"the click selected nothing: {value}"
    truth_share = float(np.mean(truth[1] == STATIC_SPHERE))
    assert 0.3 * truth_share < float(share.group(1)) / 100 < 3.0 * truth_share, (value, truth_share)

    # The output 'tracked_mask' highlights the selected object: the pixels turned greener cover the sphere, and
    # they are as much of the view as the selection's mask (the status line's share; at the clicked time the viewer's
    # render decodes the clicked view's own features, `viewer.sam_view`, and the low-resolution render spreads the
    # mask by a render pixel or so). How well the built-in stand-in segments this blurry 400-iteration render
    # varies with the view (1 % to 4 % of it for a click on the sphere): the tracking benchmarks measure that
    # (tracking_real.md for the viewer's views), not this test.
    before = settled_view(driver, box, 60)
    by_label(driver, "Output type", "input").click()
    option = f"//*[@role='option' and normalize-space()='{OUTPUT}']"
    wait_for(lambda: driver.find_elements(By.XPATH, option), 30, f"the output {OUTPUT} in the list")
    driver.find_element(By.XPATH, option).click()
    # Under load the still render can take longer than ``SETTLED``, so a settled view may still be the frame at the
    # moving resolution, whose blocks spread the mask over several times its area: the highlight is read again from
    # new screenshots until the still render has replaced it (or the wait fails with the last reading).
    sphere, seen = truth[1] == STATIC_SPHERE, {}

    def highlight(shot: np.ndarray) -> Optional[np.ndarray]:
        green = (shot - before)[top : top + height, left : left + width] @ np.array([-0.5, 1.0, -0.5])
        greener = green > 20.0
        seen["on the sphere"] = float((greener & sphere).sum() / sphere.sum())
        seen["x the selection's mask"] = float(greener.mean()) / (float(share.group(1)) / 100)
        return shot if seen["on the sphere"] > 0.5 and 0.5 < seen["x the selection's mask"] < 2.0 else None

    shown = settled_view(driver, box, 60, differs_from=before)
    if highlight(shown) is None:
        shown = wait_for(lambda: highlight(screenshot(driver)), 60, f"the highlight of the selection ({value})", last=seen)
    Image.fromarray(shown.astype(np.uint8)).save(tmp_path / "tracked_mask.png")

    # A moved camera is redrawn: back to the output "rgb", a drag turns the view, and the screenshot changes when the
    # viewer's render from the new view arrives (the training cameras' frusta are hidden, so nothing else on the page
    # moves with it). The time is printed, not asserted: the rate above is what sets it.
    by_label(driver, "Output type", "input").click()
    driver.find_element(By.XPATH, "//*[@role='option' and normalize-space()='rgb']").click()
    before = settled_view(driver, box, 60, differs_from=shown)
    ActionChains(driver).move_to_element(canvas_element).click_and_hold().move_by_offset(60, 0).release().perform()
    moved = time.monotonic()
    def redrawn_view():
        shot = screenshot(driver)
        return shot if np.abs(block_means(shot, box) - block_means(before, box)).mean() > 1.0 else None

    redrawn = wait_for(redrawn_view, 30, "the moved camera's render", interval=0.05)
    print(f"moved camera redrawn {time.monotonic() - moved:.2f} s after the drag")
    Image.fromarray(redrawn.astype(np.uint8)).save(tmp_path / "moved.png")
