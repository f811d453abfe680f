"""Per-frame pose solving (paper appendix "Motion Retargeting Details"): the run configuration
(:mod:`retarget_core.solve.config`) and the solver passes that use it."""
