"""The service process's memory allocator: jemalloc when the system has it.

With glibc's malloc the server's resident memory grows for as long as it serves images of new
sizes: the 2D stage's buffers (images, feature, score and message maps, all sized by the image)
are freed into arenas that fragment and are not given back, while the bytes in use stay flat.
jemalloc gives them back: over 360 LSP images it stays flat where glibc grows by 12 %, and in a
30-minute soak of the service it holds within 1.5 % (docs/service-results.md, "Memory"; the other
remedies measured there, malloc_trim, MALLOC_ARENA_MAX, a smaller oneDNN cache, tcmalloc, each
either grows or costs speed). So `ds3d-serve` runs itself under jemalloc.

jemalloc has to be loaded before anything else (LD_PRELOAD), so `ds3d-serve` re-executes itself
with it once, at the start, when it is installed (Debian: libjemalloc2) and not yet loaded.
"""

from __future__ import annotations

import ctypes.util
import os
import sys

from ds3d.util.memory import loaded_allocator

# Set in the re-executed process, so that a jemalloc that fails to preload is not retried forever.
_REEXEC_MARK = "DS3D_ALLOCATOR_REEXEC"


def find_jemalloc() -> str | None:
    """The shared library to preload for jemalloc (a name the dynamic loader finds), or None."""
    return ctypes.util.find_library("jemalloc")


def run_under_jemalloc(argv: list[str]) -> None:
    """Replace this process by `python -m ds3d_service ARGV` with jemalloc preloaded, when
    jemalloc is installed and not loaded yet; return (doing nothing) otherwise."""
    if loaded_allocator() != "glibc":
        return
    library = find_jemalloc()
    if library is None or os.environ.get(_REEXEC_MARK):
        return
    preload = " ".join(filter(None, [library, os.environ.get("LD_PRELOAD")]))
    env = {**os.environ, "LD_PRELOAD": preload, _REEXEC_MARK: "1"}
    os.execve(sys.executable, [sys.executable, "-m", "ds3d_service", *argv], env)


def describe(wanted: str) -> str:
    """A log line on the allocator in use (wanted: the `allocator` setting), with what to do
    when it is glibc's against the setting."""
    name = loaded_allocator()
    if name != "glibc" or wanted == "system":
        return f"memory allocator: {name}"
    return (
        "memory allocator: glibc malloc, whose resident memory grows with the image sizes "
        "served; install jemalloc (Debian: libjemalloc2) and ds3d-serve runs on it"
    )
