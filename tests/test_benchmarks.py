"""The benchmarks' entry point: every subcommand parses, and speed-accuracy's methods give ns-train overrides."""

from __future__ import annotations

import numpy as np
import pytest
import tyro

from benchmarks.__main__ import subcommands
from benchmarks.common import gear_mask_counts
from benchmarks.speed_accuracy import METHODS, method_overrides

NAMES = ("speed-accuracy", "tracking", "tracking-real", "render-speed", "gpu-speed",
         "real-size-costs", "process-accuracy", "footprint", "gear-masks", "plane-kernel")  # fmt: skip


@pytest.mark.parametrize("name", NAMES)
def test_subcommand_help(name: str, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exit_info:
        tyro.cli(subcommands(), args=[name, "--help"])
    assert exit_info.value.code == 0
    assert "usage" in capsys.readouterr().out


def test_speed_accuracy_options() -> None:
    command = tyro.cli(subcommands(), args=["speed-accuracy", "--scenes", "panoptic", "--main-methods", "kplanes",
                                            "--ablations", "--seeds", "1"])  # fmt: skip
    assert command.main_methods == ("kplanes",) and command.ablations == () and command.seeds == 1


def test_method_overrides() -> None:
    for method in METHODS:
        assert all(" " not in arg and "{" not in arg for arg in method_overrides(method))
    assert method_overrides("kplanes") == ["--pipeline.model.num-gears", "1"]
    with pytest.raises(ValueError):
        method_overrides("no-such-method")


def test_gear_mask_counts() -> None:
    levels = np.array([[1, 2], [3, 1]])
    moving = np.array([[True, True], [False, False]])
    assert gear_mask_counts(levels, moving).tolist() == [1, 2, 1, 2]
