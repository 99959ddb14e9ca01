"""SAM feature cache and the SAM-aware datamanager (targets of Eq 9), with the real built-in backend."""

from __future__ import annotations

import copy
import json
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from PIL import Image

from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from gear_nerfstudio.data.datamanager import GearDataManagerConfig
from gear_nerfstudio.method_configs.gear_nerf import gear_nerf_small
from gear_nerfstudio.model.gear_model import GearNeRFModelConfig
from gear_nerfstudio.sam.builtin_backend import BuiltinSamBackend
from gear_nerfstudio.sam.interface import Embedding, cell_centres, sample_features, valid_grid
from gear_nerfstudio.sam.feature_cache import MAX_COMPONENTS, SamFeatureCache, read_header
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene
from tests.conftest import SHARED_REAL

pytestmark = pytest.mark.cost(30)

BIN = Path(sys.executable).parent
SPEC = SyntheticSpec(dataset="n3d", width=24, height=18, frames=2, cameras=3)  # 4 training, 2 held-out images


class CountingBackend(BuiltinSamBackend):
    """The built-in backend, counting (and keeping) its encoder outputs; `variant` changes its settings only."""

    def __init__(self, variant: int = 0):
        super().__init__()
        self.variant = variant
        self.outputs = []

    @property
    def settings(self):
        return {**super().settings, "variant": self.variant}

    @property
    def calls(self) -> int:
        return len(self.outputs)

    def encode(self, image):
        self.outputs.append(super().encode(image))
        return self.outputs[-1]


class FullRankBackend(BuiltinSamBackend):
    """Features of full rank: Gaussian noise (seeded by the image) plus `value` in channel 0 of cell (0, 0)."""

    name = "full-rank"

    def __init__(self, value: float = 0.0):
        super().__init__()
        self.value = value

    def encode(self, image):
        rng = np.random.default_rng(int(image.sum()))
        features = rng.standard_normal((self.embedding_dim, self.grid_size, self.grid_size)).astype(np.float32)
        features[0, 0, 0] += self.value
        return Embedding(features=features, image_size=image.shape[:2])


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    folder = tmp_path_factory.mktemp("images")
    rng = np.random.default_rng(0)
    paths = []
    for i, size in enumerate([(18, 24), (30, 20)]):  # landscape and portrait
        paths.append(folder / f"image{i}.png")
        Image.fromarray(rng.integers(0, 256, (*size, 3), dtype=np.uint8)).save(paths[-1])
    return paths


@pytest.fixture(scope="module")
def warm(images, tmp_path_factory):
    """A cache directory holding the features of `images`, and the backend that computed them."""
    folder = tmp_path_factory.mktemp("sam-cache")
    backend = CountingBackend()
    SamFeatureCache(backend, folder, images).precompute()
    return folder, backend


def test_cache_computes_once_compressed(images, warm):
    folder, first = warm
    assert first.calls == len(images)
    again = CountingBackend()  # a second set-up, as a new training run does
    cache = SamFeatureCache(again, folder, images)
    assert cache.precompute() == 0 and again.calls == 0

    for path in images:  # encoded on several threads: `first.outputs` is in the order they finished
        output = BuiltinSamBackend().encode(np.array(Image.open(path).convert("RGB")))
        header, offset = read_header(cache.path_for(path))
        assert header["backend"] == "builtin" and (header["grid"], header["channels"]) == (64, 256)
        count = header["components"]
        assert 1 <= count <= 16  # the built-in features span 16 dimensions
        assert cache.path_for(path).stat().st_size == offset + (count + 1) * 256 * 4 + 64 * 64 * count * 2
        embedding = cache.embedding(path)
        assert embedding.features.shape == (256, 64, 64) and embedding.features.dtype == np.float32
        assert embedding.image_size == output.image_size == Image.open(path).size[::-1]
        error = np.linalg.norm(embedding.features - output.features) / np.linalg.norm(output.features)
        assert error < 0.01, error
    assert again.calls == 0


def test_full_rank_features_are_at_least_4x_smaller_than_float16(images, tmp_path):
    """Features that no few components hold keep `MAX_COMPONENTS`: the file is the largest it gets."""
    cache = SamFeatureCache(FullRankBackend(), tmp_path, images[:1])
    cache.precompute()
    header, offset = read_header(cache.path_for(images[0]))
    assert header["components"] == MAX_COMPONENTS and header["pca_residual"] > 0.5
    size = cache.path_for(images[0]).stat().st_size
    assert size == offset + (MAX_COMPONENTS + 1) * 256 * 4 + 64 * 64 * MAX_COMPONENTS * 2
    assert 4 * size <= 64 * 64 * 256 * 2, size  # float16 (G, G, C) data alone, without a header


