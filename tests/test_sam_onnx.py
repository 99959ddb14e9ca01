"""The ONNX SAM backend against segment-anything's own SamPredictor, on a tiny randomly initialised SAM
exported with the package's own model classes and ONNX wrapper (no weights can be downloaded)."""

from __future__ import annotations

import dataclasses
import json
import re
import subprocess
import sys
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from gear_nerfstudio.gears.config import GearUpdateConfig
from gear_nerfstudio.gears.updater import with_mask_source
from gear_nerfstudio.sam.builtin_backend import BuiltinSamBackend
from gear_nerfstudio.sam.config import BuiltinSamConfig, OnnxSamConfig
from gear_nerfstudio.sam.feature_cache import read_header
from gear_nerfstudio.sam.interface import Embedding
from gear_nerfstudio.sam.onnx_backend import (
    OnnxSamBackend,
    SamModelError,
    preprocess_image,
    preprocess_shape,
    prompt_inputs,
    transform_coords,
)
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene
from gear_nerfstudio.tracking.cli import dataset_cameras
from gear_nerfstudio.tracking.click import project_prompt
from gear_nerfstudio.tracking.propagation import render_embedding, segment

pytest.importorskip("segment_anything")
pytest.importorskip("onnxruntime")
pytest.importorskip("onnx")  # torch.onnx.export needs it

from segment_anything import SamPredictor  # noqa: E402

from tests.conftest import IMPORT_WARNING, command, ns  # noqa: E402
from segment_anything.modeling import ImageEncoderViT, MaskDecoder, PromptEncoder, Sam, TwoWayTransformer  # noqa: E402
from segment_anything.utils.onnx import SamOnnxModel  # noqa: E402
from segment_anything.utils.transforms import ResizeLongestSide  # noqa: E402

# Exporting segment-anything's modules warns about traced constants, the legacy exporter and indexing.
pytestmark = [
    pytest.mark.cost(100),
    pytest.mark.filterwarnings(
        "ignore::torch.jit.TracerWarning", "ignore:.*legacy TorchScript-based ONNX", "ignore:Exporting aten..index operator"
    ),
]

IMAGE_SIZES = [(48, 40), (30, 40)]
DECODER_INPUT_NAMES = [
    "image_embeddings",
    "point_coords",
    "point_labels",
    "mask_input",
    "has_mask_input",
    "orig_im_size",
]


def tiny_sam(grid: int = 64) -> Sam:
    """A SAM with SAM's structure (ViT encoder with windowed and global attention, prompt encoder,
    two-way transformer decoder) but a few thousand parameters, randomly initialised with a fixed seed."""
    torch.manual_seed(0)
    image_size = grid * 16
    sam = Sam(
        image_encoder=ImageEncoderViT(
            img_size=image_size,
            patch_size=16,
            embed_dim=32,
            depth=2,
            num_heads=2,
            mlp_ratio=2.0,
            out_chans=256,
            qkv_bias=True,
            norm_layer=partial(torch.nn.LayerNorm, eps=1e-6),
            use_rel_pos=True,
            window_size=8,
            global_attn_indexes=(1,),
        ),
        prompt_encoder=PromptEncoder(
            embed_dim=256,
            image_embedding_size=(grid, grid),
            input_image_size=(image_size, image_size),
            mask_in_chans=16,
        ),
        mask_decoder=MaskDecoder(
            num_multimask_outputs=3,
            transformer=TwoWayTransformer(depth=1, embedding_dim=256, mlp_dim=32, num_heads=2),
            transformer_dim=256,
            iou_head_depth=2,
            iou_head_hidden_dim=32,
        ),
    )
    with torch.no_grad():  # parameters that SAM initialises to zero (positions) get random values too
        for parameter in sam.parameters():
            if not parameter.any():
                parameter.normal_(0.0, 0.05)
    return sam.eval()


def export_encoder(encoder: torch.nn.Module, path: Path) -> Path:
    """An image encoder taking the pre-processed (1, 3, 1024, 1024) image, as the backend expects."""
    image = torch.randn(1, 3, 1024, 1024)
    export = dict(dynamo=False, opset_version=17, input_names=["image"], output_names=["image_embeddings"])
    torch.onnx.export(encoder, (image,), str(path), **export)
    return path


