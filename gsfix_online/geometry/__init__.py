"""Pure geometry: SE(3) helpers and timestamped trajectories."""
