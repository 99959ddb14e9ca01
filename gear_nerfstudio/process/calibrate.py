"""Calibration with COLMAP (pycolmap): intrinsics and pose per camera, sparse points.

The cameras of a rig do not move, so all the instants a camera filmed constrain one pose. SIFT features are
extracted from the frames of each calibration instant (`<images>/<camera>/<instant>.png`) and matched between the
cameras at the same instant (a moving scene matches only at one instant). Then each camera becomes one image in a
second database, whose keypoints are those of all its instants and whose matches with another camera are the
matches of all instants together: COLMAP verifies them (one epipolar geometry per camera pair, whatever the
instant), pairs that fit only a pure rotation are forgotten, and COLMAP maps one image per camera, so a camera's
intrinsics and pose are shared by its instants and people who moved between instants add points across the scene.
The largest reconstruction is kept. Everything runs on the CPU.
"""

from __future__ import annotations

import itertools
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np

from gear_nerfstudio.errors import InputError

CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")
"""COLMAP camera models `--camera-model` accepts (perspective ones; distortion is removed when writing)."""

SEED = 0
"""COLMAP's RANSAC and mapper seed of a calibration: two runs on the same frames give the same cameras."""


@dataclass
class Calibration:
    """What the writer needs of COLMAP's result, per camera in the input order."""

    cameras: list
    """pycolmap.Camera per input camera (model, parameters, size)."""
    cam_from_world: np.ndarray
    """(N, 3, 4) world-to-camera, OpenCV axes (x right, y down, z forward)."""
    depths: List[np.ndarray]
    """Per camera, the depths (camera z) of the sparse points it observes."""
    reprojection_errors: np.ndarray
    """(N,) mean reprojection error of each camera's observations, pixels."""
    points: np.ndarray
    """(P, 3) sparse points."""
    colors: np.ndarray
    """(P, 3) uint8."""
    reconstruction: object
    """The pycolmap.Reconstruction (the largest COLMAP made)."""


def reconstruct(
    images: Path,
    names: Sequence[str],
    instants: Sequence[int],
    camera_model: str,
    camera_params: Optional[Sequence[float]],
    progress,
    seed: int = SEED,
    label: str = "",
):
    """The largest pycolmap.Reconstruction COLMAP makes of the frames `<images>/<name>/<instant:05d>.png` (None if it
    makes none); `progress` is a rich Progress, `label` prefixes its lines. COLMAP's scratch files (databases, pair
    list, models) live in a temporary folder."""
    with tempfile.TemporaryDirectory() as work:
        return _reconstruct(images, Path(work), names, instants, camera_model, camera_params, progress, seed, label)


def registered(reconstruction) -> Dict[str, object]:
    """The registered pycolmap.Image of each camera name (its folder in the frame names)."""
    if reconstruction is None:
        return {}
    return {image.name.split("/")[0]: image for image in reconstruction.images.values() if image.has_pose}