def export_decoder(sam: Sam, path: Path, input_names=DECODER_INPUT_NAMES, return_single_mask: bool = False) -> Path:
    """As segment-anything's scripts/export_onnx_model.py does (dynamic number of points)."""
    grid = sam.prompt_encoder.image_embedding_size
    dummy = (
        torch.randn(1, 256, *grid),
        torch.randint(0, 1024, (1, 5, 2), dtype=torch.float),
        torch.randint(0, 4, (1, 5), dtype=torch.float),
        torch.randn(1, 1, 4 * grid[0], 4 * grid[1]),
        torch.tensor([1.0]),
        torch.tensor([1500.0, 2250.0]),
    )
    export = dict(
        dynamo=False,
        opset_version=17,
        do_constant_folding=True,
        input_names=list(input_names),
        output_names=["masks", "iou_predictions", "low_res_masks"],
        dynamic_axes={input_names[1]: {1: "num_points"}, input_names[2]: {1: "num_points"}},
    )
    torch.onnx.export(SamOnnxModel(sam, return_single_mask=return_single_mask), dummy, str(path), **export)
    return path


@pytest.fixture(scope="session")
def sam_model() -> Sam:
    return tiny_sam()


@pytest.fixture(scope="session")
def onnx_files(sam_model, tmp_path_factory) -> dict:
    """The tiny SAM exported once per session, plus broken variants for the error cases."""
    folder = tmp_path_factory.mktemp("sam-onnx")
    garbage = folder / "garbage.onnx"
    garbage.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    renamed = ["embeddings", *DECODER_INPUT_NAMES[1:]]
    return {
        "encoder": export_encoder(sam_model.image_encoder, folder / "encoder.onnx"),
        "decoder": export_decoder(sam_model, folder / "decoder.onnx"),
        "decoder_single": export_decoder(sam_model, folder / "decoder_single.onnx", return_single_mask=True),
        "decoder_renamed": export_decoder(sam_model, folder / "decoder_renamed.onnx", input_names=renamed),
        "decoder_grid32": export_decoder(tiny_sam(grid=32), folder / "decoder_grid32.onnx"),
        "encoder_grid32": export_encoder(torch.nn.Conv2d(3, 256, 32, stride=32), folder / "encoder_grid32.onnx"),
        "garbage": garbage,
    }


@pytest.fixture(scope="session")
def backend(onnx_files) -> OnnxSamBackend:
    return OnnxSamBackend(onnx_files["encoder"], onnx_files["decoder"])


def _image(size) -> np.ndarray:
    """A smooth non-square test image with a bright disc."""
    height, width = size
    ys, xs = np.mgrid[0:height, 0:width]
    disc = (xs - 0.6 * width) ** 2 + (ys - 0.4 * height) ** 2 < (0.25 * min(size)) ** 2
    rgb = np.stack([xs / width, ys / height, 0.5 + 0.5 * disc], axis=-1) * 255
    return rgb.round().astype(np.uint8)


def test_preprocessing_matches_segment_anything(sam_model):
    transform = ResizeLongestSide(1024)
    for size in IMAGE_SIZES + [(1088, 2048), (1014, 1352), (333, 500)]:
        assert preprocess_shape(*size) == transform.get_preprocess_shape(size[0], size[1], 1024)
        coords = np.array([[0.0, 0.0], [size[1] - 1.0, size[0] - 1.0], [3.25, 7.5]])
        np.testing.assert_allclose(transform_coords(coords, size), transform.apply_coords(coords, size))
    for size in IMAGE_SIZES:
        image = _image(size)
        resized = torch.as_tensor(transform.apply_image(image)).permute(2, 0, 1)[None]
        expected = sam_model.preprocess(resized.float()).numpy()
        np.testing.assert_allclose(preprocess_image(image), expected, atol=1e-5)


def test_prompt_inputs_follow_the_onnx_example():
    size = (48, 40)
    coords, labels = prompt_inputs(np.array([[10.0, 20.0]]), np.array([1]), None, size)
    np.testing.assert_allclose(coords[0], [transform_coords([10.0, 20.0], size), [0.0, 0.0]], rtol=1e-6)
    np.testing.assert_array_equal(labels[0], [1.0, -1.0])
    coords, labels = prompt_inputs(np.array([[10.0, 20.0]]), np.array([0]), np.array([1.0, 2.0, 30.0, 40.0]), size)
    np.testing.assert_allclose(coords[0], transform_coords([[10.0, 20.0], [1.0, 2.0], [30.0, 40.0]], size), rtol=1e-6)
    np.testing.assert_array_equal(labels[0], [0.0, 2.0, 3.0])
    assert coords.dtype == np.float32 and labels.dtype == np.float32
    with pytest.raises(ValueError):
        prompt_inputs(None, None, None, size)


