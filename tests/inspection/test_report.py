"""The HTML report: tables, escaped text, image links, atomic write."""

from __future__ import annotations

import math

from gsfix_online.inspection.report import Report, Table, ViewRow, write_report


def test_report_has_tables_images_and_escapes_text(tmp_path):
    r = Report(
        "Repair <run>",
        tables=[
            Table("Novel views", ["stage", "PSNR"], [["raw 3DGS", 18.25], ["GSFixer", math.inf]])
        ],
        views=[
            ViewRow(
                "view 000",
                {"3DGS": "views/000/gs.png", "fixed": "views/000/fixed.png"},
                "holes 30%",
            )
        ],
        notes=["seed 0"],
    )
    out = write_report(tmp_path / "index.html", r)
    text = out.read_text()
    assert "Repair &lt;run&gt;" in text and "<td>18.25</td>" in text and "<td>∞</td>" in text
    assert "src='views/000/gs.png'" in text and "holes 30%" in text
    assert not list(tmp_path.glob("*.tmp*"))
