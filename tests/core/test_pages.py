"""The HTML report: tables, escaped text, image links, the before/after slider, the plots;
the run report RepairOutputs writes, opened in chromium from disk."""

from __future__ import annotations

import base64
import json
import math
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from gsfix_online.core.pages import Report, Table, ViewRow, write_report
from tests.apps.run_data import make_run


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


def test_plots_hold_the_values_they_are_given():
    from gsfix_online.core.pages import psnr_figure, stage_times_figure

    fig = stage_times_figure({"score_s": 1.5, "fix_s": 12.0, "distill_s": math.nan})
    (ax,) = fig.axes
    assert [t.get_text() for t in ax.get_yticklabels()] == ["score_s", "fix_s"]  # NaN left out
    assert [p.get_width() for p in ax.patches] == [1.5, 12.0]
    fig = psnr_figure(["000", "001"], {"gs": [18.0, 20.5], "fixed": [22.0, None]})
    (ax,) = fig.axes
    lines = {ln.get_label(): list(ln.get_ydata()) for ln in ax.get_lines()}
    assert lines["gs"] == [18.0, 20.5]
    assert lines["fixed"][0] == 22.0 and math.isnan(lines["fixed"][1])  # unscored: a gap
    assert [t.get_text() for t in ax.get_xticklabels()] == ["000", "001"]


def test_a_compare_must_name_two_of_the_views_images(tmp_path):
    v = ViewRow("view 000", {"3DGS": "a.png"}, compare=("3DGS", "repair"))
    with pytest.raises(
        ValueError, match="view 000: compare names '3DGS' and 'repair', images hold 3DGS"
    ):
        write_report(tmp_path / "r.html", Report("x", views=[v]))


@pytest.fixture(scope="module")
def run_report(tmp_path_factory) -> Path:
    """report.html of a tiny run written by RepairOutputs (ground truth: every stage scored)."""
    return make_run(tmp_path_factory.mktemp("report"), n_views=2, maps=False) / "report.html"


def test_run_report_has_a_slider_per_repaired_view_tables_and_embedded_plots(run_report):
    text = run_report.read_text()
    root = run_report.parent
    metrics = json.loads((root / "metrics.json").read_text())
    # 1. Nothing from the network; every linked image is a file beside the page
    assert "http://" not in text and "https://" not in text
    srcs = re.findall(r"<img[^>]* src='([^']+)'", text)
    files = [s for s in srcs if not s.startswith("data:")]
    assert files and all((root / s).is_file() for s in files)
    # 2. A before/after slider for view 000 (repaired), none for 001 (skipped)
    sliders = re.findall(r"<h3>view (\d+).*?</h3><div>(<figure><div class='cmp'>.*?</div>)", text)
    assert [v for v, _ in sliders] == ["000"]
    for v, block in sliders:
        assert f"class='after' src='views/{v}/output.png'" in block
        assert f"class='before' src='views/{v}/gs.png'" in block
        assert "type='range'" in block
    # 3. The tables carry metrics.json's figures
    gs = metrics["summary"]["stages"]["gs"]["psnr_db"]
    assert f"<td>gs</td><td>{gs:.2f}</td>" in text
    # 4. Two plots, embedded PNGs that decode
    plots = re.findall(r"<img class='plot' src='data:image/png;base64,([^']+)' alt='([^']+)'", text)
    assert [alt for _, alt in plots] == [
        "Time per stage",
        "PSNR per view, every stage and baseline",
    ]
    for data, _ in plots:
        img = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.shape[0] > 100 and img.shape[1] > 300


def test_the_slider_uncovers_the_before_image_in_chromium(run_report):
    """The page from disk in headless chromium: images load, the slider moves the split."""
    from tests.apps.browser import chromium, missing, wait_for

    why = missing()
    if why:
        pytest.skip(why)
    from selenium.webdriver.common.by import By

    with chromium() as driver:
        driver.get(run_report.as_uri())
        wait_for("every image loaded", lambda: driver.execute_script(
            "return [...document.images].every(i => i.complete && i.naturalWidth > 0)"))  # fmt: skip
        slider = driver.find_elements(By.CSS_SELECTOR, ".cmp input[type=range]")[0]
        before = driver.find_elements(By.CSS_SELECTOR, ".cmp img.before")[0]
        assert before.value_of_css_property("clip-path") == "inset(0px 50% 0px 0px)"
        driver.execute_script(
            "arguments[0].value = 80; arguments[0].dispatchEvent(new Event('input'))", slider
        )
        assert before.value_of_css_property("clip-path") == "inset(0px 20% 0px 0px)"


def test_a_later_plot_goes_after_the_others_and_before_the_views(tmp_path):
    from gsfix_online.core.pages import Plot, Report, ViewRow, add_plot, write_report

    page = tmp_path / "report.html"
    views = [ViewRow("view 000", {"gs": "views/000/gs.png"})]
    write_report(page, Report("run", plots=[Plot("Time per stage", b"\x89PNG1")], views=views))
    add_plot(page, Plot("Timeline", b"\x89PNG2"))
    text = page.read_text()
    assert text.index("Time per stage") < text.index("Timeline") < text.index("<h2>Views</h2>")
    assert text.count("<img class='plot'") == 2
    (tmp_path / "other.html").write_text("<h1>not a report</h1>")
    with pytest.raises(ValueError, match="other.html: not a report page"):
        add_plot(tmp_path / "other.html", Plot("Timeline", b""))
