"""Core: what every layer above shares, and which imports nothing of the project's own.

- ``types.py``: RGB-D frames and intrinsics, validated once where they enter
- ``config.py``: typed configuration (dataclass sections, YAML with ``extends:``, overrides)
- ``io.py``: atomic file writes
- ``se3.py``, ``trajectory.py``: rigid transforms and timestamped trajectories
- ``metrics.py``: image metrics (PSNR and SSIM through kornia)
- ``progress.py``: progress display (a live bar on a terminal, plain lines in a log)
- ``pages.py``: self-contained HTML report pages
"""
