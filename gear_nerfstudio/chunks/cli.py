"""`ns-gear-chunks`: train, render and evaluate a long video as chunks of --chunk-frames frames.

    ns-gear-chunks train --output-dir outputs/flame_salmon --chunk-frames 100 -- \\
        gear-nerf neural-3d-video-data --data n3d/flame_salmon_1 --downscale-factor 2
    ns-gear-chunks render --output-dir outputs/flame_salmon --output-path renders/flame_salmon.mp4
    ns-gear-chunks eval --output-dir outputs/flame_salmon

Everything after ``--`` is an `ns-train` command line for the whole video (its frame window is the
dataparser's ``--frame-start``/``--frame-count``, default: every frame). Running `train` again resumes: chunks
that finished are skipped, a stopped chunk continues from its latest checkpoint.
"""

from __future__ import annotations

import json
import sys
import tempfile
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Tuple, Union

import tyro
from nerfstudio.cameras.camera_paths import get_path_from_json
from typing_extensions import Annotated

from gear_nerfstudio.chunks.executors import Executor, execute
from gear_nerfstudio.chunks.plan import ChunkError
from gear_nerfstudio.chunks.training import plan_runs, read_manifest
from gear_nerfstudio.chunks.video import blended_frames, evaluate, write_json, write_png
from gear_nerfstudio.tools.camera_path import TimeSweep, path_json, rig_cameras
from gear_nerfstudio.tools.commands import run_command


@dataclass
class ChunksCommand(ABC):
    output_dir: Path
    """Folder of the chunks (chunks.json and one run folder per chunk)."""

    @abstractmethod
    def main(self) -> None:
        """Run the command."""


@dataclass
class Train(ChunksCommand):
    """Train every chunk (or finish the ones a stopped run left)."""

    chunk_frames: int = 100
    """Frames per chunk (the paper trains every 100 frames as a model of its own)."""
    overlap: int = 0
    """Frames shared by consecutive chunks; renders blend across them (less than half a chunk)."""
    executor: Executor = "local"
    """'local': chunks one after another on this machine; 'ray': Ray tasks (one GPU each where there are GPUs)."""
    ray_address: Optional[str] = None
    """Ray cluster to join ('auto', 'host:port'); default: start Ray on this machine."""
    train_args: tyro.conf.Suppress[Tuple[str, ...]] = ()

    def main(self) -> None:
        if not self.train_args:
            raise ChunkError("give the ns-train command line of the whole video after '--'")
        plan = plan_runs(self.train_args, self.output_dir, self.chunk_frames, self.overlap)
        configs = execute(plan, self.executor, self.ray_address)
        print(f"[chunks] {len(configs)} chunks trained in {self.output_dir}")


@dataclass
class Render(ChunksCommand):
    """Render a camera path whose render_time runs over the whole video (default: the held-out camera, one frame
    per video frame); each time is rendered by the chunk that owns it, blended where chunks overlap."""

    output_path: Path = Path("renders/chunks.mp4")
    """An .mp4 video, or a folder of PNG frames."""
    camera_path_filename: Optional[Path] = None
    """nerfstudio camera-path JSON (ns-gear-path writes them; times are times of the whole video)."""
    fps: float = 30.0
    """Frame rate of the default path's video."""

    def main(self) -> None:
        manifest = read_manifest(self.output_dir)
        configs = manifest["configs"]
        num_frames = len(manifest["frame_numbers"])
        if self.camera_path_filename is None:
            cameras, held_out, _ = rig_cameras(Path(configs[0]))
            first, poses = TimeSweep(load_config=Path(configs[0])).poses(cameras, held_out, num_frames)
            path = path_json(first, poses, [k / max(num_frames - 1, 1) for k in range(len(poses))], self.fps)
        else:
            path = json.loads(self.camera_path_filename.read_text())
        cameras = get_path_from_json(path)
        if cameras.times is None:
            raise ChunkError(f"{self.camera_path_filename}: the camera path has no render_time (ns-gear-path writes them)")
        video = self.output_path.suffix.lower() == ".mp4"
        with tempfile.TemporaryDirectory() as scratch:
            frames_dir = Path(scratch) if video else self.output_path
            frames_dir.mkdir(parents=True, exist_ok=True)
            for index, rgb in blended_frames(configs, manifest["plan"], num_frames, cameras):
                write_png(rgb, frames_dir / f"{index:05d}.png")
            if video:
                self.output_path.parent.mkdir(parents=True, exist_ok=True)
                run_command(
                    [
                        "ffmpeg", "-y", "-loglevel", "error", "-framerate", str(path["fps"]),
                        "-i", str(frames_dir / "%05d.png"), "-pix_fmt", "yuv420p", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2",
                        str(self.output_path),
                    ],
                    "chunks",
                )
        print(f"[chunks] wrote {self.output_path} ({len(cameras)} frames)")


@dataclass
class Eval(ChunksCommand):
    """PSNR / SSIM (LPIPS when its weights are local) of the held-out camera over the whole video: overall, per
    chunk and per frame, in one JSON file."""

    output_path: Optional[Path] = None
    """Where the metrics go; default: <output-dir>/metrics.json."""

    def main(self) -> None:
        manifest = read_manifest(self.output_dir)
        configs = manifest["configs"]
        frames = manifest["frame_numbers"]
        metrics = evaluate(configs, manifest["plan"], len(frames), frames)
        path = self.output_path or self.output_dir / "metrics.json"
        write_json(metrics, path)
        shown = ", ".join(f"{k} {v:.4g}" for k, v in metrics["results"].items() if not k.endswith("_std"))
        print(f"[chunks] held-out camera over {len(frames)} frames: {shown}; written to {path}")


Commands = Union[
    Annotated[Train, tyro.conf.subcommand(name="train")],
    Annotated[Render, tyro.conf.subcommand(name="render")],
    Annotated[Eval, tyro.conf.subcommand(name="eval")],
]


def split_arguments(argv: List[str]) -> Tuple[List[str], Tuple[str, ...]]:
    """This command's arguments and the ns-train command line after ``--``."""
    if "--" not in argv:
        return argv, ()
    cut = argv.index("--")
    return argv[:cut], tuple(argv[cut + 1 :])


def entrypoint() -> None:
    """Console script; bad input is reported in one line (``gear_nerfstudio.errors``)."""
    own, train_args = split_arguments(sys.argv[1:])
    command = tyro.cli(Commands, args=own)
    if isinstance(command, Train):
        command.train_args = train_args
    command.main()
