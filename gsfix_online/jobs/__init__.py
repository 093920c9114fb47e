"""Jobs: whole runs built from the layers below, each started by one command.

- ``repair_run.py``: ``gsfix-online repair``: the repair graph over a recorded input
- ``demo.py``, ``config.py``: ``gsfix-online demo`` and the root configuration of the commands
- ``fixer_report.py``, ``splat_report.py``, ``tsdf_report.py``, ``figure.py``: reports
- ``pretrain.py``, ``map_corpus.py``: GSFixer pretraining and its corpus of maps
- ``bench/``: run time against error; ``stress/``: the numerical stress suite
"""