@pytest.mark.parametrize("size", IMAGE_SIZES)
def test_onnx_backend_matches_sam_predictor(backend, sam_model, size):
    image = _image(size)
    predictor = SamPredictor(sam_model)
    predictor.set_image(image)
    embedding = backend.encode(image)
    assert embedding.features.shape == (256, 64, 64) and embedding.image_size == size
    np.testing.assert_allclose(embedding.features, predictor.features[0].numpy(), atol=1e-4, rtol=1e-4)

    height, width = size
    click, corner = np.array([[0.6 * width, 0.4 * height]]), np.array([[5.0, 6.0]])
    box = np.array([0.3 * width, 0.1 * height, 0.9 * width, 0.7 * height])
    cases = [  # points, labels, box, multimask_output as SAM recommends (one click is ambiguous)
        (click, np.array([1]), None, True),
        (np.concatenate([corner, click]), np.array([0, 1]), None, False),
        (None, None, box, False),
        (click, np.array([1]), box, False),
    ]
    for points, labels, prompt_box, multimask in cases:
        masks, scores = backend.decode(embedding, points, labels, prompt_box)
        expected_masks, expected_scores, _ = predictor.predict(points, labels, prompt_box, multimask_output=multimask)
        assert masks.dtype == bool and masks.shape[1:] == size
        if multimask:  # the three multimask outputs, by predicted IoU
            order = np.argsort(-expected_scores, kind="stable")
            expected_masks, expected_scores = expected_masks[order], expected_scores[order]
            assert masks.shape[0] == 3
        else:  # SAM's single-mask output comes first
            assert masks.shape[0] == 4
        np.testing.assert_allclose(scores[: len(expected_scores)], expected_scores, atol=1e-5)
        agreement = (masks[: len(expected_masks)] == expected_masks).mean()
        assert agreement > 0.999, (points, labels, prompt_box, agreement)
        assert 0.05 < expected_masks.mean() < 0.95  # the tiny model's masks are not trivial


def test_single_mask_export(onnx_files, backend):
    single = OnnxSamBackend(onnx_files["encoder"], onnx_files["decoder_single"])
    embedding = backend.encode(_image((48, 40)))
    masks, scores = single.decode(embedding, np.array([[20.0, 20.0]]), np.array([1]))
    assert masks.shape == (1, 48, 40) and scores.shape == (1,)


def test_settings_name_both_files(backend, onnx_files):
    settings = backend.settings
    assert backend.name == "onnx" and backend.embedding_dim == 256 and backend.grid_size == 64
    for role in ("encoder", "decoder"):
        assert settings[role]["path"] == str(onnx_files[role].resolve())
        assert settings[role]["size"] == onnx_files[role].stat().st_size
        assert settings[role]["mtime_ns"] == onnx_files[role].stat().st_mtime_ns


def test_config_builds_backends(onnx_files):
    config = OnnxSamConfig(encoder=onnx_files["encoder"], decoder=onnx_files["decoder"])
    assert isinstance(config.setup(), OnnxSamBackend)
    with pytest.raises(SamModelError, match="encoder"):
        OnnxSamConfig(decoder=onnx_files["decoder"]).setup()
    assert BuiltinSamConfig().setup().name == "builtin"


def test_the_gear_updates_take_sams_masks_with_a_sam_backend_and_the_loss_threshold_with_the_stand_in(backend):
    """mask_source 'auto' (the default): the paper's SAM masks with an ONNX SAM backend, the loss threshold with the
    built-in stand-in; a mask source that is set stays."""
    config = GearUpdateConfig()
    assert config.mask_source == "auto"
    assert with_mask_source(config, backend).mask_source == "sam"
    assert with_mask_source(config, BuiltinSamBackend()).mask_source == "loss_threshold"
    chosen = dataclasses.replace(config, mask_source="sam")
    assert with_mask_source(chosen, BuiltinSamBackend()) is chosen


@pytest.mark.parametrize(
    "encoder, decoder, message",
    [
        ("missing", "decoder", "does not exist"),
        ("encoder", "missing", "does not exist"),
        ("folder", "decoder", "is not a file"),
        ("garbage", "decoder", "not a readable ONNX model"),
        ("encoder", "garbage", "not a readable ONNX model"),
        ("encoder", "decoder_renamed", "missing \\['image_embeddings'\\]"),
        ("encoder", "decoder_grid32", "'image_embeddings'"),
        ("encoder_grid32", "decoder", "output 'image_embeddings' has shape"),
        ("decoder", "encoder", "expected one input"),
        ("encoder", "encoder", "not the official segment-anything ONNX decoder"),
    ],
)
def test_bad_model_files_fail_clearly(onnx_files, tmp_path, encoder, decoder, message):
    files = {**onnx_files, "missing": tmp_path / "nowhere.onnx", "folder": tmp_path}
    with pytest.raises(SamModelError, match=message) as error:
        OnnxSamBackend(files[encoder], files[decoder])
    assert isinstance(error.value, ValueError)
    bad = files[encoder] if encoder != "encoder" else files[decoder]
    assert str(bad) in str(error.value)


