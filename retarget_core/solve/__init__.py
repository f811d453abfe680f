"""The per-frame problem (paper Eq. "optframe" and appendix "Motion Retargeting Details"): the
run configuration (:mod:`.config`), per-frame targets (:mod:`.targets`), the objectives
(:mod:`.objective`, :mod:`.baselines`), the problem a worker solves and the one place a method
picks its objective (:mod:`.problem`), and the bounded solver (:mod:`.frame_solver`). The passes
that use them are in :mod:`retarget_core.pipeline`."""
