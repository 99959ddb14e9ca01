"""A built-in stand-in for SAM that needs no weights. It is NOT SAM.

It exists so that the demo, the synthetic scenes and the tests can run the whole method (SAM feature
supervision, Eq 9; upshift masks, Sec 4.3; tracking, Sec 4.5) without a user's SAM model. On real
footage use the `onnx` backend with SAM or MobileSAM; this stand-in only separates regions that differ
in colour or texture and knows nothing about objects.

Encoder: CIE Lab colour and a shading-invariant chroma direction averaged over each cell of SAM's
64 x 64 grid (longest side 64 cells, zero padding at the bottom/right; see `interface`), the same
averaged over neighbouring cells, and the local colour contrast at two scales (texture). These 16
hand-made features are mapped to 256 dimensions by a fixed, seeded matrix with orthonormal columns; the
map is linear, so features volume-rendered by the NeRF (Eq 8) stay meaningful.

Decoder: features are mapped back with the transposed matrix (which also drops whatever a rendered map
adds outside the features' span) and rescaled to a fixed median norm over the cells that carry features
(rendered maps may be shrunk, and cells where a render meets nothing are zero: `interface.median_norm`);
the cells are segmented by a graph segmentation at three granularities, and the segments selected by
the prompts are the candidate masks, scored by how little they change with the granularity (like SAM's
stability score), for a box by how well they fill it, and with a depth cue (below) by their outline. On the
synthetic scenes one click gives about 0.8 mean IoU and a tight box about 0.89 (tests/test_sam_builtin.py).

Depth cue (issue 26): an embedding rendered from the radiance field carries the field's depth at its cells
(`Embedding.depth`). The decoder then segments the features with the log depth beside them
(`interface.with_depth_cue`): a depth jump, such as a person's outline against the wall behind, is a
boundary however alike the colours on both sides, so a click on a grey shirt no longer spreads into the grey
wall. Thin parts (legs, arms) are kept: the opening that removes leaks along colour boundaries is not made,
since a depth edge stops them. On the real capture the depth cue raised the mIoU of one click per person on
rendered training views from 19.7 to 49.7 (benchmarks/results/tracking_real.md). Parts of one object that differ
in colour (shirt and trousers) are still separate segments, so a clicked region is then joined by its
neighbouring segments at about its depth while that keeps its outline in front of what lies behind it
(`_joined_by_depth`, with `occlusion.in_front_share`): 54.6-61.7 on the same views of four models, against
49.5-53.3 with the cue alone. With the cue the segmentation is also finer (the joins put the parts back together),
and the candidates of a click or a box are ranked also by the share of their outline in front of what surrounds
them (`_in_front`), so that a person at the image's edge no longer takes the floor in front of their feet, nor a
box the wall beside them: tracking into `panoptic`'s held-out camera, mIoU 66.0 -> 70.3 and t-mIoU 56.4 -> 62.7
(3 seeds, both people, `min_views` 2; tracking_real.md). The cue also takes in what lies at an object's depth beside
it, such as a floater of the floor's colour below a sphere or a strip of light on the floor at a person's feet, where
the colours tell them apart: so the candidates of the features alone are ranked beside the cue's, those whose
outline is at least half in front of what surrounds them (`_IN_FRONT`). In the viewer's wide view a click on a
sphere of the synthetic scenes then gives mean IoU 77.6 instead of 70.9, a click on a person 56.8 and 58.0 on the
two real captures, as before (tracking_real.md), and tracking into the 31 cameras' held-out camera mIoU
75.1 / t-mIoU 65.0 instead of 72.3 / 63.5 (the other tracking figures unchanged).
"""

from __future__ import annotations

from typing import Any, Dict, List, Optional, Tuple

import numpy as np
from PIL import Image
from scipy import ndimage

from gear_nerfstudio.parallel import available_cores
from gear_nerfstudio.sam.interface import (
    Embedding,
    SamBackend,
    cells_per_pixel,
    log_depth,
    median_norm,
    pixel_cells,
    valid_depth,
    valid_grid,
    with_depth_cue,
)
from gear_nerfstudio.sam.occlusion import filtered_disparity, occluding_share

