"""Checks the "At a glance" tables of the results docs against the JSON reports they cite.

    python -m tools.check_results [-v] [DOC.md ...]     # make check-results

Default docs: docs/RESULTS.md and docs/service-results.md. Exit status 0 when every figure
matches its JSON, 1 with one line per problem otherwise; -v also lists each figure that matches,
with the commit and date its JSON records.

The table is the first Markdown table under the heading "## At a glance". Its columns "what",
"figure" and "JSON" (by header, any order, other columns ignored) are read; in each row:

- the JSON cell: a link to a JSON file (relative to the doc), then one code span per figure, the
  figure's key in that file as a jq path (`.variants.clean.pose_error`, `.batches."64".x`,
  `.rows[1].images_per_s`: keys other than identifiers quoted, list indices in brackets). A key
  followed by `×100` (or `x100`) is scaled by 100 before the comparison: the JSON holds a
  fraction, the doc shows a percentage. A second link starts the keys of a second file.
- the figure cell: every number in it, in order, one per key ("1,362" is 1362; a number glued
  to a letter, "@", "/" or "." before it, as in p99 or PCK@0.2, is not a figure). Bold, units and
  words between them are free.

A row fails when its figure cell and its keys differ in number, when a JSON or a key is missing,
when a JSON records no provenance (its "provenance" object, ds3d.util.provenance: commit, date,
machine with its cores and CPU model), or when a shown figure differs from the JSON's value by
more than half a unit of its last shown decimal (53.5 shows 53.45 to 53.55; 973 shows 972.5 to
973.5).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = (ROOT / "docs" / "RESULTS.md", ROOT / "docs" / "service-results.md")
HEADING = "## at a glance"
COLUMNS = ("what", "figure", "json")
PROVENANCE_FIELDS = ("commit", "machine", "date")
MACHINE_FIELDS = ("cores", "cpu_model")

NUMBER = re.compile(r"(?<![\w.@/])([+\-−]?)(\d{1,3}(?:,\d{3})+(?:\.\d+)?|\d+(?:\.\d+)?)")
LINK_OR_KEY = re.compile(
    r"\[[^\]]*\]\((?P<link>[^)\s]+)\)|`(?P<key>[^`]+)`(?:\s*[×x](?P<scale>\d+(?:\.\d+)?))?"
)
KEY_STEP = re.compile(
    r'\.(?P<name>[A-Za-z_]\w*)|\."(?P<quoted>(?:[^"\\]|\\.)*)"|\[(?P<index>-?\d+)\]'
)

Key = tuple[str | int, ...]
Loader = Callable[[Path], object]


@dataclass(frozen=True)
class Row:
    """One row of an at-a-glance table: its line in the doc and its three cells."""

    line: int
    what: str
    figure: str
    json: str


@dataclass(frozen=True)
class Shown:
    """A number as the doc shows it: its value and how many decimals it shows."""

    text: str
    value: float
    decimals: int


@dataclass(frozen=True)
class Ref:
    """A figure's source: a JSON file (as linked, relative to the doc), a key path, a scale."""

    file: str
    key: str
    scale: float = 1.0


def split_cells(line: str) -> list[str]:
    """The cells of a Markdown table line, stripped (`\\|` is a pipe inside a cell)."""
    body = line.strip()
    body = body.removeprefix("|")
    body = body[:-1] if body.endswith("|") and not body.endswith("\\|") else body
    return [cell.replace("\\|", "|").strip() for cell in re.split(r"(?<!\\)\|", body)]


