"""Per-frame filters for the live path.

* :mod:`.grid` -- ``MarkerGridFilter``: a recursive grid filter over 1-3 parameters.
* :mod:`._live_kernel` -- the live Gaussian form's compiled frame update (used by :mod:`skelid.live`).
"""
