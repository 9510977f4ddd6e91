"""The at-a-glance tables of the results docs against their JSON reports (tools.check_results):
the parser and the comparison on small docs written here, then the real docs, whose every
figure must be its report's, measured with provenance."""

from __future__ import annotations

import json

import pytest

from tools import check_results
from tools.check_results import Row, Shown, check_doc, check_row, references, shown_figures

PROVENANCE = {
    "commit": "0123456789abcdef0123456789abcdef01234567",
    "dirty": False,
    "date": "2026-01-01T00:00:00+00:00",
    "machine": {"cpu_model": "Some CPU", "cores": 2},
    "command": "ds3d eval h36m",
}
REPORT = {
    "variants": {"clean": {"pose_error": 53.489, "database-proportions": 50.94}},
    "results": {"full/iteration1": {"pck@0.2": 0.791}},
    "batches": {"64": {"poses_per_s": 749.3}},
    "rows": [{"images_per_s": 14.91}, {"images_per_s": 1362.2}],
    "provenance": PROVENANCE,
}


def doc(tmp_path, rows: list[str], report: dict = REPORT) -> tuple:
    """A doc with an at-a-glance table of `rows` (figure | JSON cells) and results/r.json."""
    (tmp_path / "results").mkdir(exist_ok=True)
    (tmp_path / "results" / "r.json").write_text(json.dumps(report))
    table = ["| what | figure | JSON |", "|---|---|---|"]
    table += [f"| row {i} | {row} |" for i, row in enumerate(rows)]
    path = tmp_path / "DOC.md"
    path.write_text("# Doc\n\n## At a glance\n\nThe convention.\n\n" + "\n".join(table) + "\n")
    return check_doc(path)


def test_figures_in_a_cell():
    cell = "**1,362** / 8.89 px (p99, PCK@0.2, x0.5); +2.0 %, -0.4, 0.73x"
    assert [(f.value, f.decimals) for f in shown_figures(cell)] == [
        (1362.0, 0),
        (8.89, 2),
        (2.0, 1),
        (-0.4, 1),
        (0.73, 2),
    ]
    assert shown_figures("–") == []


def test_keys_follow_their_link():
    cell = '[a.json](results/a.json) `.x."pck@0.2"` ×100, `.y`; [b.json](b.json) `.rows[1].z` x100'
    refs = references(cell)
    assert [(r.file, r.key, r.scale) for r in refs] == [
        ("results/a.json", '.x."pck@0.2"', 100.0),
        ("results/a.json", ".y", 1.0),
        ("b.json", ".rows[1].z", 100.0),
    ]
    with pytest.raises(ValueError):
        references("`.x` [a.json](a.json)")


def test_jq_paths():
    assert check_results.parse_key('.a."b.c"[-1]._d') == ("a", "b.c", -1, "_d")
    with pytest.raises(ValueError):
        check_results.parse_key(".variants.database-proportions")  # jq needs the quotes


def test_matches_within_half_a_unit_of_the_last_decimal():
    assert check_results.matches(Shown("53.5", 53.5, 1), 53.489)
    assert not check_results.matches(Shown("53.4", 53.4, 1), 53.489)
    assert check_results.matches(Shown("1,362", 1362.0, 0), 1362.2)
    assert not check_results.matches(Shown("1,363", 1363.0, 0), 1362.2)


def test_a_table_that_matches(tmp_path):
    problems, ok = doc(
        tmp_path,
        [
            "**53.5 mm** | [r.json](results/r.json) `.variants.clean.pose_error`",
            '79.1 %; 749.3 / 1,362 | [r.json](results/r.json) `.results."full/iteration1".'
            '"pck@0.2"` ×100, `.batches."64".poses_per_s`, `.rows[1].images_per_s`',
        ],
    )
    assert problems == []
    assert len(ok) == 4


def test_a_rounding_mismatch(tmp_path):
    problems, _ = doc(
        tmp_path,
        [
            "53.4 mm | [r.json](results/r.json) `.variants.clean.pose_error`",
            '79.1 % | [r.json](results/r.json) `.results."full/iteration1"."pck@0.2"`',
        ],
    )
    assert len(problems) == 2
    assert "DOC.md:9: row 0: shows 53.4," in problems[0]
    assert "pose_error holds 53.489" in problems[0]
    assert "shows 79.1," in problems[1]  # a fraction shown as a percentage needs ×100


def test_a_missing_key_file_or_figure(tmp_path):
    problems, _ = doc(
        tmp_path,
        [
            "50.9 | [r.json](results/r.json) `.variants.clean.no_such_key`",
            "50.9 | [gone.json](results/gone.json) `.variants.clean.pose_error`",
            "– | [r.json](results/r.json) `.variants.clean.pose_error`",
            "50.9 | no link",
        ],
    )
    assert len(problems) == 4
    assert "has no .variants.clean.no_such_key (no 'no_such_key')" in problems[0]
    assert "results/gone.json does not exist" in problems[1]
    assert "0 figures shown (none), 1 keys named" in problems[2]
    assert "no JSON key named" in problems[3]


def test_a_report_without_provenance(tmp_path):
    old = {k: v for k, v in REPORT.items() if k != "provenance"}
    problems, ok = doc(
        tmp_path, ["53.5 | [r.json](results/r.json) `.variants.clean.pose_error`"], old
    )
    assert len(problems) == 1 and "records no provenance" in problems[0]
    assert len(ok) == 1  # the figure itself is the report's
    partial = {**REPORT, "provenance": {**PROVENANCE, "commit": None, "machine": {"cores": 2}}}
    row = Row(1, "row", "53.5", "[r.json](results/r.json) `.variants.clean.pose_error`")
    (tmp_path / "results" / "r.json").write_text(json.dumps(partial))
    problems, _ = check_row(row, tmp_path)
    assert len(problems) == 1
    assert problems[0].endswith("r.json provenance without commit, machine.cpu_model")


def test_a_doc_without_the_table(tmp_path):
    path = tmp_path / "DOC.md"
    path.write_text("# Doc\n\nNo table.\n")
    problems, _ = check_doc(path)
    assert len(problems) == 1 and "no '## At a glance' heading" in problems[0]


def test_the_docs_figures_are_their_reports():
    """Every at-a-glance figure of docs/RESULTS.md and docs/service-results.md is the value of
    the key its row names, in a JSON report that records its commit, machine and date. Fails
    until each figure is measured again by the command in its row."""
    problems = []
    for path in check_results.DOCS:
        problems += check_doc(path)[0]
    assert not problems, "\n".join(problems)
