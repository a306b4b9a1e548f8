"""The workspace: where a key lives on disk (layout.py names the keys), and atomic writes.

A workspace is a folder holding the pipeline's outputs for one scene:

    WS/
      ibr.toml                 config: [input] path = "..." and one table per stage
      scene.json               the scene manifest (stage `ingest`)
      sfm/  global/            global_mesh outputs
      views/<view>/...         per-view outputs (view names made path-safe: layout.view_key)
      renders/ eval/           novel views, metrics, charts
      .ibr/state/<stage>.json  whole-stage records; .ibr/state/<stage>/<view>.json per-view ones
      .ibr/hashes.json         content-hash cache keyed by (size, mtime)

Everything else refers to files by *keys*: posix paths relative to the workspace ("global/mesh.ply")
or, with the prefix "input/", relative to the input folder ("input/images/0001.png"). The input
folder is the workspace itself unless ibr.toml names another one. Every write goes through
`atomic_write`: the data lands in a temporary file in the same folder and is renamed over the
target, so a killed process never leaves a half-written file under a real name.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import tomllib
from pathlib import Path
from typing import Iterator

from . import layout
from .errors import InputError, WorkspaceError, confined, write_error
from .layout import view_key

CONFIG_FILE = "ibr.toml"
INPUT_KEYS = frozenset({"path"})  # the [input] table; stage tables are checked by their configs
INPUT_PREFIX = layout.INPUT
_TMP_MARK = ".ibrtmp-"
_UMASK = os.umask(0)  # read the process umask once (os.umask can only be read by setting it)
os.umask(_UMASK)


def read_toml(path: Path) -> dict:
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise InputError(f"{path}: malformed TOML ({e})") from None
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not UTF-8 text (byte {e.start}); TOML files must be UTF-8") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror})") from None


class Workspace:
    def __init__(self, root: Path | str, must_exist: bool = True, config: dict | None = None):
        """`config`: the parsed ibr.toml to use instead of reading one (a workspace that exists
        only in memory, for `--dry-run`)."""
        self.root = Path(root).absolute()
        if must_exist and not self.root.is_dir():
            raise InputError(f"{self.root}: workspace does not exist (create it with `ibr init`)")
        self._config: dict | None = config

    # --- configuration file -------------------------------------------------------------------
    @property
    def config_path(self) -> Path:
        return self.root / CONFIG_FILE

    def config(self) -> dict:
        """The parsed ibr.toml ({} when there is none)."""
        if self._config is None:
            self._config = read_toml(self.config_path) if self.config_path.is_file() else {}
        return self._config

    @property
    def input_root(self) -> Path:
        raw = self.config().get("input", {})
        if not isinstance(raw, dict):
            raise InputError(f"{self.config_path}: [input] must be a table with a 'path' key")
        unknown = sorted(set(raw) - INPUT_KEYS)
        if unknown:
            raise InputError(f"{self.config_path}: unknown key input.{unknown[0]} "
                             f"([input] takes: {', '.join(sorted(INPUT_KEYS))})")
        p = raw.get("path")
        if p is None:
            return self.root
        if not isinstance(p, str):
            raise InputError(f"{self.config_path}: input.path must be a string, got {p!r}")
        path = Path(p)
        return path if path.is_absolute() else (self.root / path).resolve()

    # --- keys -> paths -------------------------------------------------------------------------
    def path(self, key: str) -> Path:
        """The file of a key. Keys come from stage code but also from files a user can edit
        (scene.json, reflectors.json masks, config fields such as `strokes_dir`), so a key that
        is absolute or climbs out with `..` is refused rather than read."""
        if key.startswith(INPUT_PREFIX):
            return confined(self.input_root, key[len(INPUT_PREFIX):], key)
        return confined(self.root, key, key) if key else self.root

    def key(self, path: Path) -> str:
        """Inverse of `path` for files inside the workspace or the input folder."""
        path = Path(path).absolute()
        for base, prefix in ((self.root, ""), (self.input_root, INPUT_PREFIX)):
            with contextlib.suppress(ValueError):
                return prefix + path.relative_to(base).as_posix()
        raise ValueError(f"{path} is outside the workspace and the input folder")

    def exists(self, key: str) -> bool:
        return self.path(key).is_file()

    # --- well-known keys (layout.py) ---------------------------------------------------------
    SCENE = layout.SCENE
    view_dir = staticmethod(layout.view_dir)

    @staticmethod
    def view_file(view: str, filename: str) -> str:
        return layout.view_file(view, filename)

    def state_file(self, stage: str, view: str | None = None) -> Path:
        base = self.root / ".ibr" / "state"
        return base / f"{stage}.json" if view is None else base / stage / f"{view_key(view)}.json"

    def state_dir(self, stage: str) -> Path:
        return self.root / ".ibr" / "state" / stage

    @property
    def hash_cache_path(self) -> Path:
        return self.root / ".ibr" / "hashes.json"

    def scene(self):
        """The manifest written by the `ingest` stage."""
        from .scene import Scene
        p = self.path(self.SCENE)
        if not p.is_file():
            raise InputError(f"{p}: no scene manifest yet (run `ibr ingest` first)")
        return Scene.from_json(p.read_text())

    # --- writing ------------------------------------------------------------------------------
    @contextlib.contextmanager
    def atomic_write(self, key: str, mode: str = "wb") -> Iterator:
        """Open a temporary file next to `key`; on success rename it over the target."""
        with atomic_path(self.path(key)) as tmp, open(tmp, mode) as f:
            yield f

    def write_text(self, key: str, text: str) -> None:
        with self.atomic_write(key, "w") as f:
            f.write(text)

    def write_json(self, key: str, obj) -> None:
        self.write_text(key, json.dumps(obj, indent=1))

    @contextlib.contextmanager
    def lock(self, wait: bool = False) -> Iterator[None]:
        """Hold the workspace for one run: a second `ibr run` on it is refused (or, with `wait`,
        waits) and is told which process holds it. An flock on the workspace folder itself: the
        kernel releases it when the holder dies, kill -9 included, and no lock file is written, so
        a refused or failed run leaves the workspace exactly as it was."""
        import fcntl
        fd = os.open(self.root, os.O_RDONLY)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _lock_holder(self.root)
                if not wait:
                    raise WorkspaceError(f"{self.root}: in use by {holder}; wait for it to end, "
                                         "or rerun with --wait") from None
                import logging
                logging.getLogger("ibr_pipeline").info("waiting for %s to release %s", holder, self.root)
                fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)  # releases the flock

    def clean_temporaries(self) -> int:
        """Remove temporary files a killed process left behind; returns how many."""
        n = 0
        for p in self.root.rglob(f"*{_TMP_MARK}*"):
            with contextlib.suppress(OSError):
                p.unlink()
                n += 1
        return n


def _lock_holder(folder: Path) -> str:
    """'pid N (`command`)' of the process holding an flock on `folder`, from /proc/locks (Linux);
    'another process' where that cannot be read."""
    try:
        st = os.stat(folder)
        dev = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
        for line in Path("/proc/locks").read_text().splitlines():
            f = line.split()
            if len(f) > 5 and f[1] == "FLOCK" and f[5] == dev and f[4] != str(os.getpid()):
                cmd = Path(f"/proc/{f[4]}/cmdline").read_bytes().replace(b"\0", b" ").decode().strip()
                return f"pid {f[4]} (`{cmd}`)" if cmd else f"pid {f[4]}"
    except (OSError, ValueError, IndexError):
        pass
    return "another process"


@contextlib.contextmanager
def atomic_path(target: Path) -> Iterator[Path]:
    """Yield a temporary path in target's folder; rename it to `target` if the block succeeds.

    For writers that want a file name (cv2.imwrite, open3d, np.save): the temporary name keeps the
    target's suffix so format detection by extension still works.
    """
    target = Path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}{_TMP_MARK}", suffix=target.suffix,
                                   dir=target.parent)
        os.close(fd)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600 files; outputs get ordinary permissions
    except OSError as e:
        err = write_error(e, target)
        if err is None:
            raise
        raise err from None
    try:
        yield Path(tmp)
        os.replace(tmp, target)
    except BaseException as e:
        err = write_error(e, target, Path(tmp))  # before the unlink: it frees the space that ran out
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if err is not None:
            raise err from None
        raise


def file_sha256(file: Path) -> str:
    """The sha256 of a file's content (hex)."""
    h = hashlib.sha256()
    with open(file, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
