"""Implementation modules of the rig model; import the public API from ``reconstructor.model``."""
