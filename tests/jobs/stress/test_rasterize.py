"""Stress property of rasterisation forward and backward (gsfix_online/mapping/splat/render.py)."""

from __future__ import annotations

from gsfix_online.jobs.stress import properties
from gsfix_online.jobs.stress.runner import assert_property


def test_render_forward_backward_property_holds():
    (prop,) = [p for p in properties("splat") if p.name == "splat.render_forward_backward"]
    run = assert_property(prop)
    assert run.examples >= prop.ci_examples