def test_ns_train_offers_the_onnx_backend(onnx_files, scene_dirs, tmp_path):
    """`sam-onnx` on the ns-train command line builds the ONNX backend from its files: a missing encoder stops the
    run before anything is written, with the backend's error in one line naming the file."""
    missing = tmp_path / "nowhere.onnx"
    result = command(
        "ns-train", "gear-nerf-small", "--output-dir", str(tmp_path / "runs"), "--machine.device-type", "cpu",
        "--vis", "tensorboard", "neural-3d-video-data", "--data", str(scene_dirs["n3d"]),
        "--cache-dir", str(tmp_path / "cache"), "sam-onnx", "--encoder", str(missing),
        "--decoder", str(onnx_files["decoder"]), cwd=tmp_path,
    )
    assert result.returncode == 1
    errors = [line for line in result.stderr.splitlines() if not IMPORT_WARNING.search(line)]
    assert errors == [f"error: SAM encoder file {missing} does not exist"], result.stderr[-2000:]
    assert not (tmp_path / "runs").exists()


def test_onnxruntime_is_imported_only_when_needed():
    """nerfstudio imports the plugin on every command: the SAM modules must not pull onnxruntime in."""
    code = (
        "import sys, gear_nerfstudio.sam.config, gear_nerfstudio.sam.onnx_backend, gear_nerfstudio.sam.builtin_backend;"
        "assert 'onnxruntime' not in sys.modules and 'segment_anything' not in sys.modules"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_decode_rejects_bad_embeddings(backend):
    with pytest.raises(ValueError, match="shape"):
        backend.decode(Embedding(np.zeros((256, 32, 32), np.float32), (48, 40)), np.array([[1.0, 1.0]]), np.array([1]))


def test_onnx_backend_end_to_end_through_ns_train_and_ns_gear_track(onnx_files, tmp_path):
    """A user's own SAM or MobileSAM export (the tiny SAM above stands in for it) through both commands.

    `ns-train ... sam-onnx --encoder E --decoder D` encodes every image with the ONNX encoder into the SAM feature
    cache (each file's header names the backend and both model files), trains the SAM head on it (L_SAM is logged)
    and prompts the ONNX decoder in its gear updates (mask source "sam"). `ns-gear-track` on that run takes the
    backend from config.yml, reuses the cache and decodes the model's rendered 256 x 64 x 64 embeddings with the
    ONNX decoder.

    The SAM is random and the model trained for 20 iterations: it renders almost the same feature in every cell,
    so the random decoder returns its own 4-cell upsampling pattern, aliased to a stripe pattern at 24 x 18 (the
    masks were looked at). This checks the plumbing, not the quality. That the ONNX decoder made the masks is
    checked by decoding the model's rendered embedding at the clicked time with a fresh `OnnxSamBackend` and the
    projected click, and by the built-in decoder giving another mask there.
    """
    from nerfstudio.utils.eval_utils import eval_setup
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cameras, frames, size = 3, 3, (18, 24)  # the encoder runs at 1024 x 1024 once per image: 9 images
    spec = SyntheticSpec(dataset="n3d", width=size[1], height=size[0], frames=frames, cameras=cameras)
    scene = write_synthetic_scene(tmp_path / "scene", spec)
    encoder, decoder = onnx_files["encoder"], onnx_files["decoder"]
    sam_cache, run = tmp_path / "sam-cache", tmp_path / "runs" / "onnx" / "gear-nerf-small" / "run"
    trained = ns(
        "ns-train", "gear-nerf-small", "--output-dir", str(tmp_path / "runs"), "--experiment-name", "onnx",
        "--timestamp", "run", "--machine.device-type", "cpu", "--vis", "tensorboard", "--max-num-iterations", "20",
        "--steps-per-eval-all-images", "1000", "--pipeline.gear-updates.iterations-per-epoch", "1",
        "--pipeline.datamanager.sam-cache-dir", str(sam_cache),
        "neural-3d-video-data", "--data", str(scene), "--cache-dir", str(tmp_path / "frames"),
        "sam-onnx", "--encoder", str(encoder), "--decoder", str(decoder), cwd=tmp_path,
    )  # fmt: skip

    # What ns-train wrote: a cache of the ONNX encoder's features of every image, the SAM loss, a checkpoint.
    backend = OnnxSamBackend(encoder, decoder)
    files = sorted(sam_cache.rglob("*.samf"))
    assert [f.parent for f in files] == [sam_cache / "onnx"] * cameras * frames, files
    for file in files:
        header, _ = read_header(file)
        assert header["backend"] == "onnx" and header["grid"] == 64 and header["channels"] == 256
        assert header["settings"] == backend.settings  # both model files: resolved path, size and mtime
        assert header["settings"]["encoder"]["path"] == str(encoder.resolve())
        assert header["settings"]["decoder"]["path"] == str(decoder.resolve())
        assert header["image_size"] == list(size)
    cached = {file: file.stat().st_mtime_ns for file in files}
    sam_loss = EventAccumulator(str(run)).Reload().Scalars("Train Loss Dict/sam_loss")
    assert sam_loss and all(np.isfinite(e.value) and e.value > 0 for e in sam_loss)
    assert (run / "nerfstudio_models" / "step-000000019.ckpt").is_file()
    for number, step in ((1, 3), (2, 6), (3, 9)):  # epochs of one iteration: L = 3
        assert f"Gear update {number} at step {step}:" in trained.stdout, trained.stdout[-3000:]
    log = " ".join(re.sub(r"\S+\.py:\d+", " ", trained.stdout).split())  # rich's log lines, unwrapped
    assert "Upshift masks from the SAM decoder on the loss maps' prompts." in log  # mask_source 'auto' with SAM
    config = run / "config.yml"

    # The click: the middle of the fast sphere in cam01 at time 0.5 (frame 1), from the scene's ground truth.
    ids = np.load(scene / "ground_truth" / "cam01.npz")["object_ids"][1]
    rows, cols = np.nonzero(ids == 3)
    x, y = float(np.median(cols)) + 0.5, float(np.median(rows)) + 0.5
    out = tmp_path / "track"
    result = ns(
        "ns-gear-track", "--load-config", str(config), "--output-dir", str(out), "--click-camera", "cam01",
        "--click-time", "0.5", "--positive", str(x), str(y), "--target-cameras", "cam00", "--times", "0.5", "1.0",
        "--min-accumulation", "0.01", "--no-video", cwd=tmp_path,
    )  # fmt: skip
    assert "Traceback" not in result.stderr
    assert {file: file.stat().st_mtime_ns for file in sorted(sam_cache.rglob("*.samf"))} == cached  # not re-encoded
    summary = json.loads((out / "tracking.json").read_text())
    assert summary["targets"] == ["cam00"] and summary["times"] == [0.5, 1.0]
    assert summary["sam_backend"] == {"name": "onnx", "settings": backend.settings}
    by_time = {record["time"]: record for record in summary["masks"]}
    assert sorted(by_time) == [0.5, 1.0]
    masks = {time: np.asarray(Image.open(out / record["mask"])) > 127 for time, record in by_time.items()}
    assert all(mask.shape == size for mask in masks.values())
    assert by_time[1.0]["prompt"]["from_time"] == 0.5

    # The clicked-time mask is the ONNX decoder's on the model's rendered embedding, prompted at the click's point.
    _, pipeline, _, _ = eval_setup(config, test_mode="test")
    assert isinstance(pipeline.sam_backend, OnnxSamBackend)  # the backend comes from config.yml
    pipeline.model.see_from(pipeline.datamanager.train_dataparser_outputs.cameras, summary["min_views"])  # as it renders
    target = dataset_cameras(pipeline)[0]["cam00"]
    point = torch.tensor(summary["click"]["prompts"][0]["point"])
    pixel = np.array([project_prompt(target, point)])
    np.testing.assert_allclose(by_time[0.5]["prompt"]["points"], pixel, atol=1e-4)
    embedding = render_embedding(pipeline.model, target, 0.5, backend)
    assert embedding.features.shape == (256, 64, 64) and embedding.image_size == size
    expected = segment(backend, embedding, pixel, np.array([1]))
    np.testing.assert_array_equal(masks[0.5], expected)
    assert 0 < expected.sum() < expected.size  # a mask that tells the decoders apart ...
    assert (segment(BuiltinSamBackend(), embedding, pixel, np.array([1])) != expected).any()  # ... which it does
