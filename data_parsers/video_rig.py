"""Multi-view parsers whose cameras are video files, one per camera, all of the same length."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Sequence, Tuple

from gear_nerfstudio.data.errors import DatasetError
from gear_nerfstudio.data.frame_cache import VideoInfo, cache_video_frames, video_info
from gear_nerfstudio.data_parsers.multiview import MultiViewVideoDataParser, ParsedRig


class VideoRigDataParser(MultiViewVideoDataParser):
    """A rig of one video per camera; `read_rig` calls `open_videos` with the videos in camera order."""

    _videos: List[Path]

    def open_videos(self, folder: Path, videos: Sequence[Path]) -> List[VideoInfo]:
        """Frame count and size of each camera's video; an error naming the folder when the lengths differ."""
        infos = [video_info(v, self.config.cache_dir) for v in videos]
        lengths = {v.name: info.num_frames for v, info in zip(videos, infos)}
        if len(set(lengths.values())) > 1:
            raise DatasetError(f"{folder}: videos have different lengths (frames): {lengths}")
        self._videos = list(videos)
        return infos

    def frame_files(
        self, rig: ParsedRig, cameras: Sequence[int], frames: Sequence[int], sizes: Sequence[Tuple[int, int]]
    ) -> List[List[Optional[Path]]]:
        videos = [self._videos[cam] for cam in cameras]
        return cache_video_frames(videos, frames, sizes, self.config.cache_dir, self.config.skip_damaged_frames)
