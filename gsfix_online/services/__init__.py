"""Services: the event-driven components that the nodes in ``nodes/`` wrap.

Each takes messages in and returns messages out, with no sockets and no clock of its own
(the node passes the time in), so it is tested without processes:

- ``tsdf.py``: the TSDF mesh of the stream, its renders and exports
- ``splat.py``: the Gaussian map, keyframes, GSFixer samples, distillation of repairs
- ``trainer.py``: GSFixer fine-tuning in the background
- ``planner.py``: which views to repair and when
- ``repair.py``: repairs a view with GSFixer and the fallback rule
- ``writer.py``: collects a run's outputs into its folder and ends the run
- ``map_server.py``, ``live_map.py``, ``run_folder.py``: serving finished and live maps
"""
