"""highway-env's reset and spawn draws in C++ (``draws_native.cpp``), bit for bit numpy's.

A tensor world carries its env's numpy generator (PCG64) as words
(:func:`torchrl_grpo.envs.core.gym_state.encode_rng`). Replaying a reset's or a spawn's
draws in Python costs a generator per world; this library replays them in one call for
all the worlds. Its normal draws and its choices are numpy's own C code: the library
links numpy's ``libnpyrandom`` (shipped in every numpy wheel, beside the headers), given
our PCG64 as the bit generator (``numpy_draws.h``). The wrappers that check the words
and name the bad ones are in :mod:`torchrl_grpo.envs.highway.native_draws`.

Example:
    >>> load_draws_library().spawn_draws.restype is None
    True
"""

from __future__ import annotations

import ctypes
import functools
import importlib.metadata
import importlib.util
from pathlib import Path

from torchrl_grpo.sim.native_build import NativeBuildError, build_library

__all__ = ["SOURCES", "load_draws_library", "numpy_random_library"]

SOURCE = Path(__file__).with_name("draws_native.cpp")
#: Every file of the library (it is rebuilt when any changes).
SOURCES = (SOURCE, SOURCE.with_name("numpy_draws.h"), SOURCE.with_name("pcg64.h"))

_WORDS_ROWS_BATCH = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64]
_ARGTYPES = {
    "merge_draws": [*_WORDS_ROWS_BATCH, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p],
    "roundabout_draws": [
        *_WORDS_ROWS_BATCH, ctypes.c_int64, ctypes.c_int64, ctypes.c_double, ctypes.c_double,
        ctypes.c_void_p, ctypes.c_void_p,
    ],
    "spawn_draws": [
        *_WORDS_ROWS_BATCH, ctypes.c_double, ctypes.c_int, ctypes.c_double, ctypes.c_double,
        ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
    ],
    "ego_draws": [
        *_WORDS_ROWS_BATCH, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
    ],
}  # fmt: skip


def numpy_random_library() -> tuple[Path, Path]:
    """``(numpy's C include directory, its libnpyrandom.a)``.

    Raises:
        NativeBuildError: this numpy ships no ``libnpyrandom`` (or no ``bitgen.h``).

    Example:
        >>> numpy_random_library()[1].name
        'libnpyrandom.a'
    """
    # Found without importing numpy: the simulator imports only torch and tensordict.
    package = Path(importlib.util.find_spec("numpy").origin).parent
    include = package / "_core" / "include"  # numpy 2 (numpy 1: core/include)
    include = include if include.is_dir() else package / "core" / "include"
    library = package / "random" / "lib" / "libnpyrandom.a"
    header = include / "numpy" / "random" / "bitgen.h"
    missing = [str(p) for p in (library, header) if not p.is_file()]
    if missing:
        raise NativeBuildError(
            f"the C++ draws link numpy's C random library, which numpy "
            f"{importlib.metadata.version('numpy')} does not ship here: "
            f"{', '.join(missing)} not found"
        )
    return include, library


@functools.cache
def load_draws_library() -> ctypes.CDLL:
    """The compiled draws, built on first use (:func:`.native_build.build_library`).

    Raises:
        NativeBuildError: no C++ compiler, the compiler failed, or numpy ships no
            ``libnpyrandom``.

    Example:
        >>> # see the module's example
    """
    include, library = numpy_random_library()
    loaded = build_library(SOURCES, includes=(include,), links=(library,))
    for name, argtypes in _ARGTYPES.items():
        function = getattr(loaded, name)
        function.restype = None
        function.argtypes = argtypes
    return loaded