def glance_rows(text: str) -> list[Row]:
    """The rows of the first table under the "## At a glance" heading of a doc. Raises
    ValueError where the heading, the table or one of its columns (COLUMNS) is missing."""
    lines = text.splitlines()
    start = next((i for i, line in enumerate(lines) if line.strip().lower() == HEADING), None)
    if start is None:
        raise ValueError("no '## At a glance' heading")
    table = []
    for i in range(start + 1, len(lines)):
        line = lines[i].strip()
        if line.startswith("#"):
            break
        if line.startswith("|"):
            table.append((i + 1, line))
        elif table:
            break
    if len(table) < 2:
        raise ValueError("no table under '## At a glance'")
    header = [cell.lower() for cell in split_cells(table[0][1])]
    missing = [name for name in COLUMNS if name not in header]
    if missing:
        raise ValueError(f"the at-a-glance table has no column {', '.join(missing)}")
    at = {name: header.index(name) for name in COLUMNS}
    rows = []
    for number, line in table[2:]:  # past the header and its |---| line
        cells = split_cells(line)
        cells += [""] * (len(header) - len(cells))
        rows.append(Row(number, cells[at["what"]], cells[at["figure"]], cells[at["json"]]))
    return rows


def shown_figures(cell: str) -> list[Shown]:
    """The numbers of a figure cell, in order."""
    figures = []
    for match in NUMBER.finditer(cell):
        sign, digits = match.groups()
        value = float(digits.replace(",", ""))
        decimals = len(digits.partition(".")[2])
        figures.append(Shown(match.group(0), -value if sign in ("-", "−") else value, decimals))
    return figures


def references(cell: str) -> list[Ref]:
    """The keys of a JSON cell, each with the file of the link before it. Raises ValueError
    for a key before any link."""
    refs: list[Ref] = []
    file = None
    for match in LINK_OR_KEY.finditer(cell):
        if match.group("link") is not None:
            file = match.group("link")
            continue
        if file is None:
            raise ValueError(f"key {match.group('key')} before any JSON link")
        scale = float(match.group("scale")) if match.group("scale") else 1.0
        refs.append(Ref(file, match.group("key").strip(), scale))
    return refs


def parse_key(key: str) -> Key:
    """A jq path (`.a.b`, `."pck@0.2"`, `[1]`) as the keys and indices it steps through.
    Raises ValueError where it is not one."""
    steps: list[str | int] = []
    at = 0
    while at < len(key):
        match = KEY_STEP.match(key, at)
        if match is None:
            raise ValueError(f"{key} is not a jq path (quote keys other than identifiers)")
        if match.group("name") is not None:
            steps.append(match.group("name"))
        elif match.group("quoted") is not None:
            steps.append(json.loads(f'"{match.group("quoted")}"'))
        else:
            steps.append(int(match.group("index")))
        at = match.end()
    if not steps:
        raise ValueError("an empty key")
    return tuple(steps)


def lookup(report: object, key: Key) -> object:
    """The value at `key` in a JSON report. Raises KeyError naming the first step missing."""
    value = report
    for step in key:
        if isinstance(step, int) and isinstance(value, list) and -len(value) <= step < len(value):
            value = value[step]
        elif isinstance(step, str) and isinstance(value, dict) and step in value:
            value = value[step]
        else:
            raise KeyError(step)
    return value


def matches(shown: Shown, value: float) -> bool:
    """Whether `value` rounds to the figure as shown: within half a unit of its last decimal."""
    half = 0.5 * 10.0**-shown.decimals
    return abs(value - shown.value) <= half * (1 + 1e-9)


def provenance_problem(report: object) -> str | None:
    """What a report's provenance lacks (None when it has a commit, a date and a machine with
    its cores and CPU model)."""
    record = report.get("provenance") if isinstance(report, dict) else None
    if not isinstance(record, dict):
        return "records no provenance (commit, machine, date)"
    missing = [name for name in PROVENANCE_FIELDS if not record.get(name)]
    machine = record.get("machine")
    if isinstance(machine, dict):
        missing += [f"machine.{name}" for name in MACHINE_FIELDS if not machine.get(name)]
    return f"provenance without {', '.join(missing)}" if missing else None


def load_json(path: Path) -> object:
    return json.loads(path.read_text())


