"""``python -m benchmarks <subcommand> [options]``: one entry point for every benchmark (tyro subcommands)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Union

import tyro
from typing_extensions import Annotated

from benchmarks.common import TRAIN_CHILD, train_child


def subcommands():
    """The subcommands, one per benchmark module (imported here: each pulls in torch and nerfstudio)."""
    from benchmarks.footprint import Footprint
    from benchmarks.gear_masks import GearMasks
    from benchmarks.gpu_speed import GpuSpeed
    from benchmarks.plane_kernel import PlaneKernel
    from benchmarks.process_accuracy import ProcessAccuracy
    from benchmarks.real_size_costs import RealSizeCosts
    from benchmarks.render_speed import RenderSpeed
    from benchmarks.speed_accuracy import SpeedAccuracy
    from benchmarks.tracking import Tracking
    from benchmarks.tracking_real import TrackingReal

    named = {
        "speed-accuracy": SpeedAccuracy, "tracking": Tracking,
        "tracking-real": TrackingReal, "render-speed": RenderSpeed, "gpu-speed": GpuSpeed,
        "real-size-costs": RealSizeCosts, "process-accuracy": ProcessAccuracy, "footprint": Footprint,
        "gear-masks": GearMasks, "plane-kernel": PlaneKernel,
    }  # fmt: skip
    return Union[tuple(Annotated[kind, tyro.conf.subcommand(name=n)] for n, kind in named.items())]  # type: ignore


def entrypoint() -> None:
    """Run the chosen benchmark (or, as ``_train``, the timed ns-train child of ``common.timed_train``)."""
    if len(sys.argv) > 2 and sys.argv[1] == TRAIN_CHILD:
        return train_child(Path(sys.argv[2]), sys.argv[3:])
    tyro.cli(subcommands()).main()


if __name__ == "__main__":
    entrypoint()
