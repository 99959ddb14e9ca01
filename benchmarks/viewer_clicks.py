"""The viewer's click decode (Sec 4.5, `tracking/viewer.py`) on trained runs: one click per object in a view as the
viewer renders it (viser's 75-degree vertical field of view, aspect 1.5, 64 pixels on the longer side as a click
decodes, at the held-out camera's pose), decoded by the built-in SAM stand-in on the SAM features alone and with
the depth cue (what the viewer and `ns-gear-track` do), over all space (the default) and where 2 training cameras see
(`min_views`). IoU against the truth in that view:
- a real capture (`--masks`): the held-out camera's person components (`tracking_real.people`) mapped into the
  wider view and scored inside the held-out camera's frame (outside it nothing is known);
- a synthetic scene (`--scene`): the scene rendered at the view (`SyntheticScene`), every object.
The click is the truth's pixel deepest inside the object.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/viewer_clicks.py outputs/t30_s{42,1,2}/runs/tracking/gear-nerf-small/run/config.yml \
        --masks ../shared/data/real/panoptic_basketball_masks --camera 00 --frames 0 5 10 15 19 --picture viewer_clicks.png

Prints a markdown table (mean IoU over the clicks of each run, and over all runs) and, with `--picture`, writes the
first run's view at the first frame with each decoding's masks.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
from pathlib import Path
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch
import tyro
from PIL import Image

FOV = math.radians(75.0)
"""Vertical field of view of viser's browser camera, which the viewer renders with."""
WIDTH, HEIGHT = 64, 43
"""The viewer's click view: 64 pixels on the longer side (`ViewerTracking._on_click`), aspect 1.5."""
DECODINGS = (("all", False), ("all", True), ("seen", False), ("seen", True))
"""(space, depth cue): all space or seen by 2 training cameras; the features alone or with the cue."""


