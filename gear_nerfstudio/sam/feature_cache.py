"""On-disk cache of SAM encoder features, the targets S(r) of L_SAM (Eq 9).

The encoder runs once per image (camera, frame) and its embedding (C, G, G) is stored as one file:

    b"GEARSAM2" | uint32 header length | JSON header (space-padded to a 64-byte boundary)
        | decoder: float32 (k + 1, C) | codes: uint16 (G, G, k)

The embedding is compressed per image: its cells' features are projected onto their k leading principal
components (the fewest that leave at most `PCA_RESIDUAL` of the features' energy unexplained, at most
`MAX_COMPONENTS`), and each component's coefficients are quantised to 16 bits over their own range
[low_j, high_j]. The decoder folds the basis, the quantisation steps and the mean into one affine map:

    features(cell) = codes(cell) @ decoder[:k] + decoder[k]

with decoder[j] = step_j * v_j (v_j the j-th principal direction, step_j = (high_j - low_j) / 65535) and
decoder[k] = mean + sum_j low_j * v_j. The map is affine and bilinear weights sum to 1, so a batch
interpolates the codes of the 4 cells around each pixel and decodes afterwards (on the batch's device).

The header names the backend, its `settings`, the source image (resolved path, byte size, mtime) and
the codes' type ("uint16"), plus the grid G, the channels C, the components k and `pca_residual` (the
energy share the dropped components held); a file whose header does not match, or that is not in this
format (another magic, such as the float16 files of b"GEARSAM1"), is recomputed. The codes are
channels-last so that the k codes of one cell are contiguous: a batch reads only the 4 cells around each
of its pixels through a memory map, never whole feature maps. At G = 64 and C = 256 a file holds at most
64 x 64 x 48 x 2 bytes of codes and 49 x 256 x 4 bytes of decoder, at least 4.7x less than the embedding
in float16. Codes of 8 bits would halve that, but their error (about 0.3 % RMS) already changes the
built-in decoder's masks.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import struct
from collections import OrderedDict
from pathlib import Path
from typing import Any, Dict, Optional, Sequence, Tuple, Union

import numpy as np
import torch
from jaxtyping import Float, Int
from PIL import Image
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from torch import Tensor

from gear_nerfstudio.parallel import run_parallel
from gear_nerfstudio.sam.interface import Embedding, SamBackend, cells_per_pixel

MAGIC = b"GEARSAM2"
ALIGNMENT = 64
MAX_COMPONENTS = 48
PCA_RESIDUAL = 1e-6  # energy share the dropped components may hold: an RMS error of at most 0.1 % of |S|
LEVELS = 65535  # quantisation steps of a uint16 code


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/gear-nerfstudio/sam``, or ``~/.cache/gear-nerfstudio/sam``."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "gear-nerfstudio" / "sam"


def _source(image_path: Path) -> Dict[str, Any]:
    stat = image_path.stat()
    return {"path": str(image_path), "bytes": stat.st_size, "mtime_ns": stat.st_mtime_ns}


def read_header(path: Path) -> Optional[Tuple[Dict[str, Any], int]]:
    """The header of a cache file and the byte offset of its data; None if it is not one."""
    try:
        with open(path, "rb") as handle:
            start = handle.read(len(MAGIC) + 4)
            if len(start) < len(MAGIC) + 4 or start[: len(MAGIC)] != MAGIC:
                return None
            (length,) = struct.unpack("<I", start[len(MAGIC) :])
            header = json.loads(handle.read(length).decode())
    except (OSError, ValueError):
        return None
    return header, len(MAGIC) + 4 + length


def compress(features: np.ndarray) -> Tuple[np.ndarray, np.ndarray, float]:
    """Decoder (k + 1, C) float32, codes (G, G, k) uint16 and PCA residual of an embedding (C, G, G).

    Principal components of the G * G cells' features (centred), the fewest that leave at most
    `PCA_RESIDUAL` of the energy sum |S|^2 unexplained (at most `MAX_COMPONENTS`, at least one), each
    quantised to 16 bits over its own range (see the module docstring for the decoder).
    """
    channels, grid = features.shape[0], features.shape[-1]
    cells = features.reshape(channels, grid * grid).T.astype(np.float64)
    mean = cells.mean(axis=0)
    centred = cells - mean
    variances, directions = np.linalg.eigh(centred.T @ centred)
    variances, directions = np.maximum(variances[::-1], 0.0), directions[:, ::-1]
    energy = max(float(np.square(cells).sum()), np.finfo(np.float64).tiny)
    left = np.concatenate([np.cumsum(variances[::-1])[::-1], [0.0]])  # left[k]: energy beyond k components
    count = int(np.clip(np.argmax(left <= PCA_RESIDUAL * energy), 1, min(MAX_COMPONENTS, channels)))
    basis = np.ascontiguousarray(directions[:, :count])  # (C, k); a strided one would miss BLAS
    coefficients = centred @ basis
    low, high = coefficients.min(axis=0), coefficients.max(axis=0)
    step = np.where(high > low, (high - low) / LEVELS, 1.0)
    codes = np.clip(np.rint((coefficients - low) / step), 0, LEVELS).astype(np.uint16)
    decoder = np.concatenate([step[:, None] * basis.T, (mean + basis @ low)[None]]).astype(np.float32)
    return decoder, np.ascontiguousarray(codes.reshape(grid, grid, count)), float(left[count] / energy)


def decompress(decoder: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """Features (..., C) float32 of codes (..., k): codes @ decoder[:k] + decoder[k]."""
    count = codes.shape[-1]
    return codes.astype(np.float32) @ decoder[:count] + decoder[count]


class SamFeatureCache:
    """SAM encoder features of images, computed once and read from disk per batch.

    Args:
        backend: encodes images (`SamBackend.encode`).
        cache_dir: where the files go; default `default_cache_dir()`.
        image_paths: the images that `features_at` indexes (a dataset's `image_filenames`).
        max_open: memory maps kept open between batches (each holds a file descriptor).
    """

    def __init__(
        self,
        backend: SamBackend,
        cache_dir: Optional[Path] = None,
        image_paths: Sequence[Path] = (),
        max_open: int = 256,
    ):
        self.backend = backend
        self.cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
        self.image_paths = [Path(p).resolve() for p in image_paths]
        self.max_open = max_open
        # JSON round trip so that settings compare equal to what a header holds (tuples, paths).
        self.settings = json.loads(json.dumps(backend.settings, sort_keys=True, default=str))
        self._open: "OrderedDict[Path, Tuple[np.memmap, np.ndarray, Tuple[int, int]]]" = OrderedDict()

    def path_for(self, image_path: Path) -> Path:
        """Cache file of an image for this backend and its settings."""
        key = json.dumps([str(Path(image_path).resolve()), self.backend.name, self.settings], sort_keys=True)
        return self.cache_dir / self.backend.name / f"{hashlib.sha1(key.encode()).hexdigest()[:24]}.samf"

    def _expected(self, image_path: Path) -> Dict[str, Any]:
        source = _source(image_path)
        return {"backend": self.backend.name, "settings": self.settings, "source": source, "codes": "uint16"}

    def _valid_header(self, image_path: Path) -> Optional[Tuple[Dict[str, Any], int]]:
        read = read_header(self.path_for(image_path))
        if read is None:
            return None
        header, offset = read
        if any(header.get(key) != value for key, value in self._expected(image_path).items()):
            return None
        return header, offset

    def compute(self, image_path: Path) -> None:
        """Encode one image and write its file atomically (temporary file, then rename)."""
        image_path = Path(image_path).resolve()
        with Image.open(image_path) as handle:
            rgb = np.array(handle.convert("RGB"))
        embedding = self.backend.encode(rgb)
        channels, grid = embedding.features.shape[0], embedding.grid_size
        if embedding.features.shape != (self.backend.embedding_dim, grid, grid):
            raise ValueError(
                f"SAM backend {self.backend.name!r} returned features of shape {embedding.features.shape} for "
                f"{image_path}; expected ({self.backend.embedding_dim}, G, G)"
            )
        if not np.isfinite(embedding.features).all():
            raise ValueError(f"SAM backend {self.backend.name!r}: features of {image_path} are not finite")
        decoder, codes, residual = compress(embedding.features)
        header = {
            **self._expected(image_path),
            "image_size": list(embedding.image_size),
            "grid": grid,
            "channels": channels,
            "components": codes.shape[-1],
            "pca_residual": residual,
        }
        text = json.dumps(header, sort_keys=True).encode()
        length = len(text) + (-(len(MAGIC) + 4 + len(text)) % ALIGNMENT)
        target = self.path_for(image_path)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f"{target.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "wb") as handle:
                handle.write(MAGIC + struct.pack("<I", length) + text.ljust(length))
                handle.write(decoder.tobytes())
                handle.write(codes.tobytes())
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        self._open.pop(image_path, None)

    def precompute(self, image_paths: Optional[Sequence[Path]] = None, description: str = "") -> int:
        """Encode every image (default: `image_paths`) whose file is missing or stale, `backend.parallel_encodes`
        at a time; returns how many."""
        paths = self.image_paths if image_paths is None else [Path(p).resolve() for p in image_paths]
        missing = [p for p in paths if self._valid_header(p) is None]
        if missing:
            columns = (TextColumn("[bold blue]{task.description}"), BarColumn(), MofNCompleteColumn())
            with Progress(*columns, TimeRemainingColumn()) as progress:
                task = progress.add_task(description or f"SAM features ({self.backend.name})", total=len(missing))
                jobs = [functools.partial(self.compute, path) for path in missing]
                run_parallel(jobs, self.backend.parallel_encodes, lambda: progress.advance(task))
        return len(missing)

    def _table(self, image_path: Path) -> Tuple[np.memmap, np.ndarray, Tuple[int, int]]:
        """Read-only memory map of an image's codes (G, G, k), its decoder (k + 1, C) and the image size (H, W)."""
        if image_path in self._open:
            self._open.move_to_end(image_path)
            return self._open[image_path]
        read = self._valid_header(image_path)
        if read is None:
            self.compute(image_path)
            read = self._valid_header(image_path)
            assert read is not None
        header, offset = read
        file, grid, count = self.path_for(image_path), header["grid"], header["components"]
        decoder = np.fromfile(file, dtype=np.float32, count=(count + 1) * header["channels"], offset=offset)
        decoder = decoder.reshape(count + 1, header["channels"])
        codes = np.memmap(file, dtype=np.uint16, mode="r", offset=offset + decoder.nbytes, shape=(grid, grid, count))
        entry = (codes, decoder, (int(header["image_size"][0]), int(header["image_size"][1])))
        self._open[image_path] = entry
        if len(self._open) > self.max_open:
            self._open.popitem(last=False)
        return entry

    def embedding(self, image_path: Path) -> Embedding:
        """The whole embedding (C, G, G) of an image, decoded to float32, computed if missing."""
        codes, decoder, image_size = self._table(Path(image_path).resolve())
        features = np.ascontiguousarray(decompress(decoder, codes).transpose(2, 0, 1))
        return Embedding(features=features, image_size=image_size)

    def features_at(
        self,
        image_indices: Int[Tensor, "num_rays"],
        pixels: Float[Tensor, "num_rays 2"],
        device: Union[torch.device, str] = "cpu",
    ) -> Float[Tensor, "num_rays channels"]:
        """Bilinear features at pixel coordinates (x, y) of images `image_paths[image_indices]` (Eq 9 targets).

        Same geometry and interpolation as `sam.interface.sample_features` (cell centres at k + 0.5,
        coordinates clamped to the grid). Only the codes of the 4 cells around each pixel are read; they
        travel to `device` (as float32, exact for uint16) with the images' decoders, and are interpolated and
        decoded there
        (interpolating the codes first is exact: the decoder is affine and the weights sum to 1).
        """
        indices = image_indices.detach().cpu().numpy()
        xy = pixels.detach().cpu().double().numpy()
        images, slots = np.unique(indices, return_inverse=True)
        tables = [self._table(self.image_paths[image_index]) for image_index in images]
        width = max(codes.shape[-1] for codes, _, _ in tables)  # images may keep different numbers of components
        # Each ray's place among its image's rays: the rays of one image are decoded together (one batched matmul).
        order = np.argsort(slots, kind="stable")
        counts = np.bincount(slots, minlength=len(images))
        places = np.empty(len(indices), dtype=np.int64)
        places[order] = np.arange(len(indices)) - np.repeat(np.cumsum(counts) - counts, counts)
        corners = np.zeros((4, len(indices), width), dtype=np.float32)
        weights = np.empty((4, len(indices)), dtype=np.float32)
        decoders = np.zeros((len(images), width + 1, self.backend.embedding_dim), dtype=np.float32)
        for slot, (codes, decoder, image_size) in enumerate(tables):
            rows = np.nonzero(slots == slot)[0]
            grid, components = codes.shape[0], codes.shape[-1]
            cells = np.clip(xy[rows] * cells_per_pixel(image_size, grid) - 0.5, 0, grid - 1)
            low = np.floor(cells).astype(np.int64)
            (x0, y0), (x1, y1) = low.T, np.minimum(low + 1, grid - 1).T
            fx, fy = (cells - low).T
            cell_indices = np.stack([y0 * grid + x0, y0 * grid + x1, y1 * grid + x0, y1 * grid + x1])
            corners[:, rows, :components] = np.take(codes.reshape(grid * grid, -1), cell_indices, axis=0)
            weights[:, rows] = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
            decoders[slot, :components], decoders[slot, width] = decoder[:components], decoder[components]
        corners_on_device = torch.from_numpy(corners).to(device)
        codes = torch.einsum("kn,knj->nj", torch.from_numpy(weights).to(device), corners_on_device)
        slots_on_device, places_on_device = torch.from_numpy(slots).to(device), torch.from_numpy(places).to(device)
        grouped = codes.new_zeros((len(images), int(counts.max()), width))
        grouped[slots_on_device, places_on_device] = codes
        decoders_on_device = torch.from_numpy(decoders).to(device)
        decoded = torch.baddbmm(decoders_on_device[:, width:], grouped, decoders_on_device[:, :width])
        return decoded[slots_on_device, places_on_device]
