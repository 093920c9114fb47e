"""Repair: choosing which views need repair (planner), the baselines a repair is compared with,
and the offline ``repair`` job that runs the online graph over a recorded input."""
