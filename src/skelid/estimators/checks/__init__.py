"""Checks on a fit: what the data say about the fit's own assumptions.

* :mod:`.misfit` -- model misfit tests, joint ranges, the still-joint and rolling-centre checks.
* :mod:`.outliers` -- the outlier screen with each frame's residual degrees of freedom.
* :mod:`.noise` -- per-marker (or per-group) noise levels.
* :mod:`.artefact` -- soft-tissue artefact as a random effect of stated size.
* :mod:`.pose_artefact` -- a pose-dependent artefact sized from a joint fit's residuals.
* :mod:`.trial_placement` -- markers placed differently in each trial of a joint fit.
* :mod:`.trial_motion` -- per-trial estimates that change with how far each trial moves a joint.

Nothing here imports the estimators above it.
"""
