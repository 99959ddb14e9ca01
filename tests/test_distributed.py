"""Several processes for one chunk (nerfstudio's ``--machine.num-devices``, DistributedDataParallel): what changes the
model outside the averaged gradient step (plane columns claimed and inherited in the forward pass, Sec 4.4; the
gear-assignment updates, Sec 4.3) is the same on every process.

nerfstudio's launcher needs CUDA devices, so two CPU processes are started here with the gloo backend; each builds
the real pipeline and trainer and wraps the model in DDP as nerfstudio's VanillaPipeline does with world_size > 1.
"""

from __future__ import annotations

import copy
import dataclasses
import datetime
import random
from pathlib import Path
from typing import Dict

import numpy as np
import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from nerfstudio.engine.callbacks import TrainingCallbackLocation
from nerfstudio.engine.trainer import TrainerConfig
from torch.nn.parallel import DistributedDataParallel

from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from gear_nerfstudio.fields.gear_field import GearField
from gear_nerfstudio.method_configs.gear_nerf import gear_nerf_small
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene

WORLD_SIZE = 2
STEPS = 7
"""Training iterations 0-6 with epochs of 1 iteration, L = 2, L' = 2 and 8 planned iterations: updates at steps 2
and 4, and the L' rule ends them at step 6."""


def small_field() -> GearField:
    """A GearField with random space-time planes for every gear (so that an inheritance changes them)."""
    torch.manual_seed(0)
    field = GearField(torch.tensor([[-1.0] * 3, [1.0] * 3]), num_frames=10, num_gears=4, feature_dim=8,
                      resolutions=(8, 16), gear_resolution=8, sam_dim=8, sam_head_dim=None)  # fmt: skip
    with torch.no_grad():
        for triple in field.time_planes:
            for plane in triple.planes:
                plane.add_(torch.randn_like(plane))
    return field.train()


def claims(rank: int):
    """Points of one process's batch: gear 1 everywhere, gear 2 on this process's side of the scene (x < 0 on
    process 0, x > 0 on process 1), gear 3 on a few points of it."""
    generator = torch.Generator().manual_seed(rank)
    x = torch.rand(200, 3, generator=generator) * 2 - 1
    levels = torch.ones(200, dtype=torch.long)
    side = x[:, 0] < 0 if rank == 0 else x[:, 0] > 0
    levels[side] = 2
    levels[side & (x[:, 1] > 0.8)] = 3
    return x, levels


def trainer_config(root: Path) -> TrainerConfig:
    config = copy.deepcopy(gear_nerf_small.config)
    config.output_dir, config.experiment_name, config.timestamp = root / "runs", "ddp", "run"
    config.machine.device_type, config.vis = "cpu", "tensorboard"
    config.max_num_iterations = STEPS + 1
    config.steps_per_eval_batch = config.steps_per_eval_image = config.steps_per_eval_all_images = 0
    config.pipeline.datamanager.dataparser = Neural3DVideoDataParserConfig(data=root / "scene", cache_dir=root / "cache")
    config.pipeline.datamanager.sam_cache_dir = root / "sam"
    config.pipeline.datamanager.train_num_rays_per_batch = 64  # small batches: the processes touch other columns
    config.pipeline.gear_updates = dataclasses.replace(
        config.pipeline.gear_updates, iterations_per_epoch=1, epochs_between_updates=2, epochs_after_updates=2,
        views_per_update=2, motion_threshold=0.0, rays_per_set=256, max_points=1024, max_steps=20,
    )  # fmt: skip
    return config


