"""Which dataset a scene folder looks like, from the files each dataset distributes, to name the right parser
when a folder is read with another one."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

LAYOUTS = {
    "technicolor-data": ("*_undist_*_*.png", "cameras_parameters.txt"),
    "neural-3d-video-data": ("cam[0-9][0-9].mp4", "poses_bounds.npy"),
    "google-immersive-data": ("camera_[0-9][0-9][0-9][0-9].mp4", "models.json"),
}
"""Parser name -> (a frame or video file pattern, the calibration file) of its dataset's folders."""


def matching_parser(folder: Path) -> Optional[str]:
    """The parser whose dataset layout (frames and calibration file) the folder has, if any."""
    if not folder.is_dir():
        return None
    for parser, (frames, calibration) in LAYOUTS.items():
        if (folder / calibration).is_file() and next(folder.glob(frames), None) is not None:
            return parser
    return None


def layout_hint(folder: Path, parser: str) -> str:
    """' (the folder looks like ...: use ns-train <method> <other parser> --data ...)' when the folder has
    another dataset's layout than `parser`'s, else ''."""
    other = matching_parser(folder)
    if other is None or other == parser:
        return ""
    return f" (the folder looks like {other}'s layout: use `ns-train gear-nerf {other} --data {folder}`)"
