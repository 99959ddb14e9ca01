"""Synchronisation: when each camera started, in frames, and the window of instants every camera covers.

A camera's offset is the instant its frame 0 shows, in frames of the first camera's clock: frame f of camera i
shows instant f + offset[i]. Offsets are given (`--offsets`) or estimated from the audio tracks (`--sync audio`):
each track is cross-correlated with the first camera's (FFT, whole tracks), the lag of the highest peak is the
offset, and the confidence is 1 - (second peak / highest peak), the second peak taken more than a frame away, so
0 means two lags fit as well and 1 a single clear match.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import List, Sequence, Tuple

import numpy as np

from gear_nerfstudio.errors import InputError
from gear_nerfstudio.process.footage import Footage, read_audio

AUDIO_RATE = 16000
"""Audio is compared at this sample rate (Hz)."""
MIN_CONFIDENCE = 0.2
"""An audio offset with a lower confidence is not trusted."""


@dataclass(frozen=True)
class AudioEstimate:
    """One camera's offset from its audio track."""

    offset: float
    """In frames (sub-frame precision)."""
    confidence: float


def audio_offsets(cameras: Sequence[Footage]) -> List[AudioEstimate]:
    """Each camera's offset from its audio track against the first camera's; a camera without audio, or whose
    offset is not clear (confidence below `MIN_CONFIDENCE`), stops with an `InputError` naming it."""
    tracks = []
    for camera in cameras:
        track = read_audio(camera, AUDIO_RATE)
        if track is None or not np.any(track):
            raise InputError(f"{camera.path}: no audio track, so its offset cannot be found; give --offsets instead")
        tracks.append(track.astype(np.float64))
    estimates = [AudioEstimate(0.0, 1.0)]
    samples_per_frame = AUDIO_RATE / float(cameras[0].frame_rate)
    for camera, track in zip(cameras[1:], tracks[1:]):
        lag, confidence = _lag(tracks[0], track, int(np.ceil(samples_per_frame)))
        estimate = AudioEstimate(lag / samples_per_frame, confidence)
        if confidence < MIN_CONFIDENCE:
            raise InputError(
                f"{camera.path}: its offset cannot be found from the audio (best {estimate.offset:+.2f} frames, "
                f"confidence {confidence:.2f} < {MIN_CONFIDENCE}); give --offsets instead"
            )
        estimates.append(estimate)
    return estimates


def _lag(reference: np.ndarray, other: np.ndarray, exclude: int) -> Tuple[float, float]:
    """The delay (samples, sub-sample by a parabola through the peak) at which `other` started after `reference`,
    and the confidence of the peak against the highest one more than `exclude` samples away."""
    size = 1 << int(np.ceil(np.log2(len(reference) + len(other))))
    reference = (reference - reference.mean()) / (reference.std() + 1e-12)
    other = (other - other.mean()) / (other.std() + 1e-12)
    # correlation[k] = sum_n other[n] * reference[n + k]: other's sample n was recorded with reference's n + k.
    correlation = np.fft.irfft(np.fft.rfft(reference, size) * np.conj(np.fft.rfft(other, size)), size)
    lags = np.concatenate([np.arange(0, len(reference)), np.arange(-len(other) + 1, 0)])
    values = np.concatenate([correlation[: len(reference)], correlation[size - len(other) + 1 :]])
    best = int(np.argmax(values))
    peak = values[best]
    away = np.abs(lags - lags[best]) > exclude
    second = values[away].max(initial=0.0)
    shift = 0.0
    if 0 < best < len(values) - 1 and lags[best - 1] == lags[best] - 1 and lags[best + 1] == lags[best] + 1:
        left, right = values[best - 1], values[best + 1]
        curvature = left - 2 * peak + right
        shift = 0.5 * (left - right) / curvature if curvature < 0 else 0.0
    confidence = float(1.0 - max(second, 0.0) / peak) if peak > 0 else 0.0
    return float(lags[best] + shift), confidence


def window(cameras: Sequence[Footage], offsets: Sequence[float]) -> Tuple[List[int], int]:
    """The first frame of each camera and the number of frames of the window every camera covers (offsets rounded
    to whole frames)."""
    whole = [int(round(o)) for o in offsets]
    start = max(whole)
    end = min(o + camera.num_frames for o, camera in zip(whole, cameras))
    if end <= start:
        raise InputError(
            "the cameras share no instant: with offsets "
            + ", ".join(f"{c.name} {o:+d}" for c, o in zip(cameras, whole))
            + " their recordings do not overlap"
        )
    return [start - o for o in whole], end - start
