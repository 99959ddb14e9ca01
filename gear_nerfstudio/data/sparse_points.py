"""Points triangulated from the training views at their known poses (COLMAP through `pycolmap`), as rays with a
depth: the targets of the sparse depth loss (``model.losses``; DS-NeRF, Deng et al. 2022).

At a few instants of the window, the training images of that instant are matched (SIFT, every pair) and the
matches triangulated with the dataparser's cameras held fixed. Each observation of a point becomes a ray: its
pixel in that image, the pixel's colour, and the distance from the camera to the point along the pixel's ray.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence, Tuple

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.datasets.base_dataset import InputDataset

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


@dataclass
class SparseDepth:
    """Rays through triangulated points: (image, row, col), the distance to the point along the ray, the colour."""

    indices: Int[Tensor, "N 3"]
    depth: Float[Tensor, "N 1"]
    rgb: Float[Tensor, "N 3"]

    def __len__(self) -> int:
        return len(self.depth)

    def sample(self, count: int) -> "SparseDepth":
        """``count`` rays drawn at random (with replacement)."""
        rows = torch.randint(len(self), (count,))
        return SparseDepth(self.indices[rows], self.depth[rows], self.rgb[rows])


def triangulate(dataset: InputDataset, frames: Sequence[int]) -> SparseDepth:
    """The rays of every point triangulated from the dataset's images of each of ``frames`` (its metadata
    ``frame_ids``), at its cameras' poses and intrinsics; none for cameras other than pinhole ones (``pinhole``)."""
    cameras = dataset.cameras
    frame_ids = dataset.metadata.get("frame_ids", torch.zeros(len(dataset), dtype=torch.long)).tolist()
    indices, points = [], []
    for frame in frames:
        images = [i for i, f in enumerate(frame_ids) if f == frame and pinhole(cameras[i])]
        if len(images) >= 2:
            for image, (x, y), point in _observations(cameras, dataset.image_filenames, images):
                indices.append((image, int(y), int(x)))
                points.append(point)
    if not points:
        return SparseDepth(torch.zeros(0, 3, dtype=torch.long), torch.zeros(0, 1), torch.zeros(0, 3))
    index = torch.tensor(indices, dtype=torch.long)
    rays = cameras.generate_rays(camera_indices=index[:, :1], coords=index[:, 1:].float() + 0.5)
    depth = ((torch.from_numpy(np.array(points)).float() - rays.origins) * rays.directions).sum(-1)
    rgb = torch.zeros(len(index), 3)
    for image in index[:, 0].unique().tolist():
        rows = index[:, 0] == image
        rgb[rows] = dataset.get_image_float32(image)[index[rows, 1], index[rows, 2], :3]
    keep = depth > 0
    return SparseDepth(index[keep], depth[keep, None], rgb[keep])


def pinhole(camera: Cameras) -> bool:
    """A perspective camera without distortion (COLMAP's PINHOLE), the one kind triangulated here."""
    distortion = camera.distortion_params
    return camera.camera_type.item() == CameraType.PERSPECTIVE.value and (distortion is None or not distortion.any())


def _observations(
    cameras: Cameras, image_filenames: Sequence[Path], images: Sequence[int]
) -> Iterator[Tuple[int, np.ndarray, np.ndarray]]:
    """(image, pixel (x, y), point) for each observation of each point triangulated from ``images``."""
    import pycolmap

    pycolmap.logging.minloglevel = 2  # COLMAP's own log: errors only
    with tempfile.TemporaryDirectory() as work:
        folder, database = Path(work) / "images", Path(work) / "database.db"
        folder.mkdir()
        for image in images:
            source = Path(image_filenames[image]).resolve()
            (folder / f"{image}{source.suffix}").symlink_to(source)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.sift.peak_threshold = 0.002  # as the calibration (process.calibrate): small, low-contrast frames
        # Images imported first, in order: extraction threads would number them as they finish, and the points
        # triangulated from the same images would differ from run to run (and so would training from a seed).
        pycolmap.Database.open(database).close()  # import_images wants the file to exist
        pycolmap.import_images(database, folder, camera_mode=pycolmap.CameraMode.PER_IMAGE, options=reader)
        pycolmap.extract_features(
            database, folder, camera_mode=pycolmap.CameraMode.PER_IMAGE, reader_options=reader,
            extraction_options=extraction, device=pycolmap.Device.cpu,
        )  # fmt: skip
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = 0  # the same points from the same images
        pycolmap.match_exhaustive(database, verification_options=verification, device=pycolmap.Device.cpu)
        with pycolmap.Database.open(database) as db:
            stored = {int(Path(image.name).stem): image for image in db.read_all_images()}
        known = pycolmap.Reconstruction()
        for image in images:
            entry, camera = stored[image], cameras[image]
            known.add_camera_with_trivial_rig(
                pycolmap.Camera(
                    model="PINHOLE", width=int(camera.width), height=int(camera.height), camera_id=entry.camera_id,
                    params=[float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)],
                )
            )  # fmt: skip
            c2w = camera.camera_to_worlds.numpy().astype(np.float64)
            rotation = c2w[:, :3] @ OPENGL_TO_OPENCV
            cam_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation.T), -rotation.T @ c2w[:, 3])
            known.add_image_with_trivial_frame(
                pycolmap.Image(name=entry.name, camera_id=entry.camera_id, image_id=entry.image_id), cam_from_world
            )
        options = pycolmap.IncrementalPipelineOptions()
        options.random_seed = 0
        result = pycolmap.triangulate_points(known, database, folder, Path(work) / "points", options=options)
        for point in result.points3D.values():
            for element in point.track.elements:
                image = result.images[element.image_id]
                yield int(Path(image.name).stem), image.points2D[element.point2D_idx].xy, point.xyz
