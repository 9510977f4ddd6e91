"""The `ds3d` command line: the parser and its `--set` machinery in ds3d.cli.parser, one module
per area (lift, image2d, pipeline, batch, bench, data). It imports the library; nothing in the
library imports it."""

from ds3d.cli.parser import main

__all__ = ["main"]
