"""Which SAM backend to use (Sec 4.2); the backends are imported only when one is built."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Optional

if TYPE_CHECKING:
    from gear_nerfstudio.sam.interface import SamBackend


@dataclass
class SamConfig:
    """SAM encoder and prompt decoder: the weight-free built-in stand-in, or the user's SAM / MobileSAM
    exported to ONNX."""

    backend: Literal["builtin", "onnx"] = "builtin"
    """'builtin': a stand-in for SAM that needs no weights (synthetic scenes, demo); 'onnx': SAM's
    encoder and decoder from ONNX files."""
    encoder: Optional[Path] = None
    """ONNX image encoder: input (1, 3, 1024, 1024) pre-processed float32, output (1, 256, 64, 64)."""
    decoder: Optional[Path] = None
    """ONNX prompt decoder exported with segment-anything's scripts/export_onnx_model.py."""

    def setup(self) -> "SamBackend":
        """Build the backend; the ONNX files are checked here, before any training."""
        if self.backend == "builtin":
            from gear_nerfstudio.sam.builtin_backend import BuiltinSamBackend

            return BuiltinSamBackend()
        if self.backend == "onnx":
            from gear_nerfstudio.sam.onnx_backend import OnnxSamBackend, SamModelError

            missing = [name for name in ("encoder", "decoder") if getattr(self, name) is None]
            if missing:
                raise SamModelError(f"the onnx SAM backend needs ONNX files for the {' and '.join(missing)}")
            return OnnxSamBackend(self.encoder, self.decoder)
        raise ValueError(f"unknown SAM backend {self.backend!r}; choose 'builtin' or 'onnx'")
