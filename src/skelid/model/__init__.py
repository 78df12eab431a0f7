"""Model description (frozen) and kinematics (pure, vectorised functions)."""

from skelid.model.description import (
    JOINT_TYPES,
    Joint,
    Marker,
    Model,
    Parameter,
    Prior,
    Segment,
    load_model,
    model_from_dict,
)
from skelid.model.kinematics import (
    Workspace,
    forward_kinematics,
    geometry,
    joint_distances,
    joint_positions,
    marker_jacobian,
    marker_positions,
)

__all__ = [
    "JOINT_TYPES", "Joint", "Marker", "Model", "Parameter", "Prior", "Segment",
    "load_model", "model_from_dict", "forward_kinematics", "geometry", "joint_distances", "joint_positions",
    "marker_jacobian", "marker_positions", "Workspace",
]
