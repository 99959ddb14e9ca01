"""`ns-gear-synthetic`: write a synthetic dynamic scene with ground truth in a dataset's format."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal

import tyro

from gear_nerfstudio.tools.synthetic.scene import MotionKind
from gear_nerfstudio.tools.synthetic.writers import SyntheticSpec, write_synthetic_scene


@dataclasses.dataclass
class SyntheticCommand:
    """Render a small deterministic scene (static background, a static and moving spheres) from a rig."""

    output: Path
    """Scene folder to write (with dataset 'all': one sub-folder per format)."""
    dataset: Literal["technicolor", "n3d", "immersive", "all"] = "all"
    width: int = 40
    height: int = 30
    frames: int = 4
    cameras: int = 6
    """Number of cameras of the N3D and Immersive rigs."""
    rows: int = 4
    """Technicolor rig rows."""
    cols: int = 4
    """Technicolor rig columns."""
    motion: MotionKind = "mixed"

    def main(self) -> None:
        formats = ["technicolor", "n3d", "immersive"] if self.dataset == "all" else [self.dataset]
        for name in formats:
            folder = self.output / name if self.dataset == "all" else self.output
            spec = SyntheticSpec(
                dataset=name,
                width=self.width,
                height=self.height,
                frames=self.frames,
                cameras=self.cameras,
                rows=self.rows,
                cols=self.cols,
                motion=self.motion,
            )
            write_synthetic_scene(folder, spec)
            print(f"wrote {name} scene to {folder}")


def entrypoint() -> None:
    tyro.cli(SyntheticCommand).main()


if __name__ == "__main__":
    entrypoint()
