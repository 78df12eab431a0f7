"""The vocabulary of a model description, shared by the model and its file schema.

Both :mod:`skelid.model.description` (which builds models) and
:mod:`skelid.model.schema` (which checks model files before they are built)
name joint types, parameter kinds and motion kinds; they live here so that
neither module needs the other's (the schema never imports the description).
Adding a joint type or a parameter kind starts with one line here.
"""

from __future__ import annotations

#: joint types by model dimension
JOINT_TYPES = {
    2: ("free", "revolute", "fixed"),
    3: ("free", "hinge", "universal", "spherical", "fixed", "custom"),
}
#: kinds of unknown parameters
PARAMETER_KINDS = ("length", "joint_position", "marker_position", "joint_centre", "axis_direction",
                   "scale", "marker_offset", "translation_gain")
#: the key naming what a parameter moves, by parameter kind (default: ``joint``)
PARAMETER_TARGET: dict[str, str] = {"marker_position": "marker", "marker_offset": "marker", "scale": "segment"}
#: a custom joint's motions: internal letter -> name in model files
MOTION_KINDS = {"R": "rotation", "T": "translation", "C": "carried"}
