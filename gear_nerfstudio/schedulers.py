"""nerfstudio's cosine-decay schedule with learning rates kept as Python floats.

nerfstudio 1.1.5 computes learning-rate factors with numpy, so optimizer and scheduler states in its
checkpoints hold numpy scalars. torch >= 2.6 loads checkpoints with `weights_only=True` (as
`ns-eval`, `ns-render` and `ns-viewer` do through nerfstudio's `eval_setup`) and refuses those
scalars (nerfstudio issue #3683). Returning Python floats keeps every checkpoint loadable.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

from nerfstudio.engine.schedulers import CosineDecayScheduler, CosineDecaySchedulerConfig
from torch.optim import Optimizer
from torch.optim.lr_scheduler import LambdaLR, LRScheduler


@dataclass
class FloatCosineDecaySchedulerConfig(CosineDecaySchedulerConfig):
    """Cosine decay after a linear warmup (nerfstudio's), storing Python floats."""

    _target: Type = field(default_factory=lambda: FloatCosineDecayScheduler)


class FloatCosineDecayScheduler(CosineDecayScheduler):
    config: FloatCosineDecaySchedulerConfig

    def get_scheduler(self, optimizer: Optimizer, lr_init: float) -> LRScheduler:
        factor = super().get_scheduler(optimizer, lr_init).lr_lambdas[0]
        return LambdaLR(optimizer, lr_lambda=lambda step: float(factor(step)))
