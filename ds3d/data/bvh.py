"""Biovision Hierarchy (.bvh, .bvh.gz) motion capture: a strict reader, forward kinematics, and a
writer (format_bvh: what parse_bvh reads back as the same BvhMotion).

Conventions (those of the format, as read by MotionBuilder, Blender and the CMU conversions):
- A joint's CHANNELS are applied in the declared order. The local rotation is the product of
  the per-channel rotations in that order, R = R_c1 @ R_c2 @ R_c3 (intrinsic rotations about the
  joint's own axes, angles in degrees, matrices acting on column vectors), so
  "Zrotation Xrotation Yrotation" means R = Rz @ Rx @ Ry.
- A position channel sets that axis of the joint's local translation, replacing the OFFSET
  component (root OFFSETs are usually zero, so for the usual files this only moves the root).
- global rotation = parent global rotation @ local rotation;
  position = parent position + parent global rotation @ local translation.
- An End Site becomes a joint named "<parent>/End" with no channels.
"""

from __future__ import annotations

import gzip
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import NoReturn

import numpy as np

from ds3d.errors import DataFormatError

# Channel name -> (kind, axis index). The format spells them capitalised; other cases are
# accepted because some exporters write "xrotation".
_CHANNELS: dict[str, tuple[str, int]] = {
    f"{axis}{kind}": (kind, i) for kind in ("position", "rotation") for i, axis in enumerate("xyz")
}


@dataclass(frozen=True)
class BvhMotion:
    """One BVH file.

    names: J joint names, End Sites as "<parent>/End", in file (depth-first) order, so every
        parent precedes its children.
    parents: (J,) int64, index of each joint's parent, -1 for the root.
    offsets: (J, 3) float64, OFFSET of each joint in its parent's frame, file units.
    channels: J tuples of channel names as declared (empty for End Sites).
    frame_time: seconds between frames.
    motion: (F, C) float64, one row per frame, C = total number of channels, in channel
        declaration order (positions in file units, rotations in degrees).
    """

    names: tuple[str, ...]
    parents: np.ndarray
    offsets: np.ndarray
    channels: tuple[tuple[str, ...], ...]
    frame_time: float
    motion: np.ndarray

    @property
    def num_frames(self) -> int:
        return self.motion.shape[0]

    def index(self, name: str) -> int:
        """Index of the joint called `name` (KeyError naming the file's joints if absent)."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint {name!r}; joints are {', '.join(self.names)}") from None


def read_bvh(path: str | Path) -> BvhMotion:
    """Read a .bvh or .bvh.gz file (gzip is detected from the content, not the name).

    Raises DataFormatError naming the file and line for anything malformed: a missing
    HIERARCHY or MOTION section, an unknown channel, a bad number, a frame with the wrong
    number of values, fewer or more frames than declared, a truncated or corrupt gzip stream.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
        if raw[:2] == b"\x1f\x8b":
            raw = gzip.decompress(raw)
        text = raw.decode("utf-8")
    except FileNotFoundError:
        raise DataFormatError(f"{path}: no such file") from None
    except (OSError, EOFError, zlib.error) as exc:  # gzip raises all three for broken streams
        raise DataFormatError(f"{path}: corrupt or truncated gzip stream ({exc})") from exc
    except UnicodeDecodeError as exc:
        raise DataFormatError(f"{path}: not a text file ({exc})") from exc
    return parse_bvh(text, source=str(path))


def parse_bvh(text: str, source: str = "<string>") -> BvhMotion:
    """Parse the text of a BVH file; `source` names it in error messages. See read_bvh."""
    lines = text.splitlines()
    motion_line = next((i for i, line in enumerate(lines) if line.strip() == "MOTION"), None)
    if motion_line is None:
        raise DataFormatError(f"{source}: no MOTION section")
    hierarchy = _parse_hierarchy(lines[:motion_line], source)
    num_channels = sum(len(c) for c in hierarchy[3])
    frame_time, motion = _parse_motion(lines, motion_line + 1, num_channels, source)
    return BvhMotion(*hierarchy, frame_time=frame_time, motion=motion)


