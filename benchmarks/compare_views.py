"""Held-out views of several benchmark runs side by side: the pictures beside the quality tables.

Every ``speed_accuracy.py`` run folder holds ``held_out_<frame>_{truth,render,gear}.png`` for the held-out frames of
its last checkpoint. This tiles them: one row per frame; the ground truth of the first run, then each run's render,
then the gear map of each run given with ``--gear-maps``; ``--crop`` keeps one box of each (the people).

    .venv/bin/python benchmarks/compare_views.py benchmarks/results/real_capture_budget_panoptic.png \\
        Gear-NeRF=outputs/sa2/runs/panoptic/gear-nerf-small/gear-nerf-seed42 \\
        "lr 0.01=outputs/sa12/runs/panoptic/gear-nerf-small/lr-0.01-seed42" --gear-maps Gear-NeRF
"""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Sequence, Tuple

import tyro
from PIL import Image, ImageDraw


def contact_sheet(labels: Sequence[str], rows: Sequence[Sequence[Image.Image]]) -> Image.Image:
    """Tiles of equal size in rows, under a line of column labels."""
    width, height = rows[0][0].size
    sheet = Image.new("RGB", (width * len(labels), 14 + height * len(rows)), "white")
    draw = ImageDraw.Draw(sheet)
    for c, label in enumerate(labels):
        draw.text((c * width + 4, 1), label, fill="black")
    for r, row in enumerate(rows):
        for c, tile in enumerate(row):
            sheet.paste(tile, (c * width, 14 + r * height))
    return sheet


def held_out_stems(run: Path) -> List[str]:
    """The ``held_out_<frame>`` names of the held-out frames a ``speed_accuracy.py`` run folder holds."""
    stems = sorted({f.name.rsplit("_", 1)[0] for f in run.glob("held_out_*_truth.png")})
    if not stems:
        raise SystemExit(f"error: {run} has no held_out_*_truth.png (a speed_accuracy.py run folder has them)")
    return stems


def main(
    output: tyro.conf.Positional[Path],
    runs: tyro.conf.Positional[Tuple[str, ...]],
    gear_maps: Tuple[str, ...] = (),
    crop: Optional[Tuple[int, int, int, int]] = None,
) -> None:
    """Write the contact sheet of ``runs`` (``label=run folder``, the first one's ground truth) to ``output``.

    ``--crop left top right bottom``: only that box of every view (pixels of the held-out view), enlarged twice.
    """
    folders = dict(run.split("=", 1) for run in runs)
    first = Path(next(iter(folders.values())))
    stems = held_out_stems(first)
    columns: List[Tuple[str, Path, str]] = [("ground truth", first, "truth")]
    columns += [(label, Path(folder), "render") for label, folder in folders.items()]
    columns += [(f"{label} gear map", Path(folders[label]), "gear") for label in gear_maps]
    rows = [[Image.open(folder / f"{stem}_{kind}.png") for _, folder, kind in columns] for stem in stems]
    if crop is not None:
        size = (2 * (crop[2] - crop[0]), 2 * (crop[3] - crop[1]))
        rows = [[tile.crop(crop).resize(size, Image.NEAREST) for tile in row] for row in rows]
    contact_sheet([label for label, _, _ in columns], rows).save(output)
    print(output)


if __name__ == "__main__":
    tyro.cli(main)
