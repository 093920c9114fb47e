"""Inspection: what users look at after a run — image metrics, reports, exported maps."""
