"""Variants of a model that relax one joint, for refits when the joint model does not fit.

**A hinge whose centre slides with its angle.** A hinge about the unit axis ``e``
with centre ``c`` moves its child's markers ``m`` (parent frame) to
``c + R_e(q) (m - c)``. Its moving-centre variant is a ``custom`` joint that first
translates the child by

.. math:: t(q) = \\sum_{k=1}^{d} (a_k u + b_k v)\\, q^k

(``u, v`` unit vectors perpendicular to ``e``; the gains ``a_k, b_k`` unknown
``translation_gain`` parameters, zero being the hinge) and then rotates it by ``q``
about ``e``. The joint's ``joint_centre`` parameters keep their meaning: the centre
at ``q = 0``. A knee whose centre moves with flexion (OpenSim's gait knees,
whose translations are splines of the flexion angle) is fitted without the bias
a fixed hinge leaves, at the price of a wider interval: the gains and the centre
are told apart only by the curvature of the path the child's markers follow.

**What the markers cannot tell apart.** The centre at ``q = 0`` of a joint whose centre
follows an arbitrary path is not identified by marker data: a shift ``delta`` of the
centre together with the path ``t(q) + (I - R_e(q)) delta`` moves every marker exactly as
before. Expanded in the angle (planar part, ``J`` the quarter turn about ``e``),

.. math:: (I - R_e(q))\\, \\delta = -q J \\delta + \\tfrac{q^2}{2} \\delta + \\tfrac{q^3}{6} J \\delta
          - \\tfrac{q^4}{24} \\delta + \\dots

so a path of degree ``d`` absorbs a centre shift up to ``q^d``, and the data pin the
centre only through the higher powers: the path's own shape beyond degree ``d`` is then
read as the centre. OpenSim's gait2354 knee (splines of the flexion) fitted with a
quadratic path over 0-90 degrees, noise-free, puts the centre at (7.7, -19.6) mm, with a
cubic at (1.7, -41.3), with a quartic at (-371, 130): the estimand of a flat-prior fit is
the polynomial's extrapolation to ``q = 0``, not the knee's centre. What does tell the
centre is the prior on the path.

**Prior on the gains.** Each gain has a normal prior of mean 0 (the hinge) and sd
``GAIN_PRIOR_SD_MM`` (10 mm per radian^k; a knee's centre slides by 10-20 mm over 90
degrees, OpenSim's gait2354 knee by 13 mm), bounded at ``GAIN_BOUND_MM``. With a path of
degree ``DEGREE = 3`` a centre shift is absorbed to third order, so the centre's interval
is the one this prior implies (sd near ``10 / sqrt(1 + 1/4 + 1/36) = 8.8`` mm once the data
fix the path) rather than a polynomial's extrapolation: in the model-mismatch benchmark it
covers the gait2354 knee's centre in 0.98-1.00 of trials at 1, 5 and 10 mm of noise
(half-width 16-20 mm), where a quadratic path covered 0.60 / 0.01 at 1 mm. An estimator
that combines normal priors (``marker``) uses it;
``gain_sd=None`` keeps flat priors.

Examples
--------
>>> from skelid.model.description import model_from_dict
>>> hinge = {"name": "knee", "type": "hinge", "axis": [0, 0, 1], "position": [0, -400, 0]}
>>> m = model_from_dict({"model": {"name": "leg"},
...     "segments": [{"name": "thigh", "parent": "ground", "joint": {"name": "hip", "type": "free",
...                   "position": [0, 0, 0]}}, {"name": "shank", "parent": "thigh", "joint": hinge}],
...     "markers": [{"name": "S1", "segment": "shank", "position": [50, -80, 40]}]})
>>> moving_centre(m, "knee").parameter_names
('knee_gain1_u', 'knee_gain1_v', 'knee_gain2_u', 'knee_gain2_v', 'knee_gain3_u', 'knee_gain3_v')
"""

from __future__ import annotations

from skelid.errors import ModelError
from skelid.model.description import Model, model_from_dict, tilt_basis

