"""Warnings of nerfstudio and torch that a user of this plugin cannot act on, silenced where they arise.

Each filter names the start of the message and its category (and, for warnings raised while the plugin runs,
the module that warns), so every other warning still shows. nerfstudio's own commands import nerfstudio, and
print its import-time deprecations, before they import any plugin: ``ns-gear-demo`` hands those commands the
same filters as ``PYTHONWARNINGS`` (``pythonwarnings``).
"""

from __future__ import annotations

import re
import warnings
from typing import Optional, Tuple, Type

DEPENDENCY_WARNINGS: Tuple[Tuple[str, Type[Warning], Optional[str]], ...] = (
    # nerfstudio's modules, when imported, use torch APIs that torch deprecates.
    ("`torch.jit.script` is deprecated", FutureWarning, None),
    ("`torch.cuda.amp.custom_fwd(args...)` is deprecated", FutureWarning, None),
    ("`torch.cuda.amp.custom_bwd(args...)` is deprecated", FutureWarning, None),
    # nerfstudio's Cameras index with a list of tensors, which torch deprecates; every ray generation warns.
    ("Using a non-tuple sequence for multidimensional indexing", UserWarning, "nerfstudio.cameras.cameras"),
    # nerfstudio's datamanager starts 4 image-loading workers per GPU whatever the CPU count.
    ("This DataLoader will create", UserWarning, "torch.utils.data.dataloader"),
    # nerfstudio's trainer builds its (disabled on the CPU) grad scaler with the deprecated torch.cuda.amp API.
    ("`torch.cuda.amp.GradScaler(args...)` is deprecated", FutureWarning, "nerfstudio.engine.trainer"),
    # nerfstudio's viewmatrix (ns-render spiral) calls torch.cross without its dim argument.
    ("Using torch.cross without specifying the dim arg is deprecated", UserWarning, "nerfstudio.cameras.camera_utils"),
    # nerfstudio's pose interpolation (ns-render interpolate, ns-gear-path through-cameras) re-wraps tensors.
    ("To copy construct from a tensor", UserWarning, "nerfstudio.cameras.camera_utils"),
    # nerfstudio's writer logs the loss dictionary's tensors, which carry gradients, as floats.
    ("Converting a tensor with requires_grad=True to a scalar", UserWarning, "nerfstudio.utils.writer"),
)
"""(start of the message, category, module or None) of each silenced warning."""


def silence_dependency_warnings() -> None:
    """Install a filter for each of ``DEPENDENCY_WARNINGS``."""
    for message, category, module in DEPENDENCY_WARNINGS:
        pattern = re.escape(module) + r"\Z" if module else ""
        warnings.filterwarnings("ignore", message=re.escape(message), category=category, module=pattern)


def pythonwarnings() -> str:
    """``DEPENDENCY_WARNINGS`` as a PYTHONWARNINGS value, for commands that import nerfstudio before the plugin."""
    return ",".join(
        f"ignore:{message}:{category.__name__}:{module or ''}" for message, category, module in DEPENDENCY_WARNINGS
    )
