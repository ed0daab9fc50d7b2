"""Reading HPointLoc query frames (`<dataset>/HPointLoc_dataset/<scene>/<scene>_point<N>.hdf5`).

Needs h5py: `pip install "pntr-client[hpointloc]"`. Depth is decoded exactly as pntr's Rust reader
does, so the frames sent are byte-identical to the ones `pntr` itself would send.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

# HPointLoc stores depth as metres / 10 in 0..1; 0 and >= 1.0 (the far clip) are not measurements.
HPOINTLOC_DEPTH_SCALE_M = 10.0
DATASET_DIR = "HPointLoc_dataset"

QueryFrame = tuple[
    int, npt.NDArray[np.uint8], npt.NDArray[np.float32], npt.NDArray[np.float64], npt.NDArray[np.float64]
]


class DatasetError(Exception):
    """A dataset folder or Point file that is missing or not in the HPointLoc layout."""


def require_h5py() -> Any:
    """The h5py module; DatasetError saying how to install it when it is missing."""
    try:
        import h5py
    except ImportError as e:
        raise DatasetError(f'{e}: reading HPointLoc files needs h5py: pip install "pntr-client[hpointloc]"') from e
    return h5py


def decode_depth(normalised: npt.ArrayLike) -> npt.NDArray[np.float32]:
    """HPointLoc normalised depth (HxW or HxWx1, metres / 10 in 0..1) -> HxW float32 metres, 0 where
    invalid (0, >= 1.0, negative or not finite), as pntr's Rust reader does."""
    v = np.asarray(normalised, dtype=np.float32)
    if v.ndim == 3 and v.shape[-1] == 1:
        v = v[..., 0]
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(v) & (v > 0.0) & (v < 1.0)
    return np.where(valid, v * np.float32(HPOINTLOC_DEPTH_SCALE_M), np.float32(0.0)).astype(np.float32)


def point_files(dataset: str | Path, scene: str, point: int | None = None) -> list[tuple[int, Path]]:
    """[(index, path)] of the scene's Point files sorted by index (only `point` when given).

    `dataset` is the folder holding `HPointLoc_dataset/`, or that folder itself. Raises DatasetError
    for a missing dataset, scene or Point file.
    """
    root = Path(dataset)
    if not root.exists():
        raise DatasetError(f"dataset folder not found: {root}")
    sdir = root / scene if root.name == DATASET_DIR else root / DATASET_DIR / scene
    if not sdir.is_dir():
        raise DatasetError(
            f"scene folder not found: {sdir} (expected <dataset>/{DATASET_DIR}/<scene>/<scene>_point<N>.hdf5)"
        )
    if point is not None:
        p = sdir / f"{scene}_point{point}.hdf5"
        if not p.is_file():
            raise DatasetError(f"Point file not found: {p}")
        return [(point, p)]
    files = []
    for p in sdir.glob(f"{scene}_point*.hdf5"):
        idx = p.name[len(scene) + len("_point") : -len(".hdf5")]
        if idx.isdigit():
            files.append((int(idx), p))
    if not files:
        raise DatasetError(f"no Point files ({scene}_point<N>.hdf5) in {sdir}")
    return sorted(files)


def read_point(path: str | Path, limit: int | None = None) -> Iterator[QueryFrame]:
    """Yield (i, rgb HxWx3 uint8, depth HxW float32 metres, gps (3,) metres, quat (4,) w x y z) for
    the first `limit` query frames of a Point file (all when None).

    `gps` / `quat` are the ground-truth world_from_camera in the dataset's frame and Habitat axes.
    Raises DatasetError for an unreadable file or missing / malformed fields.
    """
    h5py = require_h5py()
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise DatasetError(f"cannot open {path}: {e}") from e
    with f:
        for name in ("rgb", "depth", "gps", "quat"):
            if name not in f:
                raise DatasetError(f"{path}: field `{name}` missing (not an HPointLoc Point file?)")
        rgb, depth = f["rgb"], f["depth"]
        n = rgb.shape[0]
        if rgb.ndim != 4 or rgb.shape[3] != 3 or rgb.dtype != np.uint8:
            raise DatasetError(f"{path}: `rgb` is {rgb.dtype}{rgb.shape}, expected uint8 (N, H, W, 3)")
        if depth.shape[:3] != rgb.shape[:3]:
            raise DatasetError(f"{path}: `depth` shape {depth.shape} does not match `rgb` {rgb.shape}")
        gps = np.asarray(f["gps"][:], dtype=np.float64)
        quat = np.asarray(f["quat"][:], dtype=np.float64)
        if gps.shape != (n, 3) or quat.shape != (n, 4):
            raise DatasetError(f"{path}: gps {gps.shape} / quat {quat.shape}, expected ({n}, 3) / ({n}, 4)")
        for i in range(n if limit is None else min(n, limit)):
            yield i, np.ascontiguousarray(rgb[i]), decode_depth(depth[i]), gps[i], quat[i]
