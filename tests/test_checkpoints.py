"""Checkpoints of the presets load with torch's safe loader (weights_only=True), as ns-eval loads them."""

from __future__ import annotations

import io

import torch

from gear_nerfstudio.method_configs.gear_nerf import gear_nerf_small


def test_scheduler_and_optimizer_state_load_with_weights_only():
    parameter = torch.nn.Parameter(torch.zeros(3))
    optimizer_config = gear_nerf_small.config.optimizers["fields"]
    optimizer = optimizer_config["optimizer"].setup(params=[parameter])
    scheduler = optimizer_config["scheduler"].setup().get_scheduler(optimizer, optimizer_config["optimizer"].lr)
    warmup = optimizer_config["scheduler"].warm_up_end
    for _ in range(warmup + 5):  # past the warmup, where the cosine factor is computed
        parameter.grad = torch.ones(3)
        optimizer.step()
        scheduler.step()
    buffer = io.BytesIO()
    torch.save({"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict()}, buffer)
    buffer.seek(0)
    loaded = torch.load(buffer, weights_only=True)
    lr = loaded["optimizer"]["param_groups"][0]["lr"]
    assert isinstance(lr, float) and 0 < lr < optimizer_config["optimizer"].lr