_PIXELS_PER_CELL = 4  # resolution at which the hand-made features are computed
_SEED = 20240617
_RAW_DIM = 16  # channels of _cell_features

# Decoder: the encoder's typical median feature norm (decoded maps are rescaled to it), segmentation
# scales k (the middle one wins ties; finer ones with a depth cue, since joins by depth put an object's parts back
# together), the shares of a segment's cells that must lie in a box for a box alone to select it (the better
# filling choice wins), and the share of a box that a mask should cover.
_MEDIAN_NORM = 0.75
_GRANULARITIES = (1.0, 1.5, 2.25)
_DEPTH_GRANULARITIES = (0.5, 1.0, 2.0)
_BOX_SHARES = (0.75, 0.5)
_BOX_AREA = 0.5
# Decoder with a depth cue: at most _JOINS neighbouring segments joined to a clicked region, each no larger than
# _JOIN_SIZE times the region and within _JOIN_DEPTH_BAND of its median log depth, while the union keeps at least
# _IN_FRONT of its outline occluding (`_joined_by_depth`); the regions of the features alone compete with the cue's
# when at least _IN_FRONT of their outline is occluding (an object in front of what surrounds it).
_JOINS = 8
_JOIN_SIZE = 3.0
_JOIN_DEPTH_BAND = 0.15
_IN_FRONT = 0.5


def _srgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """CIE Lab (D65) of sRGB values in [0, 1], channels last."""
    linear = np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)
    to_xyz = np.array(
        [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]]
    )
    xyz = linear @ to_xyz.T / np.array([0.95047, 1.0, 1.08883])
    eps = 216.0 / 24389.0
    f = np.where(xyz > eps, np.cbrt(xyz), (24389.0 / 27.0 * xyz + 16.0) / 116.0)
    return np.stack([116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]), 200.0 * (f[..., 1] - f[..., 2])], -1)


def _cell_features(rgb: np.ndarray, grid_size: int) -> np.ndarray:
    """Hand-made features (G, G, _RAW_DIM) of an sRGB image in [0, 1] resized to _PIXELS_PER_CELL pixels
    per cell; each is of order 0.1 to 1 and zero on padded cells.

    Lightness is weighted least (shading changes it most), the chroma direction most (it separates
    differently coloured surfaces under any shading); an average over neighbouring cells and the local
    colour contrast at two scales describe texture such as stripes.
    """
    lab = _srgb_to_lab(rgb) / 100.0
    chroma = np.sqrt(lab[..., 1:2] ** 2 + lab[..., 2:3] ** 2)
    hue = lab[..., 1:] / (chroma + 0.08)  # chroma direction, damped for greyish pixels
    colour = np.concatenate([lab[..., :1] * 0.1, lab[..., 1:] * 0.3, hue], axis=-1)
    pixels = np.concatenate([colour, lab, lab**2, np.ones_like(lab[..., :1])], axis=-1)

    # Average over each cell's pixels (padding counts as missing), then blur between covered cells.
    cell = _PIXELS_PER_CELL
    padded = np.zeros((grid_size * cell, grid_size * cell, pixels.shape[-1]))
    padded[: pixels.shape[0], : pixels.shape[1]] = pixels
    pooled = padded.reshape(grid_size, cell, grid_size, cell, -1).mean(axis=(1, 3))
    coverage = pooled[..., -1:]
    mask = (coverage > 0).astype(np.float64)
    cells = pooled[..., :-1] / np.maximum(coverage, 1e-6) * mask

    def smooth(values: np.ndarray, sigma: float) -> np.ndarray:
        """Gaussian average over the covered cells only."""
        weights = ndimage.gaussian_filter(mask, (sigma, sigma, 0), mode="constant", truncate=3.0)
        blurred = ndimage.gaussian_filter(values * mask, (sigma, sigma, 0), mode="constant", truncate=3.0)
        return blurred / np.maximum(weights, 1e-6) * mask

    colour, lab, lab_squared = cells[..., :5], cells[..., 5:8], cells[..., 8:11]
    features = [colour, smooth(colour, 2.0)]
    for sigma in (1.0, 2.0):
        variance = smooth(lab_squared, sigma) - smooth(lab, sigma) ** 2
        features.append(0.2 * np.sqrt(np.maximum(variance, 0.0)))
    return np.concatenate(features, axis=-1) * mask


