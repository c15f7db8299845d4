"""Compiling the C++ steps on first use: one shared library per source version.

A library is built with the system's C++ compiler (``$CXX``, else ``c++`` or ``g++``)
into ``$XDG_CACHE_HOME/torchrl_grpo`` (default ``~/.cache/torchrl_grpo``; the temporary
directory where the home is read-only), named by a digest of its sources, the static
libraries it links and its flags, so an edited source (or another numpy) rebuilds and an
unchanged one loads at once.

Example:
    >>> from torchrl_grpo.sim.native import SOURCES
    >>> build_library(SOURCES).highway_step is not None
    True
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

__all__ = ["FLAGS", "NativeBuildError", "build_library"]

logger = logging.getLogger(__name__)

#: No contraction of multiply-adds: each expression rounds as the tensor path's does.
FLAGS = ("-O2", "-std=c++17", "-ffp-contract=off", "-fPIC", "-shared", "-pthread")


class NativeBuildError(RuntimeError):
    """A C++ step could not be compiled (no compiler, or the compiler failed)."""


def _cache_dir() -> Path:
    root = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "torchrl_grpo"
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError:  # a read-only home: the temporary directory instead
        root = Path(tempfile.gettempdir()) / f"torchrl_grpo-{os.getuid()}"
        root.mkdir(parents=True, exist_ok=True)
    return root


def build_library(
    sources: tuple[Path, ...], includes: tuple[Path, ...] = (), links: tuple[Path, ...] = ()
) -> ctypes.CDLL:
    """Compile ``sources[0]`` (which includes the others) unless built already, and load it.

    Args:
        sources: the translation unit first, then every header it includes (all of
            them name the build).
        includes: more header directories (``-I``).
        links: static libraries linked in (their bytes name the build too).

    Returns:
        The loaded library (argument types are the caller's to declare).

    Raises:
        NativeBuildError: no C++ compiler was found, or it failed (its message is kept).

    Example:
        >>> # see the module's example
    """
    text = b"".join(path.read_bytes() for path in (*sources, *links))
    options = [*FLAGS, *(f"-I{path}" for path in includes)]
    digest = hashlib.sha256(text + " ".join(options).encode()).hexdigest()[:16]
    target = _cache_dir() / f"{sources[0].stem}-{digest}.so"
    if not target.exists():
        asked = os.environ.get("CXX")
        compiler = shutil.which(asked) if asked else shutil.which("c++") or shutil.which("g++")
        if not compiler:
            raise NativeBuildError(
                f"the C++ step needs a C++ compiler: found none "
                f"({'CXX=' + repr(asked) if asked else 'no c++ or g++ on PATH'}); "
                "install g++ or step with tensors: "
                "TensorHighwayEnv(..., native=False)"
            )
        # Built beside the target and renamed: concurrent builds (test workers) never
        # load a half-written library.
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
            built = Path(tmp) / target.name
            libraries = [*map(str, links), "-lm"] if links else []
            command = [compiler, *options, str(sources[0]), *libraries, "-o", str(built)]
            run = subprocess.run(command, capture_output=True, text=True)
            if run.returncode != 0:
                raise NativeBuildError(f"{' '.join(command)} failed:\n{run.stderr[-2000:]}")
            os.replace(built, target)
        logger.info("built %s", target)
    return ctypes.CDLL(str(target))
