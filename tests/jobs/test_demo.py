"""The demo's quality table: every stage a repair scores, with its gain over the raw 3DGS."""

from __future__ import annotations

from gsfix_online.jobs.demo import QUALITY_ROWS, quality_table
from gsfix_online.repair.outputs import STAGES


def test_the_table_shows_every_stage_and_baseline_a_run_scores():
    rows = {key for key, _ in QUALITY_ROWS}
    # GSFixer and the output are shown as scored over every view (the 3DGS render where a view
    # was skipped), the way the final map is
    assert rows == set(STAGES) - {"fixed", "output"}
    stages = {k: {"psnr_db": 15.0 + i, "ssim": 0.5, "views": 8} for i, k in enumerate(STAGES)}
    del stages["inpaint_fsr"]  # a run without it: no row, no error
    lines = quality_table(stages).splitlines()
    assert len(lines) == 2 + len(QUALITY_ROWS) - 1
    ns = next(line for line in lines if "Navier-Stokes" in line)
    assert ns.split()[-4:-2] == [
        f"{15.0 + STAGES.index('inpaint_ns'):.2f}",
        f"+{STAGES.index('inpaint_ns'):.2f}",
    ]
