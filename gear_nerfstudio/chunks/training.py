"""Training the chunks of a long video: one `ns-train` run per chunk, resumed chunk by chunk.

The whole-video config is the user's own `ns-train` command line. Chunk k is that config with the
dataparser's frame window narrowed to the chunk (``frame_start``, ``frame_count``) and its run folder set to
``<output-dir>/chunk_<k>/<method>/run``. Chunks share the frame and SAM caches: a frame is decoded and
encoded once, whichever chunk (or preparation task) comes first. ``chunks.json`` in the output folder records
the plan; a second `ns-gear-chunks train` with the same command skips the chunks whose last checkpoint is
the final step and resumes the others from their latest checkpoint.
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
import yaml

from gear_nerfstudio.chunks.plan import Chunk, ChunkError, plan_chunks
from gear_nerfstudio.sam.feature_cache import SamFeatureCache
from gear_nerfstudio.tools.commands import run_command

MANIFEST = "chunks.json"


def parse_train_args(train_args: Sequence[str]) -> Any:
    """The TrainerConfig of an `ns-train` command line (without ``ns-train``), with ``--data`` applied to the
    dataparser as ns-train does."""
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion

    from gear_nerfstudio.data_parsers.multiview import MultiViewVideoDataParserConfig

    config = tyro.cli(AnnotatedBaseConfigUnion, args=list(train_args))
    datamanager = config.pipeline.datamanager
    if config.data is not None:
        datamanager.data, config.data = config.data, None
    if not isinstance(datamanager.dataparser, MultiViewVideoDataParserConfig):
        raise ChunkError(
            "ns-gear-chunks cuts video into chunks with the multi-view video parsers: end the ns-train arguments "
            "with technicolor-data, neural-3d-video-data or google-immersive-data and its options"
        )
    if datamanager.data is not None:
        datamanager.dataparser.data = datamanager.data
    return config


def window_frames(config: Any) -> Tuple[List[int], int]:
    """Frame numbers of the whole video's window (the dataparser's ``--frame-start``/``--frame-count``) and the
    number of cameras of the rig."""
    parser = config.pipeline.datamanager.dataparser.setup()
    rig = parser.read_rig()
    return parser.window(rig), len(rig.names)


@dataclass
class ChunkRun:
    """What one worker needs to train one chunk; plain data, so that it travels to Ray workers."""

    base_config: str
    """YAML of the whole-video config."""
    chunk: Chunk
    frame_start: int
    """Dataset frame number of the chunk's first frame."""
    output_dir: str
    threads: int
    """Torch threads of the run (the same under every executor, so that results are the same)."""


def chunk_config(run: ChunkRun) -> Any:
    """The whole-video config narrowed to the chunk's frames, with the chunk's run folder."""
    config = copy.deepcopy(yaml.load(run.base_config, Loader=yaml.Loader))
    dataparser = config.pipeline.datamanager.dataparser
    dataparser.frame_start, dataparser.frame_count = run.frame_start, run.chunk.count
    config.output_dir = Path(run.output_dir)
    config.experiment_name = f"chunk_{run.chunk.index:03d}"
    config.timestamp = "run"
    return config


def latest_step(checkpoint_dir: Path) -> Optional[int]:
    """Step of the newest ``step-*.ckpt`` in a run's checkpoint folder, None if there is none."""
    steps = [int(path.stem.split("-")[1]) for path in checkpoint_dir.glob("step-*.ckpt")]
    return max(steps, default=None)


def train_chunk(run: ChunkRun) -> str:
    """Train one chunk with `ns-train`, or finish it from its latest checkpoint; returns its config.yml."""
    config = chunk_config(run)
    total = config.max_num_iterations
    checkpoints = config.get_checkpoint_dir()
    done = latest_step(checkpoints)
    if done is not None and done >= total - 1:
        print(f"[chunks] chunk {run.chunk.index} is trained ({checkpoints})", flush=True)
        return str(config.get_base_dir() / "config.yml")
    if done is not None:
        config.load_dir = checkpoints
        config.max_num_iterations = total - 1 - done
        print(f"[chunks] chunk {run.chunk.index}: resuming after step {done}", flush=True)
    launch = Path(run.output_dir) / config.experiment_name / "launch.yml"
    launch.parent.mkdir(parents=True, exist_ok=True)
    launch.write_text(yaml.dump(config), "utf8")
    command = ["ns-train", config.method_name, "--load-config", str(launch)]
    try:
        run_command(command, "chunks", env={"OMP_NUM_THREADS": str(run.threads)})
    except subprocess.CalledProcessError as err:
        raise ChunkError(
            f"{launch}: ns-train of chunk {run.chunk.index} stopped with exit status {err.returncode} (its output is above)"
        ) from err
    return str(config.get_base_dir() / "config.yml")