def format_bvh(motion: BvhMotion, decimals: int = 4) -> str:
    """The text of a BVH file of `motion` (tab-indented, numbers to `decimals` places): its
    joints depth-first as in motion.names, an End Site for each "<parent>/End"."""
    lines = ["HIERARCHY"]
    children = [
        [c for c, p in enumerate(motion.parents) if p == j] for j in range(len(motion.names))
    ]

    def number(value: float) -> str:
        return f"{value:.{decimals}f}"

    def block(j: int, depth: int) -> None:
        pad = "\t" * depth
        offset = " ".join(number(v) for v in motion.offsets[j])
        if motion.names[j].endswith("/End"):
            lines.extend([f"{pad}End Site", f"{pad}{{", f"{pad}\tOFFSET {offset}", f"{pad}}}"])
            return
        lines.append(f"{pad}{'ROOT' if depth == 0 else 'JOINT'} {motion.names[j]}")
        lines.extend([f"{pad}{{", f"{pad}\tOFFSET {offset}"])
        declared = motion.channels[j]
        lines.append(f"{pad}\tCHANNELS {len(declared)} {' '.join(declared)}")
        for child in children[j]:
            block(child, depth + 1)
        lines.append(f"{pad}}}")

    block(0, 0)
    lines += ["MOTION", f"Frames: {motion.num_frames}", f"Frame Time: {motion.frame_time:.6f}"]
    lines += [" ".join(number(v) for v in row) for row in motion.motion]
    return "\n".join(lines) + "\n"


def _parse_hierarchy(
    lines: list[str], source: str
) -> tuple[tuple[str, ...], np.ndarray, np.ndarray, tuple[tuple[str, ...], ...]]:
    tokens = [(tok, n + 1) for n, line in enumerate(lines) for tok in line.split()]
    pos = 0

    def fail(message: str, line: int) -> NoReturn:
        raise DataFormatError(f"{source}, line {line}: {message}")

    def take(expected: str | None = None) -> tuple[str, int]:
        nonlocal pos
        if pos == len(tokens):
            last = tokens[-1][1] if tokens else 1
            fail(f"hierarchy ends early{f', expected {expected!r}' if expected else ''}", last)
        tok, line = tokens[pos]
        pos += 1
        if expected is not None and tok != expected:
            fail(f"expected {expected!r}, found {tok!r}", line)
        return tok, line

    def number() -> float:
        tok, line = take()
        try:
            value = float(tok)
        except ValueError:
            fail(f"bad number {tok!r}", line)
        if not np.isfinite(value):
            fail(f"non-finite number {tok!r}", line)
        return value

    if not tokens or tokens[0][0] != "HIERARCHY":
        fail("missing HIERARCHY header", tokens[0][1] if tokens else 1)
    pos = 1
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []

    def joint(parent: int, end_site: bool) -> None:
        name, line = (f"{names[parent]}/End", tokens[pos - 1][1]) if end_site else take()
        if name in names:
            fail(f"joint name {name!r} used twice", line)
        index = len(names)
        names.append(name)
        parents.append(parent)
        take("{")
        take("OFFSET")
        offsets.append([number(), number(), number()])
        declared: tuple[str, ...] = ()
        if not end_site:
            take("CHANNELS")
            count_tok, line = take()
            if not count_tok.isdigit():
                fail(f"bad channel count {count_tok!r}", line)
            taken = [take() for _ in range(int(count_tok))]
            for ch, line in taken:
                if ch.lower() not in _CHANNELS:
                    fail(f"unknown channel {ch!r} for joint {name!r}", line)
            declared = tuple(ch for ch, _ in taken)
        channels.append(declared)
        while True:
            tok, line = take()
            if tok == "}":
                return
            if end_site:
                fail(f"expected '}}' closing End Site of {names[parent]!r}, found {tok!r}", line)
            if tok == "JOINT":
                joint(index, end_site=False)
            elif tok == "End":
                tok, line = take()
                if tok.lower() != "site":  # some exporters write "End site"
                    fail(f"expected 'Site' after 'End', found {tok!r}", line)
                joint(index, end_site=True)
            else:
                fail(f"expected JOINT, End Site or '}}' in joint {name!r}, found {tok!r}", line)

    take("ROOT")
    joint(-1, end_site=False)
    if pos != len(tokens):
        fail(f"unexpected {tokens[pos][0]!r} after the root joint", tokens[pos][1])
    return (
        tuple(names),
        np.asarray(parents, dtype=np.int64),
        np.asarray(offsets, dtype=np.float64),
        tuple(channels),
    )


