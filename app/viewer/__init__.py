"""The 3D viewer (viser): consumes replay arrays and server callbacks, nothing else."""
