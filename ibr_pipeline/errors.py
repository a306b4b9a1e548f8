"""Error types shared by every module, and the two boundaries every user-facing path crosses.

`InputError` is the one error a user is meant to see: bad input (a missing workspace, a corrupt
image, an invalid config value, a path that leaves the input folder, a workspace that cannot be
written...). The CLI prints its message as one line and exits with code 2; everything else is a bug
and keeps its traceback (saved under WS/.ibr/logs/).

`confined` is the one resolver for paths named *inside* input files and configs (reflector masks,
`strokes_dir`, workspace keys in scene.json): a shared reflectors.json or ibr.toml must not make the
pipeline read files outside the folder it was given.
"""
from __future__ import annotations

import errno
import os
from pathlib import Path

_MAX_LINE = 600  # a message longer than this is cut: one line a terminal can show


def one_line(text: str) -> str:
    """`text` with newlines and runs of spaces folded, cut to one readable line. Library messages
    (torch, PIL, pycolmap) often span several lines; the user gets one."""
    flat = " ".join(str(text).split())
    return flat if len(flat) <= _MAX_LINE else flat[:_MAX_LINE - 1] + "…"


class InputError(Exception):
    """Bad user input. The message names the file or field at fault, in one line."""

    exit_code = 2

    def __init__(self, message: str = ""):
        super().__init__(one_line(message))


class ConfigError(InputError):
    """An invalid config value: names `stage.field` and says what is allowed."""

    def __init__(self, field: str, message: str):
        super().__init__(f"invalid config {field}: {message}")
        self.field = field

    def __reduce__(self):  # picklable across worker processes despite the two-argument __init__
        return (_config_error, (self.field, str(self)))


def _config_error(field: str, text: str) -> ConfigError:
    err = ConfigError(field, "")
    err.args = (text,)
    return err


class WorkspaceError(InputError):
    """The workspace cannot be written (read-only, full disk, no permission, in use): the user must
    fix the machine, not the data. Finished work is kept; a rerun continues."""


# errno values that mean "the place we write to", not a bug: each with what the user can do
_WRITE_FIXES = {
    errno.ENOSPC: "no space left on the device: free some space and rerun (finished work is kept)",
    errno.EDQUOT: "disk quota exceeded: free some space and rerun (finished work is kept)",
    errno.EFBIG: "file size limit exceeded (ulimit -f): raise the limit and rerun",
    errno.EROFS: "read-only file system: use a writable workspace folder",
    errno.EACCES: "permission denied: make the workspace writable or use another folder",
    errno.EPERM: "operation not permitted: make the workspace writable or use another folder",
}
_LOW_SPACE = 1 << 20  # bytes: below this a write error without errno is taken as a full disk


def write_error(exc: BaseException, target: Path,
                written: Path | None = None) -> WorkspaceError | None:
    """The WorkspaceError to raise for an exception met while writing `target` (through the
    temporary `written`, when one exists), or None when it is not a write problem the user can fix: an error that
    names another file came from reading something and stays what it was. numpy and torch report a
    full disk as a bare OSError ("57600 requested and 30688 written"), so with no errno the free
    space decides."""
    if not isinstance(exc, OSError):
        return None
    if written is not None and exc.filename is not None and str(exc.filename) not in (
            str(target), str(written)):
        return None
    fix = _WRITE_FIXES.get(exc.errno)
    if fix is None and exc.errno is None:
        try:
            import shutil
            if shutil.disk_usage(Path(target).parent).free < _LOW_SPACE:
                fix = _WRITE_FIXES[errno.ENOSPC]
        except OSError:
            pass
    if fix is None:
        return None
    return WorkspaceError(f"{target}: cannot write: {fix}")


def escapes(rel: str) -> str | None:
    """Why `rel` would leave the folder it is relative to (absolute, or climbing with `..`), or
    None when it stays inside. Lexical: a symlink the folder's owner put inside it is followed, as
    the rest of the folder is trusted as given."""
    rel = str(rel)
    if rel.startswith(("/", "\\")) or os.path.isabs(rel) or (len(rel) > 1 and rel[1] == ":"):
        return "is absolute"
    parts = os.path.normpath(rel).replace("\\", "/").split("/")
    if parts[0] == "..":
        return "climbs out with '..'"
    return None


def confined(root: Path, rel: str, what: str) -> Path:
    """`root / rel`, refused (InputError naming `what`) when `rel` would leave `root`."""
    why = escapes(rel)
    if why is not None:
        raise InputError(f"{what}: path {str(rel)!r} {why}; paths in input files and configs must "
                         f"stay inside {root}")
    return Path(root) / os.path.normpath(str(rel))


def input_text(path: Path) -> str:
    """The UTF-8 text of an input file (cameras.json, reflectors.json, a COLMAP text model), or
    InputError naming it: the reader boundary for text, so that a missing file, a permission
    problem or a stray non-UTF-8 byte is one line and not a UnicodeDecodeError traceback."""
    try:
        return Path(path).read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not UTF-8 text (byte {e.start}); save it as UTF-8") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror or e})") from None