def check_row(row: Row, base: Path, load: Loader = load_json) -> tuple[list[str], list[str]]:
    """(problems, figures that match) of one row; `base`: the doc's folder, which links are
    relative to."""
    name = short(row.what)
    try:
        refs = references(row.json)
    except ValueError as error:
        return [f"{name}: {error}"], []
    if not refs:
        return [f"{name}: no JSON key named"], []
    figures = shown_figures(row.figure)
    problems: list[str] = []
    if len(figures) != len(refs):
        shown = ", ".join(f.text for f in figures) or "none"
        problems.append(f"{name}: {len(figures)} figures shown ({shown}), {len(refs)} keys named")
    reports: dict[str, object] = {}
    ok = []
    for index, ref in enumerate(refs):
        file = display(base / ref.file)
        if ref.file not in reports:
            try:
                reports[ref.file] = load(base / ref.file)
            except FileNotFoundError:
                reports[ref.file] = None
                problems.append(f"{name}: {file} does not exist")
            except (OSError, ValueError) as error:
                reports[ref.file] = None
                problems.append(f"{name}: {file} unreadable ({error})")
            else:
                lacking = provenance_problem(reports[ref.file])
                if lacking:
                    problems.append(f"{name}: {file} {lacking}")
        report = reports[ref.file]
        if report is None:
            continue
        try:
            value = lookup(report, parse_key(ref.key))
        except ValueError as error:
            problems.append(f"{name}: {error}")
            continue
        except KeyError as error:
            problems.append(f"{name}: {file} has no {ref.key} (no {error})")
            continue
        if isinstance(value, bool) or not isinstance(value, int | float):
            problems.append(f"{name}: {file} {ref.key} is not a number: {value!r}")
            continue
        scaled = value * ref.scale
        if index >= len(figures):
            continue
        figure = figures[index]
        if matches(figure, scaled):
            ok.append(f"{name}: {figure.text} = {file} {ref.key} {scaled:g}{stamp(report)}")
        else:
            problems.append(f"{name}: shows {figure.text}, {file} {ref.key} holds {scaled:g}")
    return problems, ok


def check_doc(path: Path, load: Loader = load_json) -> tuple[list[str], list[str]]:
    """(problems, figures that match) of a doc's at-a-glance table, each line prefixed with the
    doc and the row's line."""
    try:
        rows = glance_rows(path.read_text())
    except (OSError, ValueError) as error:
        return [f"{display(path)}: {error}"], []
    problems, ok = [], []
    for row in rows:
        bad, good = check_row(row, path.parent, load)
        problems += [f"{display(path)}:{row.line}: {line}" for line in bad]
        ok += [f"{display(path)}:{row.line}: {line}" for line in good]
    return problems, ok


def display(path: Path) -> Path:
    """A path as the checkout names it where it lies in the checkout."""
    resolved = Path(os.path.normpath(path.absolute()))
    return resolved.relative_to(ROOT) if resolved.is_relative_to(ROOT) else path


def short(what: str, width: int = 70) -> str:
    """A row's "what" cell without Markdown emphasis or code marks, cut to `width`."""
    plain = re.sub(r"[*`]", "", re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", what)).strip()
    return plain if len(plain) <= width else plain[: width - 1] + "…"


def stamp(report: object) -> str:
    """ " (commit, date)" from a report's provenance, for -v."""
    record = report.get("provenance") if isinstance(report, dict) else None
    if not isinstance(record, dict):
        return ""
    return f" ({str(record.get('commit'))[:7]}, {record.get('date')})"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("docs", nargs="*", type=Path, default=list(DOCS))
    parser.add_argument("-v", "--verbose", action="store_true", help="list the matches too")
    args = parser.parse_args(argv)
    problems: list[str] = []
    for doc in args.docs:
        bad, good = check_doc(doc.resolve())
        problems += bad
        for line in good if args.verbose else ():
            print(f"ok {line}")
    for line in problems:
        print(line, file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