@pytest.mark.skipif(not (SHARED_REAL / "panoptic_basketball").is_dir(), reason="shared real data not present")
def test_round_trip_of_a_real_frame(tmp_path):
    """The built-in encoder on a real frame: per-cell errors of 0.3 % RMS at most (the decoder's masks change
    at larger ones), and a file at least 4x smaller than float16."""
    image = SHARED_REAL / "panoptic_basketball" / "Basketball_undist_00000_05.png"
    backend = BuiltinSamBackend()
    original = backend.encode(np.array(Image.open(image).convert("RGB")))
    cache = SamFeatureCache(backend, tmp_path, [image])
    decoded = cache.embedding(image)
    rows, cols = valid_grid(original.image_size, 64)
    before = original.features[:, :rows, :cols].reshape(256, -1)
    after = decoded.features[:, :rows, :cols].reshape(256, -1)
    relative = np.linalg.norm(after - before, axis=0) / np.linalg.norm(before, axis=0)
    rms = np.sqrt(np.mean(relative**2))
    assert rms < 0.003 and relative.max() < 0.02, (rms, relative.max())  # 8-bit codes: 0.4 %, 2.2 %
    assert 4 * cache.path_for(image).stat().st_size <= 64 * 64 * 256 * 2


def test_old_format_files_are_recomputed(images, warm, tmp_path):
    """A float16 file of the first format (b"GEARSAM1"), header otherwise matching, is encoded again."""
    shutil.copytree(warm[0], tmp_path, dirs_exist_ok=True)
    backend = CountingBackend()
    cache = SamFeatureCache(backend, tmp_path, images[:1])
    file = cache.path_for(images[0])
    header, offset = read_header(file)
    old = {key: header[key] for key in ("backend", "settings", "source", "image_size")}
    text = json.dumps({**old, "shape": [64, 64, 256], "dtype": "float16"}).encode().ljust(500)
    data = cache.embedding(images[0]).features.transpose(1, 2, 0).astype(np.float16)
    file.write_bytes(b"GEARSAM1" + struct.pack("<I", len(text)) + text + data.tobytes())
    cache = SamFeatureCache(backend, tmp_path, images[:1])
    assert read_header(file) is None
    assert cache.precompute() == 1 and backend.calls == 1 and read_header(file) is not None


def test_non_finite_features_are_a_one_line_error(images, tmp_path):
    cache = SamFeatureCache(FullRankBackend(value=np.nan), tmp_path, images[:1])
    with pytest.raises(ValueError, match=f"features of {images[0]} are not finite$"):
        cache.precompute()
    assert not any(tmp_path.rglob("*"))


