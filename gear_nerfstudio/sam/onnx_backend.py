"""SAM or MobileSAM exported to ONNX by the user, run with onnxruntime (Sec 4.2, 4.3, 4.5).

Encoder file: one input, the pre-processed image as SAM's `Sam.preprocess` produces it: float32
(1, 3, 1024, 1024), RGB resized with ResizeLongestSide to a longest side of 1024, normalised by SAM's
pixel mean and std and zero-padded at the bottom/right; one output, the (1, 256, 64, 64) embedding
(e.g. `torch.onnx.export` of `sam.image_encoder`). Decoder file: the official segment-anything export
(`scripts/export_onnx_model.py`, `SamOnnxModel`) with inputs image_embeddings (1, 256, 64, 64),
point_coords (1, N, 2), point_labels (1, N), mask_input (1, 1, 256, 256), has_mask_input (1,),
orig_im_size (2,) and outputs masks, iou_predictions, low_res_masks.

Both files are checked when the backend is built, before any training. onnxruntime is imported only
here, when an ONNX backend is made.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence, Tuple, Union

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

from gear_nerfstudio.errors import InputError
from gear_nerfstudio.sam.interface import Embedding, SamBackend

IMAGE_SIZE = 1024  # SAM's input side
EMBEDDING_DIM = 256
GRID_SIZE = 64
MASK_INPUT_SIZE = 4 * GRID_SIZE
PIXEL_MEAN = np.array([123.675, 116.28, 103.53], dtype=np.float32)
PIXEL_STD = np.array([58.395, 57.12, 57.375], dtype=np.float32)

# Official decoder signature: input name -> shape (None: any size; the point count is dynamic).
DECODER_INPUTS: Dict[str, Tuple[Optional[int], ...]] = {
    "image_embeddings": (1, EMBEDDING_DIM, GRID_SIZE, GRID_SIZE),
    "point_coords": (1, None, 2),
    "point_labels": (1, None),
    "mask_input": (1, 1, MASK_INPUT_SIZE, MASK_INPUT_SIZE),
    "has_mask_input": (1,),
    "orig_im_size": (2,),
}
DECODER_OUTPUTS = ("masks", "iou_predictions", "low_res_masks")
ENCODER_INPUT = (1, 3, IMAGE_SIZE, IMAGE_SIZE)
ENCODER_OUTPUT = (1, EMBEDDING_DIM, GRID_SIZE, GRID_SIZE)


class SamModelError(InputError):
    """A SAM model file is missing, unreadable or does not have the expected signature."""


def preprocess_shape(height: int, width: int, long_side: int = IMAGE_SIZE) -> Tuple[int, int]:
    """ResizeLongestSide's output size (H, W), with its rounding rule int(x * scale + 0.5)."""
    scale = long_side * 1.0 / max(height, width)
    return int(height * scale + 0.5), int(width * scale + 0.5)