def worker(rank: int, root: Path) -> None:
    """One process: claims of a bare field, then DDP training with gear updates; writes what it ends with."""
    dist.init_process_group(
        "gloo", init_method=f"file://{root / 'rendezvous'}", rank=rank, world_size=WORLD_SIZE,
        timeout=datetime.timedelta(minutes=5),
    )  # fmt: skip
    torch.set_num_threads(1)
    field = small_field()
    field.inherit_new_columns(field.claim_columns(*claims(rank)))
    result: Dict[str, object] = {"field": copy.deepcopy(field.state_dict())}

    config = trainer_config(root)
    seed = config.machine.seed + rank  # as nerfstudio's train_loop: each process draws its own rays
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    if rank:
        dist.barrier()  # the first process writes the frame and SAM caches, the other reads them
    trainer = config.setup(local_rank=rank, world_size=1)
    trainer.setup()
    if not rank:
        dist.barrier()
    pipeline = trainer.pipeline
    pipeline._model = DistributedDataParallel(pipeline._model, find_unused_parameters=True)  # VanillaPipeline's
    batches = []
    next_train = pipeline.datamanager.next_train

    def recorded_next_train(step: int):
        ray_bundle, batch = next_train(step)
        batches.append(batch["indices"].clone())
        return ray_bundle, batch

    pipeline.datamanager.next_train = recorded_next_train
    for step in range(STEPS):  # Trainer.train's loop, without its timers, evaluation and checkpoints
        for callback in trainer.callbacks:
            callback.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
        trainer.train_iteration(step)
        for callback in trainer.callbacks:
            callback.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
    result.update(
        model=pipeline.model.state_dict(),
        optimizers={name: optimizer.state_dict() for name, optimizer in trainer.optimizers.optimizers.items()},
        updates=pipeline.gear_update_state.state_dict(),
        batches=torch.stack(batches),
    )
    torch.save(result, root / f"rank{rank}.pt")
    dist.destroy_process_group()


@pytest.fixture(scope="module")
def ranks(tmp_path_factory):
    """What each of the two processes ends with. The processes are forked (they start with this process's
    imports, a spawn would import torch and nerfstudio again in each)."""
    root = tmp_path_factory.mktemp("ddp")
    write_synthetic_scene(root / "scene", SyntheticSpec(dataset="n3d", width=32, height=24, frames=4, cameras=5))
    mp.start_processes(worker, args=(root,), nprocs=WORLD_SIZE, join=True, start_method="fork")
    return [torch.load(root / f"rank{rank}.pt", weights_only=False) for rank in range(WORLD_SIZE)]


def assert_identical(first, second, where: str = "") -> None:
    """Nested state (dicts, lists, tensors, numbers) bit for bit the same."""
    if isinstance(first, dict):
        assert first.keys() == second.keys(), where
        for key in first:
            assert_identical(first[key], second[key], f"{where}/{key}")
    elif isinstance(first, (list, tuple)):
        assert len(first) == len(second), where
        for index, (a, b) in enumerate(zip(first, second)):
            assert_identical(a, b, f"{where}/{index}")
    elif isinstance(first, torch.Tensor):
        assert torch.equal(first, second), f"{where} differs"
    else:
        assert first == second, where


def test_processes_claim_and_inherit_the_union_of_their_batches_columns(ranks):
    """Each process's batch alone claims other columns (and would inherit other plane columns); together every
    process ends as one process that had both batches."""
    alone = []
    for rank in range(WORLD_SIZE):
        field = small_field()
        field.inherit_new_columns(field.claim_columns(*claims(rank)))
        alone.append(field.state_dict())
    assert not torch.equal(alone[0]["used_columns"], alone[1]["used_columns"])
    assert not torch.equal(alone[0]["time_planes.1.planes.0"], alone[1]["time_planes.1.planes.0"])

    both = small_field()
    points = [claims(rank) for rank in range(WORLD_SIZE)]
    both.inherit_new_columns(
        both.claim_columns(torch.cat([x for x, _ in points]), torch.cat([levels for _, levels in points]))
    )
    for rank in range(WORLD_SIZE):
        assert_identical(ranks[rank]["field"], both.state_dict(), f"field of process {rank}")


def test_ddp_training_with_gear_updates_keeps_every_process_identical(ranks):
    """Different ray batches per process, two gear updates (Eq 10-11) and the L' rule: the model (planes, gear
    function, used columns), the optimizers' state and the updates' record are bit for bit the same."""
    first, second = ranks
    assert not torch.equal(first["batches"], second["batches"])
    assert int(first["updates"]["num_updates"]) == 2 and bool(first["updates"]["finished"])
    used = first["model"]["field.used_columns"]
    assert bool(used[1:].any())  # the updates moved regions up, and training claimed higher gears' columns
    assert first["optimizers"]["gear_field"]["state"]  # the Eq 11 steps ran
    assert_identical(first["model"], second["model"], "model")
    assert_identical(first["optimizers"], second["optimizers"], "optimizers")
    assert_identical(first["updates"], second["updates"], "gear updates")
