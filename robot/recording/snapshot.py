"""Depth snapshot files (.npz): depth (H x W uint16), depth_scale (m per unit), K, camera and optional truth.

Loading reads only a regular file of at most 256 MiB (``robot.base.files``), and only what a
depth frame can be: the archive's members must each unpack to at most ``MAX_MEMBER_BYTES``
(a compressed archive of zeros would otherwise unpack to gigabytes), the image must fit a real
camera (``MAX_WIDTH`` x ``MAX_HEIGHT``), and every problem is one InputError naming the file.
"""

from __future__ import annotations

import struct
import tokenize
import zipfile
import zlib
from pathlib import Path

import numpy as np

from robot.base.errors import InputError
from robot.base.files import SNAPSHOT, format_size, open_regular_file
from robot.base.frames import MAX_DEPTH_SCALE, MAX_HEIGHT, MAX_WIDTH, validate_frame_arrays  # noqa: F401  (one check for files and live frames)
from robot.base.samples import DepthFrame

MAX_MEMBER_BYTES = 64 * 1024 * 1024  # unpacked size of one array; a 1920x1080 uint16 frame is 4 MB
MAX_CAMERA_NAME = 64
_FIELDS = ("depth", "depth_scale", "K", "camera", "truth")


def save_snapshot(path, frame: DepthFrame) -> None:
    data = dict(depth=frame.depth, depth_scale=np.float64(frame.depth_scale), K=frame.K, camera=np.str_(frame.camera))
    if frame.truth is not None:
        data["truth"] = np.asarray(frame.truth, dtype=float)
    np.savez_compressed(path, **data)


def _check_members(p: Path, f) -> None:
    """Refuse an archive whose members unpack to more than a depth frame could need."""
    try:
        with zipfile.ZipFile(f) as zf:
            infos = zf.infolist()
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, OSError, EOFError, NotImplementedError,
            RuntimeError, struct.error) as e:  # NotImplementedError: a member "needs" zip version 6.4 (the long fuzz run)
        raise InputError(f"{p}: not a readable .npz snapshot ({type(e).__name__}: {str(e)[:100]})") from None
    if len(infos) > 2 * len(_FIELDS):
        raise InputError(f"{p}: {len(infos)} arrays, a snapshot has at most {len(_FIELDS)}")
    for info in infos:
        if info.file_size > MAX_MEMBER_BYTES:
            raise InputError(f"{p}: array {info.filename[:40]!r} unpacks to {format_size(info.file_size)}, more than "
                             f"the {format_size(MAX_MEMBER_BYTES)} a depth frame can need")
    f.seek(0)


def load_snapshot(path) -> DepthFrame:
    p = Path(path)
    with open_regular_file(p, SNAPSHOT) as f:
        head = f.read(4)
        f.seek(0)
        if head != b"PK\x03\x04":
            raise InputError(f"{p}: not a readable .npz snapshot (not a zip archive)")
        _check_members(p, f)
        try:
            with np.load(f, allow_pickle=False) as z:
                missing = [k for k in ("depth", "depth_scale", "K", "camera") if k not in z.files]
                if missing:
                    raise InputError(f"{p}: missing array(s): {', '.join(missing)}")
                depth = z["depth"]
                scale_arr = z["depth_scale"]
                K = z["K"]
                camera = z["camera"]
                truth = z["truth"] if "truth" in z.files else None
        except InputError:
            raise
        except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, KeyError, TypeError, RuntimeError,
                NotImplementedError, SyntaxError, tokenize.TokenError, struct.error, RecursionError) as e:
            # what zipfile and numpy's .npy header parser let through on a hostile archive: an
            # encrypted member, an unknown compression, a header that is not a Python literal, ...
            raise InputError(f"{p}: not a readable .npz snapshot ({type(e).__name__}: {str(e)[:100]})") from None
        except MemoryError:  # an array header claiming a shape far beyond its data
            raise InputError(f"{p}: not a readable .npz snapshot (an array claims more memory than there is)") from None
    if scale_arr.size != 1 or not np.issubdtype(scale_arr.dtype, np.number) or scale_arr.dtype.kind == "c":
        raise InputError(f"{p}: 'depth_scale' must be one number")
    if camera.size != 1 or camera.dtype.kind not in "US":
        raise InputError(f"{p}: 'camera' must be a string")
    if K.dtype.kind not in "fiu":
        raise InputError(f"{p}: 'K' must be numeric")
    if truth is not None and truth.dtype.kind not in "fiu":
        raise InputError(f"{p}: 'truth' must be numeric")
    scale = float(scale_arr.reshape(()))
    validate_frame_arrays(str(p), depth, scale, K, truth)
    try:
        name = str(camera.item() if camera.dtype.kind == "U" else camera.item().decode("utf-8"))
    except UnicodeDecodeError:
        raise InputError(f"{p}: 'camera' is not UTF-8 text") from None
    if not name or len(name) > MAX_CAMERA_NAME:
        raise InputError(f"{p}: 'camera' must be a camera name of 1 to {MAX_CAMERA_NAME} characters")
    return DepthFrame(
        camera=name,
        depth=depth,
        depth_scale=scale,
        K=K.astype(float),
        truth=tuple(float(v) for v in truth) if truth is not None else None,
    )
