"""`python -m ds3d.cli ...`: the `ds3d` command without its installed entry point."""

from ds3d.cli.parser import main

raise SystemExit(main())