class BuiltinSamBackend(SamBackend):
    """Weight-free stand-in for SAM's encoder and prompt decoder (see the module docstring).

    Plain numpy / scipy on the CPU: the maps are small (64 x 64 cells), where thread start-up would
    cost more than the work. So each encode runs on one core, and the feature cache encodes one image per core
    at a time (2 threads encoded 40 frames of the real capture at 608x336 in 1.4 s, one thread in 2.9 s).
    """

    name = "builtin"
    embedding_dim = 256
    grid_size = 64
    parallel_encodes = available_cores()

    def __init__(self) -> None:
        gaussian = np.random.default_rng(_SEED).standard_normal((self.embedding_dim, _RAW_DIM))
        self._projection = np.linalg.qr(gaussian)[0]  # (256, raw), orthonormal columns

    @property
    def settings(self) -> Dict[str, Any]:
        return {"seed": _SEED, "raw_dim": _RAW_DIM, "pixels_per_cell": _PIXELS_PER_CELL, "version": 2}

    def encode(self, image: np.ndarray) -> Embedding:
        """Hand-made features averaged over the cells of SAM's grid geometry; padded cells are zero."""
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"expected an RGB uint8 image (H, W, 3), got {image.dtype} {image.shape}")
        height, width = image.shape[:2]
        work = self.grid_size * _PIXELS_PER_CELL
        scale = work / max(height, width)
        size = (min(work, int(np.ceil(width * scale - 1e-6))), min(work, int(np.ceil(height * scale - 1e-6))))
        resized = Image.fromarray(image).resize(size, Image.BILINEAR)  # antialiased when shrinking
        cells = _cell_features(np.asarray(resized, dtype=np.float64) / 255.0, self.grid_size)
        features = np.einsum("kr,hwr->khw", self._projection, cells)
        return Embedding(features=features.astype(np.float32), image_size=(height, width))

    def decode(
        self,
        embedding: Embedding,
        points: Optional[np.ndarray] = None,
        labels: Optional[np.ndarray] = None,
        box: Optional[np.ndarray] = None,
    ) -> Tuple[np.ndarray, np.ndarray]:
        """Candidate masks at three granularities of the cell segmentation of the features alone and, with a depth
        cue, three more of the features with the cue, best first.

        Positive points select the segments they fall in, negative points remove the cells closer to
        them than to the positives, a box keeps the cells inside it; a box alone selects the segments
        that lie (mostly) inside it, or the part inside it of the segment at its centre, whichever fills it
        better (an object that grew past the box between two frames is not left for a sliver inside it).
        """
        expected = (self.embedding_dim, self.grid_size, self.grid_size)
        if tuple(embedding.features.shape) != expected:
            raise ValueError(f"expected features of shape {expected}, got {tuple(embedding.features.shape)}")
        if embedding.depth is not None and tuple(embedding.depth.shape) != expected[1:]:
            raise ValueError(f"expected a depth cue of shape {expected[1:]}, got {tuple(embedding.depth.shape)}")
        image_size = (int(embedding.image_size[0]), int(embedding.image_size[1]))
        points = np.zeros((0, 2)) if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 2)
        labels = np.ones(len(points), dtype=np.int64) if labels is None else np.asarray(labels).reshape(-1)
        if len(labels) != len(points):
            raise ValueError(f"{len(points)} points but {len(labels)} labels")
        if box is None and not (labels == 1).any():
            raise ValueError("decode needs a positive point or a box")

        rows, cols = valid_grid(image_size, self.grid_size)
        scale = cells_per_pixel(image_size, self.grid_size)
        features = np.asarray(embedding.features[:, :rows, :cols], dtype=np.float64)
        raw = np.einsum("kr,khw->hwr", self._projection, features)
        raw = raw * (_MEDIAN_NORM / max(median_norm(raw), 1e-6))
        depth = valid_depth(embedding)
        logs = log_depth(depth)
        raw = with_depth_cue(raw, logs)
        disparity = None if depth is None else filtered_disparity(depth)
        inside, centre = np.ones((rows, cols), dtype=bool), None
        if box is not None:
            box = np.asarray(box, dtype=np.float64).reshape(4)
            inside = _box_cells(box, rows, cols, scale)
            centre = _cells(box.reshape(2, 2).mean(axis=0, keepdims=True), image_size, self.grid_size)[0]
        positives = _cells(points[labels == 1], image_size, self.grid_size)
        negatives = _cells(points[labels == 0], image_size, self.grid_size)
        closer_to_negative = np.zeros((rows, cols), dtype=bool)
        if len(negatives) and len(positives):
            closer_to_negative = _distance(raw, negatives) < _distance(raw, positives)

        # The candidates of the features alone, and with a depth cue also those of the features with the cue beside
        # them, all ranked by the same score: the cue's win where it separates an object from a background of its
        # colour, the features' where the cue takes in something of another colour at the object's depth beside it.
        features_alone = raw if depth is None else raw[..., :-1]
        sets = [(features_alone, False)] if depth is None else [(raw, True), (features_alone, False)]
        box_cells = inside if box is not None else None
        regions, scores, middles = [], [], []
        for cells, cue in sets:
            granularities = _DEPTH_GRANULARITIES if cue else _GRANULARITIES
            joins = logs if cue else None
            found = [
                _region(_segment(cells, k), positives, inside, centre, closer_to_negative, disparity, joins)
                for k in granularities
            ]
            # the features alone's regions compete beside the cue's only as objects in front of their surroundings
            least_in_front = _IN_FRONT if depth is not None and not cue else 0.0
            regions.extend(found)
            scores.extend(_scores(found, len(positives) > 0, box_cells, disparity, least_in_front))
            middles.extend(j == len(granularities) // 2 for j in range(len(granularities)))
        order = sorted(range(len(regions)), key=lambda i: (-scores[i], not middles[i], i))  # middles win ties
        masks = np.stack([self.upsample(regions[i], image_size, scale) for i in order])
        return masks, np.asarray(scores, dtype=np.float32)[order]

    @staticmethod
    def upsample(region: np.ndarray, image_size: Tuple[int, int], scale: float) -> np.ndarray:
        """Mask at every pixel centre of a region of valid cells: cell logits (+1 in, -1 out) interpolated
        bilinearly, > 0."""
        logits = np.where(region, 1.0, -1.0)
        rows = _interpolation_matrix(image_size[0], region.shape[0], scale)
        cols = _interpolation_matrix(image_size[1], region.shape[1], scale)
        return rows @ logits @ cols.T > 0


def _region(
    segments: np.ndarray,
    positives: np.ndarray,
    inside: np.ndarray,
    centre: Optional[np.ndarray],
    closer_to_negative: np.ndarray,
    disparity: Optional[np.ndarray],
    logs: Optional[np.ndarray],
) -> np.ndarray:
    """The prompts' region of a segmentation: the segments of the positive points (with `logs`, the segmentation's
    cells carried the depth cue, joined by depth: `_joined_by_depth`), or for a box alone the segments (mostly) inside
    it or the part inside it of the segment at its `centre` cell, whichever fills it better; without the cells inside
    the box or closer to a negative point, and connected to the positive points."""
    if len(positives):
        region = np.isin(segments, segments[positives[:, 0], positives[:, 1]])
        if logs is not None:
            region = _joined_by_depth(region, segments, disparity, logs)
    else:
        candidates = [_segments_inside(segments, inside, share) & inside for share in _BOX_SHARES]
        candidates.append((segments == segments[centre[0], centre[1]]) & inside)  # what the box is around
        region = max(candidates, key=lambda mask: _box_fill(mask, inside) * _in_front(mask, disparity))
    region = region & inside & ~closer_to_negative
    if len(positives):  # thin strands are leaks along colour boundaries: open, if the seeds survive
        opened = _connected_to(ndimage.binary_opening(region) if logs is None else region, positives)
        region = opened if opened.any() else _connected_to(region, positives)
    return region


def _scores(
    regions: List[np.ndarray],
    points: bool,
    box: Optional[np.ndarray],
    disparity: Optional[np.ndarray],
    least_in_front: float = 0.0,
) -> List[float]:
    """Scores of one segmentation's regions at its granularities. Points: their agreement with the other
    granularities' (like SAM's stability score). With a depth cue: the share of the region's outline that lies in
    front of what surrounds it, 0 below `least_in_front`. A box (its cells): the region should fill it, as an object
    fills its bounding box (Sec 4.5 prompts with a previous mask's box)."""
    scores = np.ones(len(regions))
    if points:
        scores *= [np.mean([_iou(r, o) for j, o in enumerate(regions) if j != i]) for i, r in enumerate(regions)]
    fronts = [_in_front(r, disparity) for r in regions]
    scores *= [front if front >= least_in_front else 0.0 for front in fronts]
    if box is not None:
        scores *= [_box_fill(r, box) for r in regions]
    return scores.tolist()


def _interpolation_matrix(pixels: int, cells: int, scale: float) -> np.ndarray:
    """(pixels, cells) weights of bilinear interpolation between cell centres at pixel centres, with
    the values of the outermost cells beyond them."""
    position = np.clip((np.arange(pixels) + 0.5) * scale - 0.5, 0.0, cells - 1.0)
    lower = np.minimum(np.floor(position).astype(np.int64), cells - 1)
    upper = np.minimum(lower + 1, cells - 1)
    weights = np.zeros((pixels, cells))
    np.add.at(weights, (np.arange(pixels), lower), 1.0 - (position - lower))
    np.add.at(weights, (np.arange(pixels), upper), position - lower)
    return weights


def _cells(points: np.ndarray, image_size: Tuple[int, int], grid_size: int) -> np.ndarray:
    """Grid cells (row, col) containing pixel points (x, y), clipped to the valid grid (``pixel_cells``); (N, 2) int."""
    return np.stack(pixel_cells(points[:, 0], points[:, 1], image_size, grid_size), axis=-1).reshape(-1, 2)


def _box_cells(box: np.ndarray, rows: int, cols: int, scale: float) -> np.ndarray:
    """Cells whose centres lie in the box, and always the cell at the box centre."""
    x0, x1 = sorted(box[[0, 2]] * scale)
    y0, y1 = sorted(box[[1, 3]] * scale)
    ys = np.arange(rows) + 0.5
    xs = np.arange(cols) + 0.5
    inside = ((ys >= y0) & (ys <= y1))[:, None] & ((xs >= x0) & (xs <= x1))[None]
    inside[int(np.clip((y0 + y1) / 2, 0, rows - 1)), int(np.clip((x0 + x1) / 2, 0, cols - 1))] = True
    return inside


def _distance(raw: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Distance of every cell's feature to the nearest prompted cell's feature."""
    prompts = raw[cells[:, 0], cells[:, 1]]
    return np.linalg.norm(raw[:, :, None, :] - prompts[None, None], axis=-1).min(axis=-1)


def _segment(raw: np.ndarray, k: float) -> np.ndarray:
    """Graph segmentation of the cell grid (Felzenszwalb and Huttenlocher, IJCV 2004): 8-connected
    cells merge while the feature difference between them is no larger than the internal variation
    of both regions plus k / size. Returns a region label per cell."""
    rows, cols, _ = raw.shape
    index = np.arange(rows * cols).reshape(rows, cols)
    pairs = [
        (index[:, :-1], index[:, 1:]),
        (index[:-1], index[1:]),
        (index[:-1, :-1], index[1:, 1:]),
        (index[:-1, 1:], index[1:, :-1]),
    ]
    first = np.concatenate([a.ravel() for a, _ in pairs])
    second = np.concatenate([b.ravel() for _, b in pairs])
    flat = raw.reshape(rows * cols, -1)
    weights = np.linalg.norm(flat[first] - flat[second], axis=1)
    parent = list(range(rows * cols))
    size = [1] * (rows * cols)
    internal = [0.0] * (rows * cols)

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    order = np.argsort(weights, kind="stable")
    for a, b, weight in zip(first[order].tolist(), second[order].tolist(), weights[order].tolist()):
        a, b = find(a), find(b)
        if a != b and weight <= internal[a] + k / size[a] and weight <= internal[b] + k / size[b]:
            if size[a] < size[b]:
                a, b = b, a
            parent[b] = a
            size[a] += size[b]
            internal[a] = weight
    return np.array([find(i) for i in range(rows * cols)]).reshape(rows, cols)


def _joined_by_depth(region: np.ndarray, segments: np.ndarray, disparity: np.ndarray, logs: np.ndarray) -> np.ndarray:
    """A clicked region joined by the parts of its object that differ in colour (trousers below a shirt, a head
    above it), one neighbouring segment at a time: the neighbour, at most _JOIN_SIZE times the region and within
    _JOIN_DEPTH_BAND of the region's median log depth (`logs`), whose union with the region has the largest share
    of occluding outline (`occlusion.in_front_share`, on the view's `filtered_disparity`), while that share is at
    least _IN_FRONT; at most _JOINS times. An object's parts complete its outline against what lies behind it;
    the floor or wall next to it goes on into its surroundings, so joining them lowers the share."""
    labels, sizes = np.unique(segments, return_counts=True)
    size_of, median_of = dict(zip(labels, sizes)), dict(zip(labels, ndimage.median(logs, segments, labels)))
    for _ in range(_JOINS):
        around = ndimage.binary_dilation(region, np.ones((3, 3), dtype=bool)) & ~region
        reference, size = float(np.median(logs[region])), np.count_nonzero(region)
        best, best_share = None, -1.0
        for label in np.unique(segments[around]):
            if size_of[label] > _JOIN_SIZE * size or abs(median_of[label] - reference) > _JOIN_DEPTH_BAND:
                continue
            part = segments == label
            share = occluding_share(region | part, disparity)
            if share is not None and share > best_share:
                best, best_share = part, share
        if best is None or best_share < _IN_FRONT:
            return region
        region = region | best
    return region


def _in_front(region: np.ndarray, disparity: Optional[np.ndarray]) -> float:
    """Share of a region's outline that lies in front of what surrounds it (`occlusion.occluding_share`) on a view's
    `filtered_disparity`; 0 for a region without an edge inside the image, 1 without a depth cue."""
    if disparity is None:
        return 1.0
    return occluding_share(region, disparity) or 0.0


def _segments_inside(segments: np.ndarray, inside: np.ndarray, share: float) -> np.ndarray:
    """Cells of the segments with at least `share` of their cells inside a box; if there are none, of
    the segment with the largest share inside."""
    labels, index, counts = np.unique(segments, return_inverse=True, return_counts=True)
    shares = np.bincount(index.ravel(), weights=inside.ravel(), minlength=len(labels)) / counts
    return (shares >= min(share, float(shares.max())))[index.reshape(segments.shape)]


def _box_fill(region: np.ndarray, box: np.ndarray) -> float:
    """How well a region fills a box: IoU of its bounding box with the box, times its share of the
    box's area up to _BOX_AREA (a sphere covers pi / 4 of its box)."""
    rs, cs = np.nonzero(region)
    if len(rs) == 0:
        return 0.0
    bounds = np.zeros_like(region)
    bounds[rs.min() : rs.max() + 1, cs.min() : cs.max() + 1] = True
    return _iou(bounds, box) * min(1.0, len(rs) / (_BOX_AREA * np.count_nonzero(box)))


def _connected_to(region: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Cells of `region` 4-connected to any of `cells`."""
    labelled, _ = ndimage.label(region)
    keep = np.unique(labelled[cells[:, 0], cells[:, 1]])
    return np.isin(labelled, keep[keep > 0])


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.count_nonzero(a & b)) / max(float(np.count_nonzero(a | b)), 1.0)
