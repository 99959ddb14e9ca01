"""Size and fidelity of the SAM feature cache (targets S(r) of L_SAM, Eq 9): compressed files against float16.

1. Bytes per image: the files the cache writes for real frames with the built-in backend, the largest file
   any backend with C = 256 on the 64 x 64 grid can get (`MAX_COMPONENTS`), and the float16 files of the
   reference module; totals for a whole Technicolor, N3D and Immersive scene.
2. Reconstruction of the built-in backend's embeddings of real frames (panoptic_basketball, N3D flame_steak
   cam00 frame 0): relative RMS error and cosine similarity per grid cell, MSE in the units of L_SAM.
3. With ``--reference-module`` (the float16 module, e.g. ``git show <commit>:gear_nerfstudio/sam/feature_cache.py``):
   `features_at` time for a batch, and, unless ``--skip-training``, ``ns-train`` of a preset on the tracking
   benchmark's synthetic scene once per seed and cache module (same seed, same iterations), with final L_SAM
   and ``ns-gear-track`` mIoU / t-mIoU on the held-out camera.

    git show HEAD:gear_nerfstudio/sam/feature_cache.py > /tmp/feature_cache_float16.py
    .venv/bin/python benchmarks/sam_cache.py --reference-module /tmp/feature_cache_float16.py

Prints a markdown report and writes it to ``<output>/sam_cache.md``.
"""

from __future__ import annotations

import argparse
import hashlib
import importlib.util
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Dict, List, Sequence

import numpy as np
import torch
from PIL import Image

from environment import command_environment
from tracking import TrackingBenchmark
from gear_nerfstudio.method_configs.gear_nerf import schedule_options
from gear_nerfstudio.sam import feature_cache
from gear_nerfstudio.sam.builtin_backend import BuiltinSamBackend
from gear_nerfstudio.sam.interface import valid_grid
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene

REPO = Path(__file__).resolve().parent.parent
REAL = REPO.parent / "shared" / "data" / "real"
# (name, cameras, frames) of a whole training window; one camera of each is held out.
SCENES = (("Technicolor", 16, 50), ("N3D", 21, 300), ("Immersive", 46, 50))
RUNNER = (
    "import importlib.util, sys\n"
    "spec = importlib.util.spec_from_file_location('gear_nerfstudio.sam.feature_cache', sys.argv[1])\n"
    "module = importlib.util.module_from_spec(spec)\n"
    "sys.modules[spec.name] = module\n"
    "spec.loader.exec_module(module)\n"
    "target, function = sys.argv[2].split(':')\n"
    "sys.argv = sys.argv[2:]\n"
    "getattr(importlib.import_module(target), function)()\n"
)  # runs an entry point with the feature-cache module of a file
ENTRY_POINTS = {
    "ns-train": "nerfstudio.scripts.train:entrypoint",
    "ns-gear-track": "gear_nerfstudio.tracking.cli:entrypoint",
}