def test_mismatched_header_recomputes(images, warm, tmp_path):
    shutil.copytree(warm[0], tmp_path, dirs_exist_ok=True)
    other = CountingBackend(variant=1)  # other settings: recomputed (into other files)
    assert SamFeatureCache(other, tmp_path, images[:1]).precompute() == 1 and other.calls == 1

    backend = CountingBackend()
    cache = SamFeatureCache(backend, tmp_path, images)
    # A file whose header names other settings (stale, or foreign at that name) is recomputed...
    file = cache.path_for(images[0])
    file.write_bytes(file.read_bytes().replace(b'"variant": 0', b'"variant": 7', 1))
    # ... and so is one whose source image changed since it was encoded.
    stat = images[1].stat()
    os.utime(images[1], ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    try:
        assert cache.precompute() == 2 and backend.calls == 2
        assert cache.precompute() == 0
    finally:
        os.utime(images[1], ns=(stat.st_atime_ns, stat.st_mtime_ns))
        cache.precompute()  # leave the shared warm cache matching the restored file for later tests


def test_bilinear_lookup_matches_the_embedding(images, warm):
    cache = SamFeatureCache(CountingBackend(), warm[0], images)
    expected = []
    for index, path in enumerate(images):
        embedding = cache.embedding(path)
        features = torch.from_numpy(embedding.features)
        centres = cell_centres(embedding.image_size, embedding.grid_size)
        rows, cols = centres.shape[:2]
        at_centres = cache.features_at(torch.full((rows * cols,), index), centres.reshape(-1, 2))
        torch.testing.assert_close(at_centres, features[:, :rows, :cols].reshape(256, -1).T, atol=1e-6, rtol=1e-5)
        height, width = embedding.image_size
        pixels = torch.rand(300, 2, generator=torch.Generator().manual_seed(index)) * torch.tensor([width, height])
        expected.append(sample_features(features, pixels, embedding.image_size))
        at_pixels = cache.features_at(torch.full((300,), index), pixels)
        torch.testing.assert_close(at_pixels, expected[-1], atol=1e-6, rtol=1e-5)
        mixed_pixels = pixels if index == 0 else torch.cat([mixed_pixels, pixels])
    # One batch from both images, interleaved: each ray decoded with its own image's decoder.
    shuffle = torch.randperm(600, generator=torch.Generator().manual_seed(2))
    indices = torch.arange(2).repeat_interleave(300)
    mixed = cache.features_at(indices[shuffle], mixed_pixels[shuffle])
    torch.testing.assert_close(mixed, torch.cat(expected)[shuffle], atol=1e-6, rtol=1e-5)
    assert cache.backend.calls == 0


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    root = tmp_path_factory.mktemp("sam-scene")
    return root, write_synthetic_scene(root / "scene", SPEC)


def datamanager_config(root: Path, data: Path, **kwargs) -> GearDataManagerConfig:
    return GearDataManagerConfig(
        dataparser=Neural3DVideoDataParserConfig(data=data, cache_dir=root / "frames"),
        sam_cache_dir=kwargs.pop("sam_cache_dir", root / "sam"),
        train_num_rays_per_batch=256,
        eval_num_rays_per_batch=128,
        train_num_images_to_sample_from=3,  # a subset of the 4 training images, resampled
        train_num_times_to_repeat_images=1,
        **kwargs,
    )


def attached(config: GearDataManagerConfig):
    """A datamanager with the built-in SAM backend attached, as the pipeline attaches its backend."""
    manager = config.setup(device="cpu", test_mode="val")
    manager.attach_sam(BuiltinSamBackend())
    return manager


@pytest.fixture(scope="module")
def datamanager(scene):
    root, data = scene
    return attached(datamanager_config(root, data))


def test_batches_carry_the_cached_features_at_pixel_centres(datamanager):
    for step in range(3):
        _, batch = datamanager.next_train(step)
        indices, features = batch["indices"], batch["sam_features"]
        assert features.shape == (256, BuiltinSamBackend().embedding_dim) and features.dtype == torch.float32
        for image_index in indices[:, 0].unique().tolist():
            rows = indices[:, 0] == image_index
            embedding = datamanager.train_embedding(image_index)
            pixels = indices[rows][:, [2, 1]].float() + 0.5
            expected = sample_features(torch.from_numpy(embedding.features), pixels, embedding.image_size)
            torch.testing.assert_close(features[rows], expected, atol=1e-6, rtol=1e-5)
    _, batch = datamanager.next_eval(0)
    assert batch["sam_features"].shape == (128, 256)


def test_second_setup_and_ablation_never_run_the_encoder(scene, datamanager, monkeypatch):
    calls = []
    encode = BuiltinSamBackend.encode
    monkeypatch.setattr(BuiltinSamBackend, "encode", lambda self, image: calls.append(1) or encode(self, image))
    root, data = scene
    again = attached(datamanager_config(root, data))
    assert "sam_features" in again.next_train(0)[1] and not calls

    ablation = datamanager_config(root, data, use_sam_features=False, sam_cache_dir=root / "unused")
    manager = attached(ablation)
    assert "sam_features" not in manager.next_train(0)[1] and "sam_features" not in manager.next_eval(0)[1]
    assert not calls and not (root / "unused").exists()


def test_sam_dim_mismatch_is_a_clear_error(scene, tmp_path):
    """The pipeline checks at set-up that the model's SAM head predicts the backend's C."""
    root, data = scene
    config = copy.deepcopy(gear_nerf_small.config.pipeline)
    config.datamanager = datamanager_config(root, data)
    config.model.sam_dim = 64
    with pytest.raises(ValueError, match="sam_dim is 64 but the SAM backend 'builtin' gives 256"):
        config.setup(device="cpu", test_mode="val")


def test_datamanager_without_a_backend_is_a_clear_error(scene):
    """The SAM backend comes from the pipeline: in a plain VanillaPipeline the datamanager says so."""
    root, data = scene
    config = VanillaPipelineConfig(datamanager=datamanager_config(root, data), model=GearNeRFModelConfig())
    pipeline = config.setup(device="cpu", test_mode="val")
    with pytest.raises(RuntimeError, match="no SAM backend: use it in a GearPipelineConfig"):
        pipeline.datamanager.next_train(0)


def test_ns_train_optimises_the_sam_loss(scene, datamanager, tmp_path):
    """Five iterations of the CPU preset log L_SAM (Eq 9); the features come from the warm cache."""
    root, data = scene
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "XDG_CACHE_HOME": str(tmp_path)}
    command = [
        str(BIN / "ns-train"), "gear-nerf-small", "--output-dir", str(tmp_path / "runs"), "--experiment-name", "sam",
        "--timestamp", "run", "--max-num-iterations", "5", "--machine.device-type", "cpu", "--vis", "tensorboard",
        "--steps-per-eval-all-images", "1000", "--pipeline.datamanager.sam-cache-dir", str(root / "sam"),
        "--pipeline.gear-updates.enabled", "False",
        "neural-3d-video-data", "--data", str(data), "--cache-dir", str(root / "frames"),
    ]  # fmt: skip
    cached = {p: p.stat().st_mtime_ns for p in (root / "sam").rglob("*")}
    result = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=300, env=env)
    assert result.returncode == 0, f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    assert {p: p.stat().st_mtime_ns for p in (root / "sam").rglob("*")} == cached  # nothing encoded again

    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(tmp_path / "runs" / "sam" / "gear-nerf-small" / "run")).Reload()
    sam_loss = events.Scalars("Train Loss Dict/sam_loss")
    assert sam_loss and all(np.isfinite(e.value) and e.value > 0 for e in sam_loss)
