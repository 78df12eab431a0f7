"""The fit itself: parameters and poses by least squares, and the kernels it runs on.

* :mod:`.joint` -- the joint Levenberg-Marquardt fit of ``theta`` and every pose
  (``joint_fit``), its motion-model penalty band, the second-order bias.
* :mod:`.pose` -- per-frame pose fits for fixed ``theta`` (``fit_pose``, ``track_poses``,
  ``initial_pose``) and the workspace their compiled path keeps.
* :mod:`.likelihood` -- the marker-space likelihood with the pose as a nuisance
  (``frame_terms``, ``pose_information``, ``crlb_sd``).
* :mod:`._lm_kernel` -- the compiled (numba) pose iteration behind :mod:`.pose`.

Nothing here imports the estimators above it or the uncertainty and check stages.
"""
