"""Headless Chromium for the viewer's checks (`ibr bench viewer`, tests/viewer): Debian's
chromium-headless-shell (scripts/install_system_deps.sh installs it), driven by Playwright's
Python package with `executable_path`, so Playwright's own browser download is never used.
Software WebGL2 (SwiftShader): the flags below, and none that reach the network."""
from __future__ import annotations

import shutil

from ..errors import InputError

CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
                 "--enable-unsafe-swiftshader", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run",
                 "--disable-quic", "--hide-scrollbars"]
EXECUTABLES = ("chromium-headless-shell", "chromium")


def chromium_path() -> str | None:
    for exe in EXECUTABLES:
        path = shutil.which(exe)
        if path:
            return path
    return None


def launch(playwright):
    """A headless Chromium browser of a `sync_playwright()` instance; InputError when none is
    installed."""
    exe = chromium_path()
    if exe is None:
        raise InputError(f"no {' or '.join(EXECUTABLES)} on PATH: `make install` installs Debian's "
                         "chromium-headless-shell (or apt-get install chromium-headless-shell)")
    return playwright.chromium.launch(executable_path=exe, args=CHROMIUM_ARGS)
