"""Repair: which views need repair (planner, scheduler), the classical baselines, the fallback
rule that never delivers worse than the mesh and OpenCV alone, the GSFixer repairer and the
files a repaired view is written as."""