def _parse_motion(
    lines: list[str], start: int, num_channels: int, source: str
) -> tuple[float, np.ndarray]:
    header: dict[str, float] = {}
    row = start
    for key in ("Frames:", "Frame Time:"):
        while row < len(lines) and not lines[row].strip():
            row += 1
        if row == len(lines) or not lines[row].strip().startswith(key):
            raise DataFormatError(f"{source}, line {row + 1}: expected {key!r}")
        value = lines[row].strip()[len(key) :].strip()
        try:
            header[key] = float(value)
        except ValueError:
            raise DataFormatError(f"{source}, line {row + 1}: bad {key} value {value!r}") from None
        row += 1
    num_frames, frame_time = header["Frames:"], header["Frame Time:"]
    if num_frames != int(num_frames) or num_frames < 0:
        raise DataFormatError(f"{source}, line {start + 1}: bad frame count {num_frames}")
    if not frame_time > 0:
        raise DataFormatError(f"{source}, line {row}: frame time must be > 0, got {frame_time}")

    body = lines[row:]
    motion = None
    if any(line.strip() for line in body):
        try:  # the C parser; on any failure the slow scan below finds the line to blame
            motion = np.loadtxt(body, dtype=np.float64, ndmin=2, comments=None)
        except ValueError:
            pass
    else:
        motion = np.empty((0, num_channels))
    if motion is None or motion.shape[1] != num_channels or not np.isfinite(motion).all():
        _raise_bad_row(body, row, num_channels, source)
    if motion.shape[0] != int(num_frames):
        raise DataFormatError(
            f"{source}: header declares {int(num_frames)} frames, found {motion.shape[0]} "
            f"(lines {row + 1}-{len(lines)})"
        )
    return frame_time, motion


def _raise_bad_row(body: list[str], first_line: int, num_channels: int, source: str) -> NoReturn:
    for line_no, line in enumerate(body, start=first_line + 1):
        values = line.split()
        if values and len(values) != num_channels:
            raise DataFormatError(
                f"{source}, line {line_no}: {len(values)} values, the hierarchy declares "
                f"{num_channels} channels"
            )
        for v in values:
            try:
                ok = np.isfinite(float(v))
            except ValueError:
                ok = False
            if not ok:
                raise DataFormatError(f"{source}, line {line_no}: bad number {v!r}")
    raise DataFormatError(f"{source}, line {first_line + 1}: unreadable MOTION rows")


def _axis_rotations(angles: np.ndarray, axis: int) -> np.ndarray:
    """(F,) radians about x/y/z (axis 0/1/2) -> (F, 3, 3) right-handed rotation matrices."""
    c, s = np.cos(angles), np.sin(angles)
    out = np.zeros((angles.shape[0], 3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    out[:, axis, axis] = 1
    out[:, i, i] = c
    out[:, j, j] = c
    out[:, i, j] = -s
    out[:, j, i] = s
    return out


def global_transforms(
    motion: BvhMotion, frames: slice | np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Global rotations and positions of every joint (End Sites included).

    frames: which rows of motion.motion (a slice or an index array); all when None.
    Returns (rotations (F, J, 3, 3) float64, positions (F, J, 3) float64 in file units), in the
    file's world axes. Vectorised over frames; loops over the J joints only.
    """
    data = motion.motion if frames is None else motion.motion[frames]
    num = data.shape[0]
    rotations = np.empty((num, len(motion.names), 3, 3))
    positions = np.empty((num, len(motion.names), 3))
    column = 0
    for j, (parent, declared) in enumerate(zip(motion.parents, motion.channels, strict=True)):
        local_rot = np.broadcast_to(np.eye(3), (num, 3, 3))
        translation = np.broadcast_to(motion.offsets[j], (num, 3)).copy()
        for name in declared:
            kind, axis = _CHANNELS[name.lower()]
            values = data[:, column]
            column += 1
            if kind == "position":
                translation[:, axis] = values
            else:
                local_rot = local_rot @ _axis_rotations(np.radians(values), axis)
        if parent < 0:
            rotations[:, j] = local_rot
            positions[:, j] = translation
        else:
            rotations[:, j] = rotations[:, parent] @ local_rot
            positions[:, j] = positions[:, parent] + np.einsum(
                "fab,fb->fa", rotations[:, parent], translation
            )
    return rotations, positions


def forward_kinematics(motion: BvhMotion, frames: slice | np.ndarray | None = None) -> np.ndarray:
    """Joint positions (F, J, 3) float32 in the file's units and axes, joints as motion.names.

    frames: which rows of motion.motion (a slice or an index array); all when None.
    """
    return global_transforms(motion, frames)[1].astype(np.float32)
