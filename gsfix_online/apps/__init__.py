"""Apps: what a user starts or holds: the command line, the viewer, the map client, exports."""
