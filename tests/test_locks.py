"""The locks in requirements/ (written by `make lock`): each names every dependency of the extras
it stands for, pinned with == inside pyproject.toml's range and with its hashes; torch and CUDA
packages stay out; a package shared by two locks has one version; torch is one version
everywhere."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
PROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
# Each lock and the extras it holds besides the runtime dependencies.
LOCKS = {"dev.txt": ("service", "dev"), "service.txt": ("service",), "ray.txt": ("service", "ray")}
PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+?)(?:\s*;.*?)?\s*\\?$")
HASH = re.compile(r"--hash=sha256:[0-9a-f]{64}\b")


def read_lock(name: str) -> dict[str, tuple[Version, int]]:
    """{canonical name: (pinned version, number of hashes)}; fails on a requirement line that is
    not a plain == pin."""
    pins: dict[str, tuple[Version, int]] = {}
    current = None
    for line in (ROOT / "requirements" / name).read_text().splitlines():
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        if line[0].isspace():  # a continuation: hashes of the pin above
            assert current is not None, f"{name}: {line!r} follows no pin"
            version, hashes = pins[current]
            pins[current] = (version, hashes + len(HASH.findall(line)))
            continue
        match = PIN.match(stripped)
        assert match, f"{name}: not a pin: {line!r}"
        current = canonicalize_name(match[1])
        pins[current] = (Version(match[2]), len(HASH.findall(line)))
    return pins


def declared(extras: tuple[str, ...]) -> list[Requirement]:
    extra = PROJECT["optional-dependencies"]
    return [Requirement(d) for d in PROJECT["dependencies"] + [d for e in extras for d in extra[e]]]


@pytest.mark.parametrize("lock", sorted(LOCKS))
def test_lock_pins_every_declared_dependency_with_hashes(lock):
    pins = read_lock(lock)
    assert pins, lock
    for name, (version, hashes) in pins.items():
        assert hashes >= 1, f"{lock}: {name}=={version} has no --hash"
        assert not name.startswith(("nvidia-", "triton")), f"{lock}: CUDA package {name}"
    assert "torch" not in pins, f"{lock}: torch is installed before the lock, not from it"
    for req in declared(LOCKS[lock]):
        name = canonicalize_name(req.name)
        if name == "torch":
            continue
        assert name in pins, f"{lock}: {req} is not locked (make lock)"
        assert req.specifier.contains(pins[name][0], prereleases=True), (
            f"{lock}: {name}=={pins[name][0]} is outside pyproject.toml's {req} (make lock)"
        )


def test_locks_agree():
    locks = {lock: read_lock(lock) for lock in LOCKS}
    dev = locks["dev.txt"]
    for lock, pins in locks.items():
        for name, (version, _) in pins.items():
            if name in dev:
                assert version == dev[name][0], f"{lock}: {name}=={version}, dev.txt {dev[name][0]}"


def test_torch_is_one_version():
    """The version the locks were resolved against is the one the Makefile and the image install,
    and inside pyproject.toml's range."""
    pins = re.findall(r"^torch==(\S+)$", (ROOT / "requirements" / "torch.txt").read_text(), re.M)
    assert len(pins) == 1, pins
    locked = Version(pins[0])
    (torch,) = [r for r in declared(()) if r.name == "torch"]
    assert torch.specifier.contains(locked)
    makefile = re.findall(r"torch==([0-9][0-9.]*)", (ROOT / "Makefile").read_text())
    dockerfile = re.findall(r"ARG TORCH_VERSION=(\S+)", (ROOT / "Dockerfile").read_text())
    assert makefile and dockerfile
    assert {Version(v) for v in makefile + dockerfile} == {Version(locked.base_version)}