def preprocess_image(image: np.ndarray) -> np.ndarray:
    """SAM's encoder input (1, 3, 1024, 1024) float32 from an RGB uint8 image (H, W, 3): bilinear
    resize of the longest side to 1024 (as SamPredictor, through PIL), normalisation, zero padding."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected an RGB uint8 image (H, W, 3), got {image.dtype} {image.shape}")
    new_h, new_w = preprocess_shape(*image.shape[:2])
    resized = np.asarray(Image.fromarray(image).resize((new_w, new_h), Image.BILINEAR), dtype=np.float32)
    padded = np.zeros((IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.float32)
    padded[:new_h, :new_w] = (resized - PIXEL_MEAN) / PIXEL_STD
    return padded.transpose(2, 0, 1)[None].copy()


def transform_coords(coords: np.ndarray, image_size: Tuple[int, int]) -> np.ndarray:
    """Pixel coordinates (..., 2) = (x, y) of the original image in the resized image (apply_coords)."""
    new_h, new_w = preprocess_shape(*image_size)
    scale = np.array([new_w / image_size[1], new_h / image_size[0]])
    return np.asarray(coords, dtype=np.float64) * scale


def prompt_inputs(
    points: Optional[np.ndarray], labels: Optional[np.ndarray], box: Optional[np.ndarray], image_size: Tuple[int, int]
) -> Tuple[np.ndarray, np.ndarray]:
    """point_coords (1, N, 2) and point_labels (1, N) as SAM's ONNX example builds them: box corners
    get labels 2 and 3; without a box a padding point (0, 0) with label -1 is appended."""
    coords: List[np.ndarray] = []
    codes: List[np.ndarray] = []
    if points is not None and len(points):
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        labels = np.ones(len(points)) if labels is None else np.asarray(labels, dtype=np.float64).reshape(-1)
        if len(labels) != len(points):
            raise ValueError(f"{len(points)} points but {len(labels)} labels")
        coords.append(points)
        codes.append(labels)
    if box is not None:
        coords.append(np.asarray(box, dtype=np.float64).reshape(2, 2))
        codes.append(np.array([2.0, 3.0]))
    elif coords:
        coords.append(np.zeros((1, 2)))
        codes.append(np.array([-1.0]))
    if not coords:
        raise ValueError("decode needs points or a box")
    all_coords = np.concatenate(coords)
    all_codes = np.concatenate(codes)
    prompted = all_codes != -1
    all_coords[prompted] = transform_coords(all_coords[prompted], image_size)
    return all_coords[None].astype(np.float32), all_codes[None].astype(np.float32)


def postprocess_masks(low_res: np.ndarray, image_size: Tuple[int, int]) -> np.ndarray:
    """Mask logits (B, K, H, W) at the image size from the decoder's (B, K, 256, 256) logits, as
    segment-anything's Sam.postprocess_masks: upsample to 1024, drop the padding, resize.

    The decoder's own `masks` output is not used: segment-anything 1.0 (PyPI) traces the padding crop
    with the dummy image's aspect ratio, so exports made with it give shifted masks for other shapes
    (facebookresearch/segment-anything issue #56).
    """
    logits = torch.from_numpy(np.ascontiguousarray(low_res, dtype=np.float32))
    logits = F.interpolate(logits, (IMAGE_SIZE, IMAGE_SIZE), mode="bilinear", align_corners=False)
    new_h, new_w = preprocess_shape(*image_size)
    logits = F.interpolate(logits[..., :new_h, :new_w], image_size, mode="bilinear", align_corners=False)
    return logits.numpy()


def _load_session(path: Path, role: str) -> Any:
    try:
        import onnxruntime as ort
    except ImportError as error:
        raise ImportError("the onnx SAM backend needs onnxruntime (pip install onnxruntime)") from error

    providers = ["CPUExecutionProvider"]
    if "CUDAExecutionProvider" in ort.get_available_providers():
        providers.insert(0, "CUDAExecutionProvider")
    if not path.exists():
        raise SamModelError(f"SAM {role} file {path} does not exist")
    if not path.is_file():
        raise SamModelError(f"SAM {role} path {path} is not a file")
    try:
        return ort.InferenceSession(str(path), providers=providers)
    except Exception as error:  # onnxruntime raises its own exception types for malformed models
        raise SamModelError(f"SAM {role} file {path} is not a readable ONNX model: {error}") from error


def _shape_matches(actual: Sequence[Union[int, str, None]], expected: Sequence[Optional[int]]) -> bool:
    """Whether an ONNX shape fits; symbolic (named or unknown) dimensions fit any expected size."""
    if len(actual) != len(expected):
        return False
    return all(e is None or not isinstance(a, int) or a == e for a, e in zip(actual, expected))


def _check_encoder(session: Any, path: Path) -> None:
    inputs, outputs = session.get_inputs(), session.get_outputs()
    if len(inputs) != 1:
        raise SamModelError(
            f"SAM encoder {path}: expected one input (the pre-processed image {ENCODER_INPUT}), got "
            f"{[i.name for i in inputs]}"
        )
    if not _shape_matches(inputs[0].shape, ENCODER_INPUT) or inputs[0].type != "tensor(float)":
        raise SamModelError(
            f"SAM encoder {path}: input {inputs[0].name!r} is {inputs[0].type} {inputs[0].shape}, expected "
            f"float32 {ENCODER_INPUT} (an image pre-processed as segment-anything's Sam.preprocess does)"
        )
    if not _shape_matches(outputs[0].shape, ENCODER_OUTPUT):
        raise SamModelError(
            f"SAM encoder {path}: output {outputs[0].name!r} has shape {outputs[0].shape}, expected {ENCODER_OUTPUT}"
        )


def _check_decoder(session: Any, path: Path) -> None:
    inputs = {i.name: i for i in session.get_inputs()}
    if set(inputs) != set(DECODER_INPUTS):
        raise SamModelError(
            f"SAM decoder {path}: inputs {sorted(inputs)} are not the official segment-anything ONNX "
            f"decoder's {sorted(DECODER_INPUTS)} (missing {sorted(set(DECODER_INPUTS) - set(inputs))}, "
            f"unexpected {sorted(set(inputs) - set(DECODER_INPUTS))})"
        )
    for name, expected in DECODER_INPUTS.items():
        if not _shape_matches(inputs[name].shape, expected) or inputs[name].type != "tensor(float)":
            raise SamModelError(
                f"SAM decoder {path}: input {name!r} is {inputs[name].type} {inputs[name].shape}, expected "
                f"float32 {tuple('N' if e is None else e for e in expected)}"
            )
    outputs = [o.name for o in session.get_outputs()]
    missing = [name for name in DECODER_OUTPUTS if name not in outputs]
    if missing:
        raise SamModelError(f"SAM decoder {path}: outputs {outputs} lack {missing}; expected {list(DECODER_OUTPUTS)}")


def _file_settings(path: Path) -> Dict[str, Any]:
    stat = path.stat()
    return {"path": str(path.resolve()), "size": stat.st_size, "mtime_ns": stat.st_mtime_ns}


class OnnxSamBackend(SamBackend):
    """The user's SAM / MobileSAM encoder and prompt decoder, exported to ONNX (see the module docstring)."""

    name = "onnx"
    embedding_dim = EMBEDDING_DIM
    grid_size = GRID_SIZE

    def __init__(self, encoder_path: Union[str, Path], decoder_path: Union[str, Path]) -> None:
        self.encoder_path = Path(encoder_path)
        self.decoder_path = Path(decoder_path)
        self._encoder = _load_session(self.encoder_path, "encoder")
        _check_encoder(self._encoder, self.encoder_path)
        self._decoder = _load_session(self.decoder_path, "decoder")
        _check_decoder(self._decoder, self.decoder_path)
        self._smoke_test_decoder()

    @property
    def settings(self) -> Dict[str, Any]:
        return {"encoder": _file_settings(self.encoder_path), "decoder": _file_settings(self.decoder_path)}

    def encode(self, image: np.ndarray) -> Embedding:
        """SAM's image embedding (256, 64, 64) of an RGB uint8 image (H, W, 3)."""
        inputs = {self._encoder.get_inputs()[0].name: preprocess_image(image)}
        features = self._encoder.run(None, inputs)[0]
        if features.shape != ENCODER_OUTPUT:
            raise SamModelError(
                f"SAM encoder {self.encoder_path} returned shape {features.shape}, expected {ENCODER_OUTPUT}"
            )
        return Embedding(features=features[0].astype(np.float32), image_size=(int(image.shape[0]), int(image.shape[1])))

    def decode(
        self,
        embedding: Embedding,
        points: Optional[np.ndarray] = None,
        labels: Optional[np.ndarray] = None,
        box: Optional[np.ndarray] = None,
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Masks (logits > 0) at the image size, best first.

        A single point is ambiguous: SAM's three multimask outputs are returned by predicted IoU. Other
        prompts: the single-mask output first, as SamPredictor with multimask_output=False (decoders
        exported with --return-single-mask give that one mask only).
        """
        expected = (EMBEDDING_DIM, GRID_SIZE, GRID_SIZE)
        if tuple(embedding.features.shape) != expected:
            raise ValueError(f"expected features of shape {expected}, got {tuple(embedding.features.shape)}")
        image_size = (int(embedding.image_size[0]), int(embedding.image_size[1]))
        coords, codes = prompt_inputs(points, labels, box, image_size)
        masks, scores = self._run_decoder(
            np.asarray(embedding.features, dtype=np.float32)[None], coords, codes, image_size
        )
        if masks.shape[0] == 1:
            return masks, scores
        single_point = box is None and coords.shape[1] == 2
        multimask = np.arange(1, masks.shape[0])
        order = multimask[np.argsort(-scores[1:], kind="stable")]
        order = order if single_point else np.concatenate([[0], order])
        return masks[order], scores[order]

    def _run_decoder(
        self, features: np.ndarray, coords: np.ndarray, codes: np.ndarray, image_size: Tuple[int, int]
    ) -> Tuple[np.ndarray, np.ndarray]:
        inputs = {
            "image_embeddings": features,
            "point_coords": coords,
            "point_labels": codes,
            "mask_input": np.zeros((1, 1, MASK_INPUT_SIZE, MASK_INPUT_SIZE), dtype=np.float32),
            "has_mask_input": np.zeros(1, dtype=np.float32),
            "orig_im_size": np.array(image_size, dtype=np.float32),
        }
        low_res, scores = self._decoder.run(["low_res_masks", "iou_predictions"], inputs)
        if (
            low_res.ndim != 4
            or low_res.shape[0] != 1
            or low_res.shape[2:] != (MASK_INPUT_SIZE, MASK_INPUT_SIZE)
            or (scores.shape != low_res.shape[:2])
        ):
            raise SamModelError(
                f"SAM decoder {self.decoder_path} returned low_res_masks {low_res.shape} and iou_predictions "
                f"{scores.shape}, expected (1, K, {MASK_INPUT_SIZE}, {MASK_INPUT_SIZE}) and (1, K)"
            )
        return postprocess_masks(low_res, image_size)[0] > 0.0, scores[0].astype(np.float32)

    def _smoke_test_decoder(self) -> None:
        """Run the decoder once on a zero embedding, so that a model that loads but cannot run fails now."""
        image_size = (48, 64)
        coords, codes = prompt_inputs(np.array([[10.0, 10.0]]), np.array([1]), None, image_size)
        try:
            self._run_decoder(np.zeros((1, *ENCODER_OUTPUT[1:]), dtype=np.float32), coords, codes, image_size)
        except SamModelError:
            raise
        except Exception as error:
            raise SamModelError(f"SAM decoder {self.decoder_path} failed on a test prompt: {error}") from error