#: bound (mm per radian^k) of the gains of a moving centre's translations
GAIN_BOUND_MM = 200.0
#: sd (mm per radian^k) of the normal prior of each gain (see the module notes)
GAIN_PRIOR_SD_MM = 10.0
#: highest power of the angle in a moving centre's path (see the module notes)
DEGREE = 3
_UNIT_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0}


def moving_centre(model: Model, joint: str, degree: int = DEGREE, gain_sd: float | None = GAIN_PRIOR_SD_MM) -> Model:
    """The model with hinge ``joint`` replaced by a hinge whose centre slides with its angle.

    Parameters
    ----------
    model : Model
        A 3-D model.
    joint : str
        Name of a hinge joint.
    degree : int
        Highest power of the angle in the centre's path (1 or more).
    gain_sd : float or None
        Sd (mm per radian^k) of each gain's normal prior about 0; None: uniform priors.

    Returns
    -------
    Model
        The same segments, markers and parameters, plus ``2 * degree`` parameters
        ``<joint>_gain<k>_<u|v>`` (normal priors about 0, the hinge, bounded at +-``GAIN_BOUND_MM``).

    Raises
    ------
    ModelError
        If ``joint`` is not a hinge of a 3-D model, its axis is a fitted parameter, or ``degree < 1``.
    """
    seg = _moving_centre_hinge(model, joint, degree)
    if gain_sd is not None and not gain_sd > 0:
        raise ModelError(f"the gains' prior sd must be positive, got {gain_sd}", "give a positive sd or None")
    d = model.to_dict()
    table = next(s for s in d["segments"] if s["name"] == seg.name)
    table["joint"] = _sliding_hinge(table["joint"], seg.joint, degree)
    prior = _gain_prior(model.units, gain_sd)
    for n in range(2 * degree):
        d["parameters"].append({"name": f"{joint}_gain{n // 2 + 1}_{'uv'[n % 2]}", "kind": "translation_gain",
                                "joint": joint, "motion": n, "prior": dict(prior)})
    return model_from_dict(d, f"{model.name} ({joint} with a moving centre)")


def _moving_centre_hinge(model: Model, joint: str, degree: int):
    """The segment of hinge ``joint``, checked to have a moving-centre variant of ``degree``."""
    seg = next((s for s in model.segments if s.joint.name == joint), None)
    if seg is None or model.dim != 3 or seg.joint.type != "hinge":
        raise ModelError(f"joint {joint!r} is not a hinge of a 3-D model, so it has no moving-centre variant",
                         "name a hinge joint")
    if degree < 1:
        raise ModelError(f"a moving centre needs degree >= 1, got {degree}")
    axis = [p.name for p in model.parameters if p.kind == "axis_direction" and p.target == joint]
    if axis:
        raise ModelError(f"the axis of hinge {joint!r} is fitted ({', '.join(axis)}), and a moving centre is "
                         "defined about a fixed axis", f"fix the axis at its estimate (drop {axis[0]!r}) first")
    return seg


def _sliding_hinge(spec: dict, hinge, degree: int) -> dict:
    """The custom joint table: translations ``q^k`` along ``u`` and ``v`` for k = 1..degree, then the rotation."""
    e, u, v = tilt_basis(hinge.axes[0])
    name = hinge.name
    motions = [{"kind": "translation", "axis": list(direction), "coordinate": name,
                "function": {"type": "polynomial", "coefficients": [1.0] + [0.0] * k}}
               for k in range(1, degree + 1) for direction in (u, v)]
    motions.append({"kind": "rotation", "axis": list(e), "coordinate": name,
                    "function": {"type": "linear", "coefficients": [1.0, 0.0]}})
    custom = {"name": name, "type": "custom", "position": spec["position"], "coordinates": [name],
              "motions": motions}
    if "range" in spec:
        custom["range"] = spec["range"]
    return custom


def _gain_prior(units: str, gain_sd: float | None) -> dict:
    """Each gain's prior table: normal about 0 with ``gain_sd`` mm (uniform without), bounded at GAIN_BOUND_MM."""
    bound = GAIN_BOUND_MM / _UNIT_MM[units]
    prior = {"type": "uniform", "lower": -bound, "upper": bound}
    if gain_sd is not None:
        prior = dict(prior, type="normal", mean=0.0, sd=gain_sd / _UNIT_MM[units])
    return prior
