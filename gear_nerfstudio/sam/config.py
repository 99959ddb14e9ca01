"""SAM backend configs (Sec 4.2): one per backend, each with the backend as its ``_target``, so that the command
line offers them as choices (``sam-builtin``, ``sam-onnx``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Type, Union

import tyro
from nerfstudio.configs.base_config import InstantiateConfig

from gear_nerfstudio.sam.builtin_backend import BuiltinSamBackend
from gear_nerfstudio.sam.interface import SamBackend
from gear_nerfstudio.sam.onnx_backend import OnnxSamBackend, SamModelError


@dataclass
class BuiltinSamConfig(InstantiateConfig):
    """A stand-in for SAM that needs no weights: colour and texture features and a region-growing decoder (good
    enough for the synthetic scenes and the demo; it is not SAM)."""

    _target: Type = field(default_factory=lambda: BuiltinSamBackend)

    def setup(self, **kwargs) -> SamBackend:
        return self._target()


@dataclass
class OnnxSamConfig(InstantiateConfig):
    """Your own SAM or MobileSAM encoder and prompt decoder exported to ONNX; the files are checked when the
    backend is built, before any training."""

    _target: Type = field(default_factory=lambda: OnnxSamBackend)
    encoder: Optional[Path] = None
    """ONNX image encoder: input (1, 3, 1024, 1024) pre-processed float32, output (1, 256, 64, 64)."""
    decoder: Optional[Path] = None
    """ONNX prompt decoder exported with segment-anything's scripts/export_onnx_model.py."""

    def setup(self, **kwargs) -> SamBackend:
        missing = [name for name in ("encoder", "decoder") if getattr(self, name) is None]
        if missing:
            raise SamModelError(f"the onnx SAM backend needs ONNX files for the {' and '.join(missing)}")
        return self._target(self.encoder, self.decoder)


SamBackendConfig = Union[BuiltinSamConfig, OnnxSamConfig]
SamConfigChoice = tyro.conf.OmitSubcommandPrefixes[  # type: ignore[valid-type]
    tyro.extras.subcommand_type_from_defaults({"sam-builtin": BuiltinSamConfig(), "sam-onnx": OnnxSamConfig()})
]
"""The SAM backend as a choice on the command line: ``sam-builtin`` (the default) or ``sam-onnx``."""
