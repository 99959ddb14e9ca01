"""ns-train's configuration for the gear-nerf methods: nerfstudio's ``TrainerConfig`` plus what a user meets before
training starts.

- The input is checked before anything is printed or written: ns-train calls ``print_to_terminal`` first with the
  final options, so it reads the data (calibration, frame window, frame cache, damaged frames), builds the SAM
  backend (model files) and checks the gear-update plan. Bad input then stops with one line
  (``gear_nerfstudio.errors``), not after the 220-line config and with no run folder left behind.
- The run is named after the scene folder instead of nerfstudio's "unnamed" (nerfstudio takes the name from
  ``--pipeline.datamanager.data``, which the dataset subcommands' ``--data`` does not set).
- Options that nerfstudio declares but this method does not use are hidden from ``--help``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Optional

import tyro
from nerfstudio.engine.trainer import TrainerConfig

from gear_nerfstudio.gears.schedule import no_updates_error, planned_updates
from gear_nerfstudio.pipeline import check_sam_dim


@dataclass
class GearTrainerConfig(TrainerConfig):
    """TrainerConfig that checks the input first and names the run after its scene."""

    prompt: tyro.conf.Suppress[Optional[str]] = None
    """Not used by Gear-NeRF (a text prompt for language-field methods)."""

    def print_to_terminal(self) -> None:
        """Check the input (the first thing ns-train does with the final options), then print the config."""
        self.check_input()
        super().print_to_terminal()

    def check_input(self) -> None:
        """Read the data of both splits, build the SAM backend and, for a new run, check that a gear update is
        planned; raises an ``InputError`` naming the file or option."""
        pipeline = self.pipeline
        dataparser = pipeline.datamanager.dataparser
        if pipeline.datamanager.data is not None:
            dataparser.data = pipeline.datamanager.data
        parser = dataparser.setup()
        for split in ("train", "test"):
            parser.get_dataparser_outputs(split)
        check_sam_dim(pipeline, pipeline.sam.setup())
        updates = pipeline.gear_updates
        new_run = self.load_dir is None and self.load_checkpoint is None
        if updates.enabled and pipeline.model.num_gears > 1 and new_run:
            last_step = self.max_num_iterations - 1
            if not planned_updates(updates, 0, last_step):
                raise no_updates_error(updates, 0, last_step)

    def set_experiment_name(self) -> None:
        """Name the run after the scene folder (``--data`` of the dataset subcommand or of ns-train)."""
        if self.experiment_name is None:
            data = self.pipeline.datamanager.data or self.pipeline.datamanager.dataparser.data
            self.experiment_name = Path(data).resolve().name or "unnamed"
