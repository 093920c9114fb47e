"""``gsfix-online bench``: run time against error, for every knob that trades one for the other,
and the time and error of every skip.

- :mod:`.knobs`: the knob table (name, graph overrides, default, values to try, stage);
- :mod:`.runner`: one run of the repair graph, timed per stage, its peak memory and its scores;
- :mod:`.sweep`: runs one after the other, resumable through the results JSON, CSV rows;
- :mod:`.pareto`: Pareto fronts of time against error and their plots;
- :mod:`.skips`: each skip against the same run without it, and the verdict;
- :mod:`.command`: the command line.

The benchmark scripts in ``benchmarks/`` stay as its building blocks for single components
(``bench_tsdf.py``, ``bench_render.py``, ``bench_mapping.py``, ``bench_fixer*.py``, ...); the
repair-graph sweeps of ``bench_skip.py`` and ``bench_variants.py`` are what ``--skips`` and the
knob sweep generalise.
"""

from __future__ import annotations
