"""Depth snapshot files (.npz): depth, depth_scale, K, camera and optional truth (DESIGN.md section 5)."""

from __future__ import annotations

import zipfile
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from robot.base.errors import InputError
from robot.base.samples import DepthFrame


def save_snapshot(path, frame: DepthFrame) -> None:
    data = dict(depth=frame.depth, depth_scale=np.float64(frame.depth_scale), K=frame.K, camera=np.str_(frame.camera))
    if frame.truth is not None:
        data["truth"] = np.asarray(frame.truth, dtype=float)
    np.savez_compressed(path, **data)


def validate_frame_arrays(where: str, depth, depth_scale, K, truth: Optional[Sequence[float]] = None) -> None:
    """Raise InputError naming the problem if the arrays cannot be a depth frame."""
    if not isinstance(depth, np.ndarray) or depth.ndim != 2:
        raise InputError(f"{where}: 'depth' must be a 2-D array, got shape {getattr(depth, 'shape', None)}")
    if depth.dtype != np.uint16:
        raise InputError(f"{where}: 'depth' must be uint16, got {depth.dtype}")
    if depth.shape[0] < 16 or depth.shape[1] < 16:
        raise InputError(f"{where}: 'depth' is too small ({depth.shape[1]}x{depth.shape[0]})")
    if not np.isfinite(depth_scale) or depth_scale <= 0:
        raise InputError(f"{where}: 'depth_scale' must be a positive finite number, got {depth_scale}")
    K = np.asarray(K)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise InputError(f"{where}: 'K' must be a finite 3x3 matrix, got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or K[0, 1] != 0 or np.any(K[2] != (0, 0, 1)):
        raise InputError(f"{where}: 'K' is not a pinhole intrinsic matrix: {K.tolist()}")
    if truth is not None:
        t = np.asarray(truth, dtype=float)
        if t.shape != (3,) or not np.all(np.isfinite(t)):
            raise InputError(f"{where}: 'truth' must be three finite numbers (x, y, phi)")


def load_snapshot(path) -> DepthFrame:
    p = Path(path)
    try:
        with np.load(p, allow_pickle=False) as z:
            missing = [k for k in ("depth", "depth_scale", "K", "camera") if k not in z.files]
            if missing:
                raise InputError(f"{p}: missing array(s): {', '.join(missing)}")
            depth = z["depth"]
            scale_arr = z["depth_scale"]
            K = z["K"]
            camera = z["camera"]
            truth = z["truth"] if "truth" in z.files else None
    except FileNotFoundError:
        raise InputError(f"{p}: file not found") from None
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise InputError(f"{p}: not a readable .npz snapshot ({e})") from None
    if scale_arr.size != 1 or not np.issubdtype(scale_arr.dtype, np.number):
        raise InputError(f"{p}: 'depth_scale' must be one number")
    if camera.size != 1 or camera.dtype.kind not in "US":
        raise InputError(f"{p}: 'camera' must be a string")
    if K.dtype.kind not in "fiu":
        raise InputError(f"{p}: 'K' must be numeric")
    if truth is not None and truth.dtype.kind not in "fiu":
        raise InputError(f"{p}: 'truth' must be numeric")
    scale = float(scale_arr)
    validate_frame_arrays(str(p), depth, scale, K, truth)
    return DepthFrame(
        camera=str(camera.item() if camera.dtype.kind == "U" else camera.item().decode()),
        depth=depth,
        depth_scale=scale,
        K=K.astype(float),
        truth=tuple(float(v) for v in truth) if truth is not None else None,
    )