def prepare_camera(base_config: str, camera: int) -> None:
    """Decode one camera's frames of the whole window into the frame cache and encode them into the SAM cache
    (Sec 4.2; the datamanager encodes the held-out camera's images too), so that no chunk waits for it."""
    config = yaml.load(base_config, Loader=yaml.Loader)
    parser = config.pipeline.datamanager.dataparser.setup()
    rig = parser.read_rig()
    frames = parser.window(rig)
    files = [path for path in parser.frame_files(rig, [camera], frames, parser.image_sizes(rig, [camera]))[0] if path]
    if config.pipeline.datamanager.use_sam_features:
        SamFeatureCache(config.pipeline.sam.setup(), config.pipeline.datamanager.sam_cache_dir, files).precompute()


@dataclass
class ChunkPlan:
    """The runs of every chunk, and what the preparation tasks need."""

    runs: List[ChunkRun]
    base_config: str
    num_cameras: int
    num_devices: int
    """GPUs of one chunk's run (``--machine.num-devices``)."""


def plan_runs(train_args: Sequence[str], output_dir: Path, chunk_frames: int, overlap: int) -> ChunkPlan:
    """Parse the ns-train command, cut its window into chunks and write (or check) ``chunks.json``."""
    config = parse_train_args(train_args)
    frames, num_cameras = window_frames(config)
    chunks = plan_chunks(len(frames), chunk_frames, overlap)
    base_config = yaml.dump(config)
    runs = [
        ChunkRun(base_config, chunk, frames[chunk.first], str(output_dir.resolve()), torch_threads())
        for chunk in chunks
    ]
    settings = {"ns_train_args": list(train_args), "frame_numbers": frames, "chunk_frames": chunk_frames, "overlap": overlap}
    folders = [chunk_config(run).get_base_dir().relative_to(output_dir.resolve()) for run in runs]
    chunk_entries = [{**asdict(run.chunk), "frame_start": run.frame_start, "run": str(f)} for run, f in zip(runs, folders)]
    manifest = {**settings, "chunks": chunk_entries}
    path = output_dir / MANIFEST
    if path.exists():
        previous = json.loads(path.read_text())
        changed = [key for key in settings if previous.get(key) != settings[key]]
        if changed:
            raise ChunkError(
                f"{path}: this folder holds chunks of another command ({', '.join(changed)} differ); use another --output-dir"
            )
    output_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(manifest, indent=1))
    return ChunkPlan(runs, base_config, num_cameras, config.machine.num_devices)


def read_manifest(output_dir: Path) -> Dict[str, Any]:
    """``chunks.json`` of a trained chunked run, with its chunks as `Chunk`s (key ``plan``) and their config.yml
    paths (key ``configs``)."""
    path = output_dir / MANIFEST
    try:
        manifest = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise ChunkError(f"{path}: not the chunks.json of an ns-gear-chunks train run ({err})") from err
    manifest["plan"] = [Chunk(c["index"], c["first"], c["count"]) for c in manifest["chunks"]]
    manifest["configs"] = [str(output_dir / c["run"] / "config.yml") for c in manifest["chunks"]]
    for entry in manifest["chunks"]:
        if latest_step(output_dir / entry["run"] / "nerfstudio_models") is None:
            folder = output_dir / entry["run"]
            raise ChunkError(f"{folder}: chunk {entry['index']} has no checkpoint; run ns-gear-chunks train")
    return manifest


def torch_threads() -> int:
    """Threads of this process's torch (``OMP_NUM_THREADS`` when set)."""
    return int(os.environ.get("OMP_NUM_THREADS") or torch.get_num_threads())