def load_module(path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(f"reference_cache_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def real_frames(frames_dir: Path) -> List[Path]:
    """The panoptic frames and frame 0 of N3D flame_steak cam00 (decoded to a PNG in `frames_dir`)."""
    import av

    frames = sorted((REAL / "panoptic_basketball").glob("*.png"))
    frames_dir.mkdir(parents=True, exist_ok=True)
    with av.open(str(REAL / "n3d_flame_steak_frame0" / "cam00.mp4")) as container:
        frame = next(container.decode(video=0)).to_ndarray(format="rgb24")
    frames.append(frames_dir / "flame_steak_cam00_frame0.png")
    Image.fromarray(frame).save(frames[-1])
    return frames


def mean_spread(values: Sequence[float], digits: int = 4) -> str:
    values = np.asarray(values, dtype=np.float64)
    spread = f" ± {values.std(ddof=1):.{digits}g}" if len(values) > 1 else ""
    return f"{values.mean():.{digits}g}{spread}"


def sizes(frames: List[Path], cache_dir: Path, reference: ModuleType) -> List[str]:
    backend = BuiltinSamBackend()
    current = feature_cache.SamFeatureCache(backend, cache_dir / "current", frames)
    old = reference.SamFeatureCache(backend, cache_dir / "reference", frames) if reference else None
    encode = compress = 0.0
    for frame in frames:
        started = time.process_time()
        embedding = backend.encode(np.array(Image.open(frame).convert("RGB")))
        encoded = time.process_time()
        feature_cache.compress(embedding.features)
        encode += (encoded - started) / len(frames)
        compress += (time.process_time() - encoded) / len(frames)
    current.precompute()
    new_bytes = np.array([current.path_for(p).stat().st_size for p in frames])
    components = [feature_cache.read_header(current.path_for(p))[0]["components"] for p in frames]
    header = int(np.mean([feature_cache.read_header(current.path_for(p))[1] for p in frames]))
    full_rank = header + (feature_cache.MAX_COMPONENTS + 1) * 256 * 4 + 64 * 64 * feature_cache.MAX_COMPONENTS * 2
    if old is not None:
        old.precompute()
        old_bytes = float(np.mean([old.path_for(p).stat().st_size for p in frames]))
    else:
        old_bytes = header + 64 * 64 * 256 * 2  # the float16 layout, with a header as long as the new one
    rows = [
        ("float16 (G, G, C), the reference format", old_bytes),
        (f"compressed, built-in backend on {len(frames)} real frames (k = {min(components)}..{max(components)})",
         float(new_bytes.mean())),
        (f"compressed, any backend with C = 256 (k = MAX_COMPONENTS = {feature_cache.MAX_COMPONENTS}, "
         "the largest file)",
         float(full_rank)),
    ]  # fmt: skip
    lines = [
        "## Bytes per image (64 x 64 grid, C = 256: the built-in and the onnx backend), header included",
        "",
        "| format | bytes / image | ratio to float16 | "
        + " | ".join(f"{n} {c}x{f}: all / training only" for n, c, f in SCENES) + " |",
        "|---|---|---|" + "---|" * len(SCENES),
    ]  # fmt: skip
    for name, per_image in rows:
        totals = [f"{c * f * per_image / 2**30:.2f} / {(c - 1) * f * per_image / 2**30:.2f} GiB" for _, c, f in SCENES]
        lines.append(f"| {name} | {per_image:,.0f} | {old_bytes / per_image:.1f}x | " + " | ".join(totals) + " |")
    lines += [
        "",
        f"Header {header} bytes. Per real frame (mean of {len(frames)}), CPU time: encoding with the built-in backend "
        f"{1000 * encode:.0f} ms, compressing (`compress`) {1000 * compress:.0f} ms.",
    ]
    return lines


def reconstruction(frames: List[Path], cache_dir: Path) -> List[str]:
    backend = BuiltinSamBackend()
    cache = feature_cache.SamFeatureCache(backend, cache_dir / "current", frames)
    groups: Dict[str, Dict[str, List[float]]] = {}
    for frame in frames:
        original = backend.encode(np.array(Image.open(frame).convert("RGB")))
        decoded = cache.embedding(frame)
        rows, cols = valid_grid(original.image_size, original.grid_size)
        before = original.features[:, :rows, :cols].reshape(original.features.shape[0], -1).astype(np.float64)
        after = decoded.features[:, :rows, :cols].reshape(before.shape[0], -1).astype(np.float64)
        norms = np.linalg.norm(before, axis=0)
        cosine = (after * before).sum(axis=0) / (np.linalg.norm(after, axis=0) * norms)
        group = groups.setdefault(f"{frame.parent.name if frame.parent.parent == REAL else frame.stem} "
                                  f"({original.image_size[1]}x{original.image_size[0]})", {})  # fmt: skip
        for key, value in (
            ("k", feature_cache.read_header(cache.path_for(frame))[0]["components"]),
            ("error", np.linalg.norm(after - before) / np.linalg.norm(before)),
            ("cell", (np.linalg.norm(after - before, axis=0) / norms).max()),
            ("cosine", cosine.mean()),
            ("cosine_min", cosine.min()),
            ("mse", np.mean((after - before) ** 2)),
            ("energy", np.mean(before**2)),
        ):
            group.setdefault(key, []).append(float(value))
    lines = [
        "## Reconstruction of the built-in backend's embeddings of real frames (grid cells covering the image)",
        "",
        "| frames | n | k | relative RMS error: mean (max) | worst cell's relative error | cosine per cell: mean (min) "
        "| MSE, L_SAM's units: mean (max) | mean S^2 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, g in groups.items():
        lines.append(
            f"| {name} | {len(g['k'])} | {int(min(g['k']))}..{int(max(g['k']))} | {100 * np.mean(g['error']):.2f} % "
            f"({100 * np.max(g['error']):.2f} %) | {100 * np.max(g['cell']):.2f} % | {np.mean(g['cosine']):.6f} "
            f"({np.min(g['cosine_min']):.6f}) | {np.mean(g['mse']):.2e} ({np.max(g['mse']):.2e}) "
            f"| {np.mean(g['energy']):.2e} |"
        )
    return lines


def decoder_agreement(frames: List[Path], cache_dir: Path, reference: ModuleType, clicks: int) -> List[str]:
    """IoU of the decoder's best mask on each format's cached embedding with its mask on the encoder's own float32
    output, for one positive click at each point of a `clicks` x `clicks` grid (upshift masks, tracking)."""
    backend = BuiltinSamBackend()
    formats = (("float16 (reference)", reference, "reference"), ("compressed", feature_cache, "current"))
    ious: Dict[str, List[float]] = {name: [] for name, _, _ in formats}
    for frame in frames:
        original = backend.encode(np.array(Image.open(frame).convert("RGB")))
        height, width = original.image_size
        clicked = [np.array([[x, y]]) for y in (np.arange(clicks) + 0.5) * height / clicks
                   for x in (np.arange(clicks) + 0.5) * width / clicks]  # fmt: skip
        truth = [backend.decode(original, points=point)[0][0] for point in clicked]
        for name, module, folder in formats:
            embedding = module.SamFeatureCache(backend, cache_dir / folder, frames).embedding(frame)
            for point, expected in zip(clicked, truth):
                mask = backend.decode(embedding, points=point)[0][0]
                ious[name].append(np.logical_and(mask, expected).sum() / max(np.logical_or(mask, expected).sum(), 1))
    lines = [
        f"## SAM decoder masks (built-in decoder) on the cached embeddings against those on the encoder's float32 "
        f"output, {len(frames)} real frames x {clicks * clicks} clicks",
        "",
        "| cache format | masks | IoU: mean | min | identical masks |",
        "|---|---|---|---|---|",
    ]
    for name, values in ious.items():
        v = np.array(values)
        identical = 100 * np.mean(v == 1)
        lines.append(f"| {name} | {len(v)} | {100 * v.mean():.2f} % | {100 * v.min():.2f} % | {identical:.1f} % |")
    return lines


def lookup_time(frames: List[Path], cache_dir: Path, reference: ModuleType, rays: int, repeats: int) -> List[str]:
    """Wall time of `features_at` for a batch of `rays` rays spread over `frames` (warm files)."""
    backend = BuiltinSamBackend()
    generator = torch.Generator().manual_seed(0)
    indices = torch.randint(len(frames), (rays,), generator=generator)
    pixels = torch.rand(rays, 2, generator=generator) * torch.tensor([180.0, 180.0])
    threads = torch.get_num_threads()
    lines = [f"## `features_at`, {rays} rays over {len(frames)} images, CPU, median of {repeats}", "",
             f"| format | ms / batch, {threads} torch threads | ms / batch, 1 torch thread |",
             "|---|---|---|"]  # fmt: skip
    formats = (("float16 (reference)", reference, "reference"), ("compressed", feature_cache, "current"))
    for name, module, folder in formats:
        cache = module.SamFeatureCache(backend, cache_dir / folder, frames)
        cells = []
        for count in (threads, 1):
            torch.set_num_threads(count)
            cache.features_at(indices, pixels)
            times = []
            for _ in range(repeats):
                started = time.perf_counter()
                cache.features_at(indices, pixels)
                times.append(time.perf_counter() - started)
            cells.append(f"{1000 * np.median(times):.1f}")
        torch.set_num_threads(threads)
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def code_hash() -> str:
    """Hash of the project's Python files other than the feature cache (other work may change them meanwhile)."""
    digest = hashlib.sha1()
    paths = [*REPO.glob("gear_nerfstudio/**/*.py"), *REPO.glob("method_configs/*.py"), *REPO.glob("data_parsers/*.py")]
    for path in sorted(paths):
        if path.name != "feature_cache.py":
            digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


def run(module: Path, command: str, *args: str, log: Path, check: bool = True) -> bool:
    """Runs `command` with the feature-cache module of file `module`; whether it succeeded."""
    with open(log, "w") as handle:
        result = subprocess.run(
            [sys.executable, "-c", RUNNER, str(module), ENTRY_POINTS[command], *args], check=check,
            env={**command_environment(), "PYTHONUNBUFFERED": "1"}, stdout=handle, stderr=subprocess.STDOUT,
        )  # fmt: skip
    return result.returncode == 0


def training(args: argparse.Namespace) -> List[str]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    scene = args.output / "scene"
    spec = SyntheticSpec(dataset="n3d", width=64, height=48, frames=6, cameras=8, motion="mixed")
    write_synthetic_scene(scene, spec)
    clicker = TrackingBenchmark(output=args.output, frames=spec.frames)
    modules = {"float16 (reference)": args.reference_module.resolve(), "compressed": Path(feature_cache.__file__)}
    results: Dict[str, List[Dict[str, float]]] = {name: [] for name in modules}
    hashes = set()
    for seed in args.seeds:
        for name, module in modules.items():  # the formats alternate, so both see the same machine load
            tag = f"{'reference' if 'reference' in name else 'compressed'}_seed{seed}"
            runs = args.output / "runs"
            runs.mkdir(parents=True, exist_ok=True)
            hashes.add(code_hash())
            started = time.time()
            run(module, "ns-train", args.method, "--output-dir", str(runs), "--experiment-name", tag, "--timestamp",
                "run", "--max-num-iterations", str(args.iterations), *schedule_options(args.iterations),
                "--machine.seed", str(seed), "--machine.device-type", "cpu", "--vis", "tensorboard",
                "--pipeline.datamanager.sam-cache-dir", str(args.output / f"sam_{tag.split('_')[0]}"),
                "neural-3d-video-data", "--data", str(scene), "--cache-dir", str(args.output / "frames"),
                log=runs / f"{tag}.log")  # fmt: skip
            run_dir = runs / tag / args.method / "run"
            losses = [e.value for e in EventAccumulator(str(run_dir)).Reload().Scalars("Train Loss Dict/sam_loss")]
            record = {"sam_loss": float(np.mean(losses[-args.last:])), "train_s": time.time() - started}
            for object_id in args.objects:
                x, y = clicker.click_pixel(scene, object_id)
                track_dir = args.output / f"track_{tag}_{object_id}"
                log = runs / f"{tag}_track{object_id}.log"
                tracked = run(module, "ns-gear-track", "--load-config", str(run_dir / "config.yml"), "--output-dir",
                              str(track_dir), "--overwrite", "--click-camera", "cam01", "--click-time",
                              str(2 / (spec.frames - 1)), "--positive", str(x), str(y), "--target-cameras", "cam00",
                              "--propagation", args.propagation, log=log, check=False)  # fmt: skip
                if not tracked:  # e.g. a click that hits nothing on a briefly trained model: counted as nan
                    print(f"{name} seed {seed}: {log.read_text().strip().splitlines()[-1]}", flush=True)
                metrics = json.loads((track_dir / "tracking.json").read_text())["metrics"] if tracked else {}
                record[f"mIoU {object_id}"] = 100 * metrics.get("mIoU", np.nan)
                record[f"t-mIoU {object_id}"] = 100 * metrics.get("t-mIoU", np.nan)
            results[name].append(record)
            print(name, seed, record, flush=True)
    hashes.add(code_hash())
    keys = ["sam_loss"] + [f"{m} {o}" for o in args.objects for m in ("mIoU", "t-mIoU")]
    names = {2: "slow sphere", 3: "fast sphere", 1: "static sphere"}
    header = ["final L_SAM (mean of the last logged values)"] + [
        f"{m} {names.get(o, o)} ({o})" for o in args.objects for m in ("mIoU", "t-mIoU")
    ]
    lines = [
        f"## Training and tracking, {args.method}, {args.iterations} iterations, seeds {list(args.seeds)}",
        "",
        f"Synthetic N3D scene (64x48, 8 cameras, 6 frames, mixed motion, the tracking benchmark's), built-in "
        f"backend; `ns-gear-track` from one click in cam01 at time 0.4 to held-out cam00 at every frame time, "
        f"propagation `{args.propagation}`. Mean ± sample standard deviation over seeds; L_SAM is the mean of the "
        f"last {args.last} logged values. Code of the rest of the project (hash of its .py files): "
        f"{'unchanged during the runs' if len(hashes) == 1 else f'CHANGED during the runs ({sorted(hashes)})'}.",
        "",
        "| cache format | " + " | ".join(header) + " | training + tracking s |",
        "|---|" + "---|" * (len(header) + 1),
    ]
    for name, records in results.items():
        cells = [mean_spread([r[key] for r in records], 4 if key == "sam_loss" else 3) for key in keys]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {mean_spread([r['train_s'] for r in records], 3)} |")
    lines += ["", "Per seed:", "", "| cache format | seed | " + " | ".join(keys) + " |"]
    lines.append("|---|---|" + "---|" * len(keys))
    for name, records in results.items():
        for seed, record in zip(args.seeds, records):
            lines.append(f"| {name} | {seed} | " + " | ".join(f"{record[key]:.5g}" for key in keys) + " |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--output", type=Path, default=Path("outputs/sam_cache"))
    parser.add_argument("--reference-module", type=Path, help="the float16 feature_cache.py to compare against")
    parser.add_argument("--skip-training", action="store_true", help="sizes, reconstruction and lookup time only")
    parser.add_argument("--method", default="gear-nerf-small")
    parser.add_argument("--iterations", type=int, default=1500)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--objects", type=int, nargs="+", default=[2, 3], help="synthetic object ids to track")
    parser.add_argument("--propagation", default="embedding", choices=["box", "embedding"])
    parser.add_argument("--last", type=int, default=10, help="logged L_SAM values averaged for the final value")
    parser.add_argument("--agreement-every", type=int, default=20, help="every n-th real frame for the masks")
    parser.add_argument("--lookup-rays", type=int, default=4096)
    parser.add_argument("--lookup-images", type=int, default=40, help="images per batch (the presets sample from 40)")
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    reference = load_module(args.reference_module) if args.reference_module else None
    frames = real_frames(args.output / "real_frames")
    cache_dir = args.output / "real_cache"
    lines = [
        "# SAM feature cache: size and fidelity",
        "",
        f"Command: `{' '.join([os.path.relpath(sys.executable, REPO), *sys.argv])}`",
        f"Load average at the start: {' / '.join(f'{v:.2f}' for v in os.getloadavg())} (1 / 5 / 15 min).",
        "",
        *sizes(frames, cache_dir, reference),
        "",
        *reconstruction(frames, cache_dir),
    ]  # fmt: skip
    if reference is not None:
        lines += ["", *decoder_agreement(frames[:: args.agreement_every], cache_dir, reference, clicks=3)]
        lookup_frames = frames[:: max(1, len(frames) // args.lookup_images)][: args.lookup_images]
        lines += ["", *lookup_time(lookup_frames, cache_dir, reference, args.lookup_rays, repeats=20)]
        if not args.skip_training:
            lines += ["", *training(args)]
    lines += ["", f"Load average at the end: {' / '.join(f'{v:.2f}' for v in os.getloadavg())} (1 / 5 / 15 min)."]
    report = "\n".join(lines) + "\n"
    print(report)
    (args.output / "sam_cache.md").write_text(report)


if __name__ == "__main__":
    main()
