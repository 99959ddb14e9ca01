"""On-disk cache of SAM encoder features, the targets S(r) of L_SAM (Eq 9).

The encoder runs once per training image (camera, frame) and its embedding is stored as one file:

    b"GEARSAM1" | uint32 header length | JSON header (space-padded to a 64-byte boundary) | float16 data

The header names the backend, its `settings` and the source image (resolved path, byte size, mtime);
a file whose header does not match is recomputed. The data is stored channels-last, (G, G, C), so that
the C features of one cell are contiguous: a batch reads only the 4 cells around each of its pixels
through a memory map, never whole feature maps.
"""

from __future__ import annotations

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

from gear_nerfstudio.sam.interface import Embedding, SamBackend, cells_per_pixel

MAGIC = b"GEARSAM1"
ALIGNMENT = 64


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
        self._open: "OrderedDict[Path, Tuple[np.memmap, Tuple[int, int]]]" = OrderedDict()

    def path_for(self, image_path: Path) -> Path:
        """Cache file of an image for this backend and its settings."""
        key = json.dumps([str(Path(image_path).resolve()), self.backend.name, self.settings], sort_keys=True)
        return self.cache_dir / self.backend.name / f"{hashlib.sha1(key.encode()).hexdigest()[:24]}.samf"

    def _expected(self, image_path: Path) -> Dict[str, Any]:
        return {"backend": self.backend.name, "settings": self.settings, "source": _source(image_path)}

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
        data = np.ascontiguousarray(embedding.features.transpose(1, 2, 0), dtype=np.float16)
        if not np.isfinite(data).all():
            raise ValueError(f"SAM backend {self.backend.name!r}: features of {image_path} do not fit float16")
        header = {
            **self._expected(image_path),
            "image_size": list(embedding.image_size),
            "shape": [grid, grid, channels],
            "dtype": "float16",
            "layout": "grid_y, grid_x, channel",
        }
        text = json.dumps(header, sort_keys=True).encode()
        length = len(text) + (-(len(MAGIC) + 4 + len(text)) % ALIGNMENT)
        target = self.path_for(image_path)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f"{target.name}.{os.getpid()}.tmp")
        try:
            with open(tmp, "wb") as handle:
                handle.write(MAGIC + struct.pack("<I", length) + text.ljust(length))
                handle.write(data.tobytes())
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        self._open.pop(image_path, None)

    def precompute(self, image_paths: Optional[Sequence[Path]] = None, description: str = "") -> int:
        """Encode every image (default: `image_paths`) whose file is missing or stale; returns how many."""
        paths = self.image_paths if image_paths is None else [Path(p).resolve() for p in image_paths]
        missing = [p for p in paths if self._valid_header(p) is None]
        if missing:
            columns = (TextColumn("[bold blue]{task.description}"), BarColumn(), MofNCompleteColumn())
            with Progress(*columns, TimeRemainingColumn()) as progress:
                task = progress.add_task(description or f"SAM features ({self.backend.name})", total=len(missing))
                for path in missing:
                    self.compute(path)
                    progress.advance(task)
        return len(missing)

    def _table(self, image_path: Path) -> Tuple[np.memmap, Tuple[int, int]]:
        """Read-only memory map (G, G, C) float16 of an image's features and the image size (H, W)."""
        if image_path in self._open:
            self._open.move_to_end(image_path)
            return self._open[image_path]
        read = self._valid_header(image_path)
        if read is None:
            self.compute(image_path)
            read = self._valid_header(image_path)
            assert read is not None
        header, offset = read
        shape = tuple(header["shape"])
        table = np.memmap(self.path_for(image_path), dtype=np.float16, mode="r", offset=offset, shape=shape)
        entry = (table, (int(header["image_size"][0]), int(header["image_size"][1])))
        self._open[image_path] = entry
        if len(self._open) > self.max_open:
            self._open.popitem(last=False)
        return entry

    def embedding(self, image_path: Path) -> Embedding:
        """The whole embedding (C, G, G) of an image (float32 holding the float16 values), computed if missing."""
        table, image_size = self._table(Path(image_path).resolve())
        features = np.ascontiguousarray(table.transpose(2, 0, 1), dtype=np.float32)
        return Embedding(features=features, image_size=image_size)

    def features_at(
        self,
        image_indices: Int[Tensor, "num_rays"],
        pixels: Float[Tensor, "num_rays 2"],
        device: Union[torch.device, str] = "cpu",
    ) -> Float[Tensor, "num_rays channels"]:
        """Bilinear features at pixel coordinates (x, y) of images `image_paths[image_indices]` (Eq 9 targets).

        Same geometry and interpolation as `sam.interface.sample_features` (cell centres at k + 0.5,
        coordinates clamped to the grid). Only the 4 cells around each pixel are read; they travel to
        `device` as float16 and are interpolated there.
        """
        indices = image_indices.detach().cpu().numpy()
        xy = pixels.detach().cpu().double().numpy()
        corners = np.empty((4, len(indices), self.backend.embedding_dim), dtype=np.float16)
        weights = np.empty((4, len(indices)), dtype=np.float32)
        for image_index in np.unique(indices):
            rows = np.nonzero(indices == image_index)[0]
            table, image_size = self._table(self.image_paths[image_index])
            grid = table.shape[0]
            cells = np.clip(xy[rows] * cells_per_pixel(image_size, grid) - 0.5, 0, grid - 1)
            low = np.floor(cells).astype(np.int64)
            (x0, y0), (x1, y1) = low.T, np.minimum(low + 1, grid - 1).T
            fx, fy = (cells - low).T
            cell_indices = np.stack([y0 * grid + x0, y0 * grid + x1, y1 * grid + x0, y1 * grid + x1])
            corners[:, rows] = np.take(table.reshape(grid * grid, -1), cell_indices, axis=0)
            weights[:, rows] = np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
        corners_on_device = torch.from_numpy(corners).to(device).float()
        return torch.einsum("kn,knc->nc", torch.from_numpy(weights).to(device), corners_on_device)
