"""Opening the files a user names: only regular files, each kind with its own size limit.

Every loader (robot config, path file, map, depth snapshot, recording, IFC model, calibration)
opens its file through here, so a FIFO, a device or a directory given by mistake (or on
purpose) is refused at once by ``os.stat``, before anything is read: ``/dev/zero`` is never
read until memory runs out and a FIFO never blocks the process waiting for a writer. The file
is then opened with ``O_NONBLOCK`` and checked again on the open descriptor, so a path swapped
for a FIFO between the two checks cannot block either.

The limits are generous for real files and far below what would exhaust the robot's memory
(the Jetson Nano has 4 GB):

=============  ===========  ===============================================================
kind           limit        why
=============  ===========  ===============================================================
config         1 MiB        the robot config and path files are a few kB of hand-written YAML
calibration    1 MiB        a few matrices
map            64 MiB       an imported building storey is under 1 MiB; 64x headroom
snapshot       256 MiB      one depth frame (.npz) is 0.8 MB at 848x480, 4 MB at 1920x1080
recording      64 GiB       MCAP is read sequentially, never held in memory
ifc            4 GiB        ifcopenshell parses in C++; large models of whole campuses exist
=============  ===========  ===============================================================

A file that grows past its limit while being read is cut at the limit plus one byte and
refused: its ``stat`` size is only a first check.
"""

from __future__ import annotations

import errno
import os
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Type, Union

from robot.base.errors import ConfigError, InputError, RobotError

KiB = 1024
MiB = 1024 * KiB
GiB = 1024 * MiB

PathLike = Union[str, os.PathLike]


@dataclass(frozen=True)
class FileKind:
    """What a loader reads: its name in messages, its size limit, and the error it raises."""

    name: str
    max_bytes: int
    error: Type[RobotError] = ConfigError


CONFIG = FileKind("config file", 1 * MiB)
PATH_FILE = FileKind("path file", 1 * MiB)
CALIBRATION = FileKind("calibration file", 1 * MiB)
MAP = FileKind("map", 64 * MiB)
SNAPSHOT = FileKind("snapshot", 256 * MiB, InputError)
RECORDING = FileKind("recording", 64 * GiB, InputError)
IFC = FileKind("IFC model", 4 * GiB)

KINDS = (CONFIG, PATH_FILE, CALIBRATION, MAP, SNAPSHOT, RECORDING, IFC)


def format_size(n: float) -> str:
    for unit, size in (("GiB", GiB), ("MiB", MiB), ("KiB", KiB)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} bytes"


def _what(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def check_regular_file(path: PathLike, kind: FileKind) -> int:
    """The size of ``path`` in bytes, or ``kind.error`` if it is missing, not a regular file or too large.

    For libraries that want a path rather than a file object (ifcopenshell): call this first.
    """
    p = Path(path)
    try:
        st = os.stat(str(p))
    except FileNotFoundError:
        raise kind.error(f"{p}: file not found") from None
    except OSError as e:
        raise kind.error(f"{p}: cannot read the {kind.name}: {e.strerror or e}") from None
    except ValueError:  # a NUL byte in the name
        raise kind.error(f"{p!r}: not a valid file name") from None
    _check_stat(p, st, kind)
    return st.st_size


def _check_stat(p: Path, st: os.stat_result, kind: FileKind) -> None:
    if not stat.S_ISREG(st.st_mode):
        raise kind.error(f"{p}: is {_what(st.st_mode)}, not a regular file (the {kind.name} must be one)")
    if st.st_size > kind.max_bytes:
        raise kind.error(f"{p}: {format_size(st.st_size)}, larger than the {format_size(kind.max_bytes)} "
                         f"limit for {kind.name}s")


def open_regular_file(path: PathLike, kind: FileKind) -> BinaryIO:
    """``path`` opened for binary reading, after the checks of :func:`check_regular_file`.

    The caller closes it (use ``with``).
    """
    p = Path(path)
    check_regular_file(p, kind)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(str(p), flags)
    except FileNotFoundError:
        raise kind.error(f"{p}: file not found") from None
    except OSError as e:
        raise kind.error(f"{p}: cannot read the {kind.name}: {e.strerror or e}") from None
    try:
        _check_stat(p, os.fstat(fd), kind)  # the path may have been replaced since the stat
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: PathLike, kind: FileKind) -> bytes:
    """The whole file, refused if it is (or grows) larger than ``kind.max_bytes``."""
    p = Path(path)
    with open_regular_file(p, kind) as f:
        try:
            data = f.read(kind.max_bytes + 1)
        except OSError as e:
            raise kind.error(f"{p}: cannot read the {kind.name}: {e.strerror or e}") from None
    if len(data) > kind.max_bytes:
        raise kind.error(f"{p}: larger than the {format_size(kind.max_bytes)} limit for {kind.name}s")
    return data


def read_text(path: PathLike, kind: FileKind) -> str:
    """The whole file as UTF-8 text (see :func:`read_bytes`)."""
    data = read_bytes(path, kind)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise kind.error(f"{Path(path)}: not UTF-8 text (byte {e.start} is 0x{data[e.start]:02x})") from None


def check_writable_file(path: PathLike, what: str = "output file") -> Path:
    """Refuse, before any work starts, an output path that cannot be written.

    The path must not be a directory or anything but a regular file, and its directory must
    exist and take a new file (tried for real: permission bits say nothing about a read-only
    mount, and root passes every permission check). Raises ConfigError naming the problem.
    """
    p = Path(path)
    if str(path) == "" or p.name == "":
        raise ConfigError(f"{what} '{path}': needs a file name")
    try:
        st = os.stat(str(p))
    except FileNotFoundError:
        st = None
    except OSError as e:
        raise ConfigError(f"{what} {p}: {e.strerror or e}") from None
    except ValueError:  # a NUL byte in the name
        raise ConfigError(f"{what} {p!r}: not a valid file name") from None
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise ConfigError(f"{what} {p}: is {_what(st.st_mode)}, give a file name")
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise ConfigError(f"{what} {p}: directory {parent} does not exist")
    check_writable_directory(parent, what)
    return p


def check_writable_directory(directory: PathLike, what: str = "output directory") -> Path:
    """Refuse a directory that cannot take a new file: missing, not a directory, read-only, full."""
    d = Path(directory)
    if not d.is_dir():
        raise ConfigError(f"{what} {d}: not a directory")
    try:
        fd, probe = tempfile.mkstemp(prefix=".robotctl-write-test-", dir=str(d))
    except OSError as e:
        why = "read-only file system" if e.errno == errno.EROFS else (e.strerror or str(e))
        raise ConfigError(f"{what} {d}: cannot write there ({why})") from None
    try:
        os.write(fd, b"\0")  # a full disk refuses data even where it still takes a name
    except OSError as e:
        raise ConfigError(f"{what} {d}: cannot write there ({e.strerror or e})") from None
    finally:
        os.close(fd)
        try:
            os.unlink(probe)
        except OSError:
            pass
    return d


__all__ = ["FileKind", "CONFIG", "PATH_FILE", "CALIBRATION", "MAP", "SNAPSHOT", "RECORDING", "IFC", "KINDS",
           "check_regular_file", "open_regular_file", "read_bytes", "read_text", "check_writable_file",
           "check_writable_directory", "format_size"]


def atomic_write_text(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` so that a reader (or a power cut) sees the old file or the new one,
    never half of one: a temporary file beside it, fsync, rename, fsync of the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=str(path.parent))
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, str(path))
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    # The rename itself must reach the disk too.
    try:
        dir_fd = os.open(str(path.parent), os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)
