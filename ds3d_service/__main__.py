"""`python -m ds3d_service` (console script `ds3d-serve`): run the HTTP service with uvicorn.

Settings come from DS3D_* env vars (ds3d_service/settings.py); each also has a flag, which overrides
its env var. The flags are made from the Settings fields by pydantic-settings' CLI support, so a new
field is a new flag, with its description as help.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys

from pydantic import ValidationError
from pydantic_settings import CliSettingsSource

from ds3d.util.memory import map_large_buffers
from ds3d_service.access.keys import InvalidKeys
from ds3d_service.allocator import run_under_jemalloc
from ds3d_service.settings import Settings

ONEDNN_CACHE_ENTRIES = 1024
# Under glibc's malloc, buffers from this size on get their own mappings, given back when freed:
# the 2D stage's buffers vary with the images and the batches, and glibc's arenas kept the free
# memory around them (docs/service-results.md, memory; jemalloc needs no such bound).
GLIBC_MMAP_THRESHOLD = 2**20


def parse_settings(argv: list[str] | None = None) -> Settings:
    """The Settings of a `ds3d-serve` command line (argv: the arguments, default sys.argv[1:]):
    flags over DS3D_* env vars over defaults. Exits (status 2) with a message on a bad value."""
    parser = argparse.ArgumentParser(
        prog="ds3d-serve",
        description=__doc__.splitlines()[0],
        epilog="Each setting is a flag and a DS3D_* env var: flags override env vars, which "
        "override the defaults.",
    )
    cli: CliSettingsSource[argparse.ArgumentParser] = CliSettingsSource(
        Settings,
        root_parser=parser,
        cli_kebab_case=True,
        cli_show_env_vars=True,
        cli_hide_none_type=True,
    )
    args = sys.argv[1:] if argv is None else argv
    try:
        return Settings(_cli_settings_source=cli(args=args))
    except ValidationError as exc:
        parser.error(_invalid(exc))


def _invalid(exc: ValidationError) -> str:
    """One line per bad setting, named by its flag and env var:
    `--port / DS3D_PORT: Input should be less than or equal to 65535 (got '70000')`."""
    prefix = Settings.model_config.get("env_prefix", "")
    lines = []
    for err in exc.errors(include_url=False):
        name = "_".join(str(part) for part in err["loc"])
        flag, env = "--" + name.replace("_", "-"), prefix + name.upper()
        lines.append(f"{flag} / {env}: {err['msg']} (got {err['input']!r})")
    return "invalid settings:\n  " + "\n  ".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    settings = parse_settings(args)
    if settings.allocator == "jemalloc":
        run_under_jemalloc(args)  # returns when jemalloc is missing or already loaded
    # Before torch loads: keep OpenMP to the configured threads too.
    os.environ.setdefault("OMP_NUM_THREADS", str(settings.torch_threads))
    # oneDNN keeps the primitives of the last ONEDNN_CACHE_ENTRIES layer shapes it ran; one
    # missed costs about 0.5 ms to create, some 10 ms for the joint network on a new input
    # shape, several times its convolutions' own time. The network's inputs are padded to a
    # few size buckets (jointnet.NET_BUCKET_STEPS): all 1,000 LSP test images make 48 input
    # shapes and 687 primitives, which the cache holds, so that it stops growing once they
    # have been met (docs/service-results.md, soak).
    os.environ.setdefault("ONEDNN_PRIMITIVE_CACHE_CAPACITY", str(ONEDNN_CACHE_ENTRIES))
    map_large_buffers(GLIBC_MMAP_THRESHOLD)

    import uvicorn

    from ds3d_service.app import create_app

    logging.basicConfig(level=settings.log_level.upper(), format="%(asctime)s %(name)s %(message)s")
    try:
        app = create_app(settings)
    except InvalidKeys as exc:
        print(f"ds3d-serve: {exc}", file=sys.stderr)
        return 2
    uvicorn.run(
        app,
        host=settings.host,
        port=settings.port,
        log_level=settings.log_level,
        # ds3d_service.access.rules logs each request, without its query or any key
        access_log=False,
        limit_concurrency=settings.max_connections,
        # seconds as a float (uvicorn's hint says int; its timer takes any number)
        timeout_keep_alive=settings.keep_alive_s,  # type: ignore[arg-type]
        # a backstop: the app refuses a head over max_header_bytes with a 431 that names it
        h11_max_incomplete_event_size=4 * settings.max_header_bytes,
        # Let in-flight requests finish (they are bounded by the request timeout).
        timeout_graceful_shutdown=int(settings.request_timeout_s) + 5,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
