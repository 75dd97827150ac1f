"""Training code of the PoseFlow network (see training/README.md)."""
