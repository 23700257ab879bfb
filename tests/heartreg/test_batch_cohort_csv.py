"""A cohort CSV as spreadsheets save it (an audit of ``heartreg batch``): Excel's byte order mark, CRLF, ';' or tab
separators, UTF-16, quoted paths with spaces and non-ASCII letters, blank rows, the empty columns after the last
used one; and one line naming the row for what cannot be read (a file in the Windows code page, a name used twice).

Only the cohort is read here: no study runs, no cluster starts.
"""

from __future__ import annotations

import pytest

from heartreg.batch import CohortError, read_cohort
from heartreg.cli import main

ROWS = [("pig1", "studies/pig 1", "sessions/pig 1"), ("mueller", "studies/M\u00fcller Hans", ""),
        ("pig3", "studies/pig3", "sessions/pig3")]


def _excel(path, delimiter=",", encoding="utf-8-sig", header=("case", "study", "session"), rows=ROWS, blank=True):
    """A cohort as a spreadsheet writes it: every path quoted, CRLF, a blank row after the first case."""
    lines = [delimiter.join(header)]
    for i, row in enumerate(rows):
        lines.append(delimiter.join(f'"{c}"' if c else "" for c in row))
        if blank and i == 0:
            lines.append(delimiter.join([""] * len(header)))
    path.write_bytes(("\r\n".join(lines) + "\r\n").encode(encoding))
    return path


def _read(path):
    return [(c.name, c.study, c.session) for c in read_cohort(path)]


@pytest.mark.parametrize(("delimiter", "encoding"), [(",", "utf-8-sig"), (";", "utf-8-sig"), ("\t", "utf-16"),
                                                     (";", "utf-8")],
                         ids=["comma-bom", "semicolon-bom", "tab-utf16", "semicolon"])
def test_a_spreadsheets_csv_reads_as_the_same_cases(tmp_path, delimiter, encoding):
    cases = _read(_excel(tmp_path / "cohort.csv", delimiter, encoding))
    base = tmp_path.resolve()
    expected = [(n, str(base / s), str(base / x) if x else "") for n, s, x in ROWS]
    assert cases == expected  # paths relative to the CSV's folder, spaces and letters kept, the blank row skipped


def test_the_empty_columns_after_the_last_are_dropped_a_value_there_is_one_line(tmp_path):
    header = ("case", "study", "session", "", "")
    rows = [(*r, "", "") for r in ROWS]
    assert [c[0] for c in _read(_excel(tmp_path / "a.csv", ";", header=header, rows=rows))] == ["pig1", "mueller", "pig3"]
    rows[2] = (*ROWS[2], "", "pig 3 was sick")
    with pytest.raises(CohortError, match=r"a\.csv line 5: 'pig 3 was sick' is in column 5, which has no name"):
        read_cohort(_excel(tmp_path / "a.csv", ";", header=header, rows=rows))


def test_a_file_in_the_windows_code_page_is_one_line_naming_the_row(tmp_path, capsys):
    path = _excel(tmp_path / "cohort.csv", ";", "cp1252")
    with pytest.raises(CohortError, match=r"cohort\.csv line 4 is not UTF-8 text .*save it as 'CSV UTF-8'"):
        read_cohort(path)
    assert main(["batch", str(path), "-o", str(tmp_path / "out"), "--workers", "1", "-q"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "line 4 is not UTF-8" in err[0] and "Traceback" not in err[0]
    assert not (tmp_path / "out").exists()


def test_rows_are_named_by_their_line_in_the_file(tmp_path):
    rows = [ROWS[0], ("PIG1", "studies/other", "")]
    with pytest.raises(CohortError, match=r"case name 'PIG1' is used twice as 'pig1' .*\(line 2 and line 4\)"):
        read_cohort(_excel(tmp_path / "twice.csv", ";", rows=rows))
    rows = [ROWS[0], ("../up", "studies/x", "")]
    with pytest.raises(CohortError, match=r"bad\.csv line 4: case name '../up'"):
        read_cohort(_excel(tmp_path / "bad.csv", rows=rows))
