"""ds3d.util.progress: bars only on a terminal, never with `ds3d --quiet`."""

from __future__ import annotations

import sys

import ds3d.util.progress
from ds3d.util.progress import progress, set_quiet


def test_a_bar_shows_on_a_terminal_only_and_never_when_quiet(monkeypatch):
    monkeypatch.setattr(ds3d.util.progress, "_quiet", False)  # restored after the test
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
    with progress(total=3, unit="img") as bar:
        assert bar.disable
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    with progress(total=3, unit="img") as bar:
        assert not bar.disable
        bar.update(3)
        assert bar.n == 3
    set_quiet(True)
    with progress(total=3, unit="img") as bar:
        assert bar.disable


def test_a_disabled_bar_passes_its_items_through(monkeypatch):
    monkeypatch.setattr(ds3d.util.progress, "_quiet", True)
    assert list(progress(range(4), desc="trees", unit="tree")) == [0, 1, 2, 3]
