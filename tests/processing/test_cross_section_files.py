"""Cross-section files in the styles hydrologists' spreadsheets export."""

import numpy as np
import pytest

from fieldtool.errors import InputFileError
from fieldtool.processing.cross_section import load_cross_section, parse_xy_text

ST = [0.0, 5.5, 12.0]
EL = [10.6, 8.25, 10.5]


@pytest.mark.parametrize(
    "text",
    [
        "0,0;10,6\n5,5;8,25\n12;10,5\n",  # European: ';' between fields, decimal commas
        "station;elevation\n0,0;10,6\n5,5;8,25\n12,0;10,5\n",
        "station\televation\n0,0\t10,6\n5,5\t8,25\n12\t10,5\n",  # tabs with decimal commas
        "station_m,elevation_m\n0,10.6\n5.5,8.25\n12,10.5\n",
        "0 10.6\n5.5   8.25\n12 10.5\n",
        "Station (cm);Elevation (m)\n0;10,6\n550;8,25\n1200;10,5\n",  # units in the header
        "Elevation (m),Distance (m)\n10.6,0\n8.25,5.5\n10.5,12\n",  # columns named in another order
        "# survey 2026-05-01\nPoint;Station [m];Z [m]\n1;0;10,6\n2;5,5;8,25\n3;12;10,5\n",
    ],
)
def test_spreadsheet_text_styles_read_right(text):
    cs = parse_xy_text(text)
    assert np.allclose(cs.station, ST) and np.allclose(cs.elevation, EL)


@pytest.mark.parametrize(
    "text, match",
    [
        ("0,10\n5,8,1\n12,10\n", "line 2: 3 fields"),
        ("station;elevation\n0;10\n5;abc\n", "line 3: 'abc' is not a number"),
        ("Depth (m);Station (m)\n0;0\n1;5\n", "line 1: the header names a depth column"),
        ("Station (in);Elevation (m)\n0;0\n1;5\n", "line 1: unit 'in'"),
        ("0;10\n", "1 data row"),
    ],
)
def test_bad_rows_are_named_by_line(text, match):
    with pytest.raises(InputFileError, match=match):
        parse_xy_text(text)


def test_windows_1252_and_utf16_files(tmp_path):
    p = tmp_path / "cs.csv"
    p.write_bytes("Abscisse (m);Élévation (m)\n0;10,6\n5,5;8,25\n12;10,5\n".encode("cp1252"))
    cs = load_cross_section(p)
    assert np.allclose(cs.elevation, EL)
    p.write_bytes("station\televation\n0\t10.6\n5.5\t8.25\n12\t10.5\n".encode("utf-16"))
    assert np.allclose(load_cross_section(p).station, ST)
    p.write_bytes(b"\x00\x01\x02binary\x00")
    with pytest.raises(InputFileError, match="binary"):
        load_cross_section(p)


@pytest.mark.parametrize("suffix, engine", [(".xlsx", "openpyxl"), (".ods", "odf")])
def test_workbooks(tmp_path, suffix, engine):
    import pandas as pd

    p = tmp_path / f"cs{suffix}"
    pd.DataFrame({"Station (m)": ST, "Elevation (m)": EL}).to_excel(p, index=False, engine=engine)
    cs = load_cross_section(p)
    assert np.allclose(cs.station, ST) and np.allclose(cs.elevation, EL)
    p.write_bytes(b"not a workbook")
    with pytest.raises(InputFileError, match="workbook"):
        load_cross_section(p)
