"""Where the chunks train: one after another on this machine, or as tasks of a Ray cluster.

Both executors run the same two kinds of work: preparing each camera (frame decoding and SAM encoding, one
task per camera) and training each chunk (one `ns-train` run per chunk), so that they give the same
checkpoints. Chunks exchange no gradients, which is what lets them spread over GPUs and machines; on a
cluster the output folder and the caches (``--cache-dir``, ``--pipeline.datamanager.sam-cache-dir``) must be on
storage that every node sees, and every node needs this package installed.
"""

from __future__ import annotations

from typing import List, Literal, Optional

from gear_nerfstudio.chunks.plan import ChunkError
from gear_nerfstudio.chunks.training import ChunkPlan, prepare_camera, train_chunk

Executor = Literal["local", "ray"]


def run_local(plan: ChunkPlan) -> List[str]:
    """Prepare every camera, then train the chunks in order; returns their config.yml paths."""
    for camera in range(plan.num_cameras):
        prepare_camera(plan.base_config, camera)
    return [train_chunk(run) for run in plan.runs]


def run_ray(plan: ChunkPlan, address: Optional[str]) -> List[str]:
    """The same work as Ray tasks: the cameras' preparations in parallel, then every chunk as a task asking
    for its run's GPUs (``--machine.num-devices``, default 1) when the cluster has GPUs (one CPU otherwise).
    ``address``: a running cluster ("auto" or "host:port"); None starts a Ray instance on this machine."""
    try:
        import ray
    except ImportError as err:
        raise ChunkError("--executor ray needs Ray: pip install 'gear-nerfstudio[ray]'") from err
    started_here = not ray.is_initialized()
    if started_here:
        # A Ray instance started here runs its workers at nice 0: Ray's default (15) lets any other process on the
        # machine starve the chunks' training.
        local = {"include_dashboard": False, "_system_config": {"worker_niceness": 0}}
        options = {"address": address} if address else local
        ray.init(log_to_driver=True, **options)
    try:
        gpus = plan.num_devices if ray.cluster_resources().get("GPU", 0) >= 1 else 0
        prepare = ray.remote(num_cpus=1)(prepare_camera)
        ray.get([prepare.remote(plan.base_config, camera) for camera in range(plan.num_cameras)])
        train = ray.remote(num_cpus=1, num_gpus=gpus)(train_chunk)
        return ray.get([train.remote(run) for run in plan.runs])
    finally:
        if started_here:
            ray.shutdown()


def execute(plan: ChunkPlan, executor: Executor, ray_address: Optional[str] = None) -> List[str]:
    """Train every chunk of the plan with the chosen executor."""
    if executor == "ray":
        return run_ray(plan, ray_address)
    return run_local(plan)