def _reconstruct(images: Path, work: Path, names, instants, camera_model, camera_params, progress, seed, label):
    import pycolmap

    pycolmap.logging.minloglevel = 2  # COLMAP's own log: errors only; progress shows what runs
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    if camera_params is not None:
        reader.camera_params = ",".join(str(p) for p in camera_params)

    frames_db, cameras_db = work / "frames.db", work / "cameras.db"
    frame_names = [f"{name}/{instant:05d}.png" for name in names for instant in instants]
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.peak_threshold = 0.002  # more features on small, low-contrast frames (COLMAP: 0.0067)
    task = progress.add_task(f"{label}Extracting features", total=1)
    pycolmap.extract_features(
        frames_db, images, image_names=frame_names, camera_mode=pycolmap.CameraMode.PER_FOLDER,
        reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
    )
    progress.advance(task)

    task = progress.add_task(f"{label}Matching", total=1)
    pair_list = work / "pairs.txt"
    pair_list.write_text(
        "".join(f"{a}/{t:05d}.png {b}/{t:05d}.png\n" for t in instants for a, b in itertools.combinations(names, 2))
    )
    pairing = pycolmap.ImportedPairingOptions()
    pairing.match_list_path = str(pair_list)
    matching = pycolmap.FeatureMatchingOptions()
    matching.skip_geometric_verification = True  # verified per camera pair, all instants together, below
    pycolmap.match_image_pairs(frames_db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    _pool_instants(frames_db, cameras_db, images, names, instants, reader)
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = seed
    pycolmap.geometric_verification(cameras_db, two_view_geometry_options=verification)
    _drop_rotation_only_pairs(cameras_db)
    progress.advance(task)

    options = pycolmap.IncrementalPipelineOptions()
    options.random_seed = seed
    # Rigs film from far apart: a first pair with fewer matches and a narrower angle than COLMAP's defaults.
    options.mapper.init_min_num_inliers = 30
    options.mapper.init_min_tri_angle = 4.0
    options.mapper.abs_pose_min_num_inliers = 15
    if camera_params is not None:
        options.ba_refine_focal_length = options.ba_refine_extra_params = False
        options.mapper.abs_pose_refine_focal_length = options.mapper.abs_pose_refine_extra_params = False
    task = progress.add_task(f"{label}Mapping (cameras registered)", total=len(names))
    reconstructions = pycolmap.incremental_mapping(
        cameras_db, images, work / "models", options=options, next_image_callback=lambda: progress.advance(task)
    )
    progress.update(task, completed=len(names))
    return max(reconstructions.values(), key=lambda r: r.num_reg_images(), default=None)


def _pool_instants(frames_db: Path, cameras_db: Path, images: Path, names, instants, reader) -> None:
    """Write `cameras_db`: one image per camera (its first instant's frame), with the keypoints of all its instants
    and, per camera pair, the matches of all instants (keypoint indices shifted to the pooled lists)."""
    import pycolmap

    pycolmap.Database.open(cameras_db).close()  # import_images wants the file to exist
    pycolmap.import_images(
        cameras_db, images, camera_mode=pycolmap.CameraMode.PER_IMAGE,
        image_names=[f"{name}/{instants[0]:05d}.png" for name in names], options=reader,
    )
    with pycolmap.Database.open(frames_db) as frames, pycolmap.Database.open(cameras_db) as cameras:
        frame_ids = {image.name: image.image_id for image in frames.read_all_images()}
        camera_ids = {image.name.split("/")[0]: image.image_id for image in cameras.read_all_images()}
        shift: Dict[tuple, int] = {}
        for name in names:
            keypoints = []
            for instant in instants:
                shift[name, instant] = sum(len(k) for k in keypoints)
                keypoints.append(frames.read_keypoints(frame_ids[f"{name}/{instant:05d}.png"]))
            cameras.write_keypoints(camera_ids[name], np.concatenate(keypoints))
        for a, b in itertools.combinations(names, 2):
            matches = []
            for instant in instants:
                found = frames.read_matches(frame_ids[f"{a}/{instant:05d}.png"], frame_ids[f"{b}/{instant:05d}.png"])
                matches.append(found.astype(np.int64) + [shift[a, instant], shift[b, instant]])
            cameras.write_matches(camera_ids[a], camera_ids[b], np.concatenate(matches).astype(np.uint32))


def _drop_rotation_only_pairs(cameras_db: Path) -> None:
    """Forget the camera pairs whose verified matches fit a pure rotation (COLMAP's PANORAMIC or PLANAR_OR_PANORAMIC):
    two fixed cameras of a rig stand apart, so such matches are repeated texture seen from symmetric places (a dome's
    wall panels), and they registered Panoptic cameras turned by 70-140 degrees or with focal and distortion 10 % off
    (benchmarks/results/process_windows.md)."""
    import pycolmap

    rotation_only = {
        pycolmap.TwoViewGeometryConfiguration.PANORAMIC, pycolmap.TwoViewGeometryConfiguration.PLANAR_OR_PANORAMIC
    }
    with pycolmap.Database.open(cameras_db) as database:
        for pair, geometry in zip(*database.read_two_view_geometries()):
            if geometry.config in rotation_only:
                database.delete_two_view_geometry(*pycolmap.pair_id_to_image_pair(pair))


def summarise(reconstruction, names: Sequence[str]) -> Calibration:
    """Per camera of `names`: its COLMAP camera, pose, observed depths and reprojection error; an `InputError` names
    the cameras the reconstruction did not register."""
    images = registered(reconstruction)
    missing = [name for name in names if name not in images]
    if missing:
        raise InputError(
            f"COLMAP registered {len(names) - len(missing)} of {len(names)} cameras; not registered: "
            f"{', '.join(missing)} (film more texture that these cameras share with the others, add "
            "--calibration-frames, or leave them out of the input folder)"
        )
    points = reconstruction.points3D
    cameras, poses, depths, errors = [], [], [], []
    for name in names:
        image = images[name]
        pose = image.cam_from_world().matrix()
        observed = [p for p in image.points2D if p.has_point3D()]
        xyz = np.array([points[p.point3D_id].xyz for p in observed]).reshape(-1, 3)
        cameras.append(image.camera)
        poses.append(pose)
        depths.append(xyz @ pose[2, :3] + pose[2, 3])
        errors.append(float(np.mean([np.linalg.norm(image.project_point(points[p.point3D_id].xyz) - p.xy) for p in observed])))
    ordered = sorted(points)
    return Calibration(
        cameras=cameras,
        cam_from_world=np.array(poses),
        depths=depths,
        reprojection_errors=np.array(errors),
        points=np.array([points[i].xyz for i in ordered]).reshape(-1, 3),
        colors=np.array([points[i].color for i in ordered], dtype=np.uint8).reshape(-1, 3),
        reconstruction=reconstruction,
    )
