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
from .errors import InputError
from .layout import view_key

CONFIG_FILE = "ibr.toml"
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
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror})") from None


class Workspace:
    def __init__(self, root: Path | str, must_exist: bool = True):
        self.root = Path(root).absolute()
        if must_exist and not self.root.is_dir():
            raise InputError(f"{self.root}: workspace does not exist (create it with `ibr init`)")
        self._config: dict | None = None

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
        p = raw.get("path")
        if p is None:
            return self.root
        if not isinstance(p, str):
            raise InputError(f"{self.config_path}: input.path must be a string, got {p!r}")
        path = Path(p)
        return path if path.is_absolute() else (self.root / path).resolve()

    # --- keys -> paths -------------------------------------------------------------------------
    def path(self, key: str) -> Path:
        if key.startswith(INPUT_PREFIX):
            return self.input_root / key[len(INPUT_PREFIX):]
        return self.root / key

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

    def clean_temporaries(self) -> int:
        """Remove temporary files a killed process left behind; returns how many."""
        n = 0
        for p in self.root.rglob(f"*{_TMP_MARK}*"):
            with contextlib.suppress(OSError):
                p.unlink()
                n += 1
        return n


@contextlib.contextmanager
def atomic_path(target: Path) -> Iterator[Path]:
    """Yield a temporary path in target's folder; rename it to `target` if the block succeeds.

    For writers that want a file name (cv2.imwrite, open3d, np.save): the temporary name keeps the
    target's suffix so format detection by extension still works.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}{_TMP_MARK}", suffix=target.suffix,
                               dir=target.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600 files; outputs get ordinary permissions
    try:
        yield Path(tmp)
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def file_sha256(file: Path) -> str:
    """The sha256 of a file's content (hex)."""
    h = hashlib.sha256()
    with open(file, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
