"""How sure a fit is: the stages that turn a point estimate into an interval.

* :mod:`.bootstrap` -- parametric bootstrap of the joint fit with a linear control variate.
* :mod:`.jackknife` -- leave-one-marker-out: how much one marker can move the estimate.
* :mod:`.singular` -- near-singular poses: the branch check and the sd along the profile.
* :mod:`.normal` -- the joint fit's normal equations with the poses eliminated.
* :mod:`.posterior` -- the typed posteriors (``GridPosterior``, ``GaussianPosterior``, ``SamplePosterior``).
* :mod:`.smc` -- tempered sequential Monte Carlo (knows nothing about skeletons).
* :mod:`.stacking` -- several models of one body averaged: stacking weights and their mixture.

The estimators that assemble these stages (``MarkerEstimator``, ``MultiTrialEstimator`` for
several trials, ``SamplerEstimator`` for posterior samples) sit one level up, in
:mod:`skelid.estimators`; nothing here imports them.
"""