@dataclasses.dataclass
class ViewerClicks:
    configs: tyro.conf.Positional[List[Path]]
    """config.yml of trained runs (one per seed)."""
    masks: Optional[Path] = None
    """A real capture's mask folder (`<camera>/<frame>.png`)."""
    camera: str = "00"
    """The held-out camera whose masks are the truth (real capture)."""
    downscale: int = 1
    """The runs' image downscale (the masks are at full size)."""
    scene: Optional[Path] = None
    """A synthetic scene's folder (with ground_truth/scene.json); default: `scene` beside the run's `runs` folder."""
    frames: List[int] = dataclasses.field(default_factory=lambda: [0, 5, 10, 15, 19])
    """Frame indices; frames past a run's last are skipped."""
    picture: Optional[Path] = None
    """Where to write the overlay picture."""

    def main(self) -> None:
        from nerfstudio.utils.eval_utils import eval_setup

        from gear_nerfstudio.tracking.cli import dataset_cameras
        from gear_nerfstudio.tracking.click import single_camera

        torch.set_num_threads(1)
        rows: Dict[Tuple[str, bool], List[float]] = {}
        print("| run | clicks | " + " | ".join(label(d) for d in DECODINGS) + " |\n|---|---|" + "---|" * len(DECODINGS))
        for index, config in enumerate(self.configs):
            _, pipeline, _, _ = eval_setup(config, test_mode="test")
            model = pipeline.model
            model.config.min_views = 2
            model.see_from(pipeline.datamanager.train_dataparser_outputs.cameras)
            cameras, held_out = dataset_cameras(pipeline)
            name = self.camera if self.masks is not None else held_out[0]
            held = single_camera(cameras[name])
            scores: Dict[Tuple[str, bool], List[float]] = {}
            for frame in [f for f in self.frames if f < model.num_frames]:
                picture = self.picture if index == 0 and frame == self.frames[0] else None
                for key, value in self.frame_scores(pipeline, config, held, name, frame, picture).items():
                    scores.setdefault(key, []).extend(value)
            for key, value in scores.items():
                rows.setdefault(key, []).append(float(np.mean(value)))
            count = len(scores[DECODINGS[0]])
            print(f"| {config.parents[4].name} | {count} | " + " | ".join(f"{np.mean(scores[d]):.1f}" for d in DECODINGS) + " |")
        means = [f"{np.mean(rows[d]):.1f} ± {np.std(rows[d], ddof=1) if len(rows[d]) > 1 else 0.0:.1f}" for d in DECODINGS]
        print("| mean ± sd over runs | | " + " | ".join(means) + " |")

    def frame_scores(
        self, pipeline, config: Path, held, name: str, frame: int, picture: Optional[Path]
    ) -> Dict[Tuple[str, bool], List[float]]:
        """IoU of each decoding for one click per object of the view at a frame, at the pose of camera `held`."""
        from nerfstudio.cameras.cameras import CameraType
        from nerfstudio.viewer.utils import CameraState, get_camera

        from gear_nerfstudio.sam.interface import Embedding
        from gear_nerfstudio.tracking.metrics import iou
        from gear_nerfstudio.tracking.propagation import render_embedding, render_rgb, segment
        from tracking_real import deepest_pixel

        model, backend = pipeline.model, pipeline.sam_backend
        time = frame / max(model.num_frames - 1, 1)
        state = CameraState(fov=FOV, aspect=WIDTH / HEIGHT, c2w=held.camera_to_worlds[0], camera_type=CameraType.PERSPECTIVE, time=time)
        view = get_camera(state, HEIGHT, WIDTH)
        truths, known = self.truths(config, held, view, name, frame)
        embeddings = {}
        for space in ("all", "seen"):
            with model.all_space() if space == "all" else contextlib.nullcontext():
                embeddings[space] = render_embedding(model, view, time, backend)
        scores: Dict[Tuple[str, bool], List[float]] = {}
        shown = []
        for truth in truths:
            x, y = deepest_pixel(truth)
            for space, cue in DECODINGS:
                embedding = embeddings[space]
                if not cue:
                    embedding = Embedding(embedding.features, embedding.image_size)
                mask = segment(backend, embedding, np.array([[x, y]]), np.array([1]))
                scores.setdefault((space, cue), []).append(100.0 * iou(mask & known, truth))
                shown.append((space, cue, mask, (x, y)))
        if picture is not None and shown:
            with model.all_space():
                rgb = render_rgb(model, get_camera(state, 3 * HEIGHT, 3 * WIDTH), time)
            write_picture(picture, rgb, shown)
        return scores

    def truths(self, config: Path, held, view, name: str, frame: int) -> Tuple[List[np.ndarray], np.ndarray]:
        """The objects' masks in `view`, and where the truth is known."""
        if self.masks is not None:
            from gear_nerfstudio.tracking.click import single_camera
            from gear_nerfstudio.tracking.projection import project
            from tracking_real import people, shrink

            ys, xs = torch.meshgrid(torch.arange(HEIGHT) + 0.5, torch.arange(WIDTH) + 0.5, indexing="ij")
            rays = single_camera(view).generate_rays(camera_indices=0, coords=torch.stack([ys, xs], -1))
            pixels, in_front = project(held, (rays.origins + rays.directions).reshape(-1, 3))
            u, v = (pixels[0, :, i].reshape(HEIGHT, WIDTH).numpy() for i in (0, 1))
            height, width = int(held.height), int(held.width)
            known = in_front[0].reshape(HEIGHT, WIDTH).numpy() & (u >= 0) & (u < width) & (v >= 0) & (v < height)
            columns, rows = np.clip(u.astype(int), 0, width - 1), np.clip(v.astype(int), 0, height - 1)
            truths = [shrink(m, self.downscale)[rows, columns] & known for m in people(self.masks, name, frame)[:2]]
            return [t for t in truths if t.sum() >= 4], known
        from gear_nerfstudio.tools.synthetic.scene import RigCamera, SyntheticScene

        scene = self.scene or config.parents[4] / "scene"
        description = json.loads((scene / "ground_truth" / "scene.json").read_text())
        rig = next(c for c in description["cameras"] if c["name"] == name)
        focal = HEIGHT / 2 / math.tan(FOV / 2)
        camera = RigCamera(
            name="viewer", rotation=np.array(rig["rotation_world_to_camera_opencv"]), centre=np.array(rig["centre"]),
            fx=focal, fy=focal, cx=WIDTH / 2, cy=HEIGHT / 2, width=WIDTH, height=HEIGHT,
        )  # fmt: skip
        ids = SyntheticScene(motion=description.get("motion", "mixed"), supersample=1).render(camera, frame).object_ids
        truths = [ids == i for i in np.unique(ids) if i != 0 and (ids == i).sum() >= 4]
        return truths, np.ones((HEIGHT, WIDTH), dtype=bool)


def label(decoding: Tuple[str, bool]) -> str:
    space, cue = decoding
    return f"{'all space' if space == 'all' else 'seen by 2'}, {'with the cue' if cue else 'features alone'}"


def write_picture(path: Path, rgb: np.ndarray, shown) -> None:
    """One tile per decoding: the view with every click's mask and the click, drawn as `ns-gear-track` draws them
    (`tracking.cli.overlay`)."""
    from gear_nerfstudio.tracking.cli import overlay

    scale = rgb.shape[1] / WIDTH
    tiles = []
    for decoding in DECODINGS:
        tile = rgb
        for space, cue, mask, (x, y) in shown:
            if (space, cue) == decoding:
                big = np.array(Image.fromarray(mask).resize((rgb.shape[1], rgb.shape[0]), Image.NEAREST))
                tile = overlay(tile, big, {"points": [(scale * x, scale * y)], "labels": [1]})
        tiles.append(tile)
    Image.fromarray(np.concatenate(tiles, axis=1)).save(path)
    print(f"wrote {path} (tiles: " + "; ".join(label(d) for d in DECODINGS) + ")")


if __name__ == "__main__":
    tyro.cli(ViewerClicks).main()
