"""Every OpenSim joint type: a tiny model built with the opensim package, markers compared at random poses.

Each model is ground -FreeJoint-> base -joint under test-> link, with offset
parent and child frames of random position and orientation on both joints and
markers on both bodies, so that the frames' algebra is exercised as well as
the joint's own motion.
"""

from __future__ import annotations

import numpy as np
import pytest

from skelid.errors import ModelError
from skelid.io.osim import read_osim
from tests.helpers import opensim_marker_gap

osim = pytest.importorskip("opensim", reason="the opensim package is not installed (pip install opensim)")

STANDARD = ("PinJoint", "SliderJoint", "UniversalJoint", "GimbalJoint", "BallJoint", "FreeJoint", "PlanarJoint",
            "WeldJoint", "EllipsoidJoint", "ScapulothoracicJoint")
N_COORDS = {"PinJoint": 1, "SliderJoint": 1, "UniversalJoint": 2, "GimbalJoint": 3, "BallJoint": 3, "FreeJoint": 6,
            "PlanarJoint": 3, "WeldJoint": 0, "EllipsoidJoint": 3, "ScapulothoracicJoint": 4}


def _extra(joint: str, winging_origin=(-0.02, 0.03)) -> tuple:
    """The arguments a joint's constructor takes after the frames (an ellipsoid's radii, the winging axis)."""
    if joint == "EllipsoidJoint":
        return (osim.Vec3(0.05, 0.08, 0.11),)
    if joint == "ScapulothoracicJoint":
        return osim.Vec3(0.07, 0.15, 0.08), osim.Vec2(*winging_origin), 0.4
    return ()


def _tiny(joint: str, rng, path, extra=None):
    """The two-body model with ``joint`` between base and link, written to ``path``."""
    osim.Logger.removeFileSink()
    m = osim.Model()
    m.setName(f"tiny_{joint}")
    base = osim.Body("base", 1.0, osim.Vec3(0), osim.Inertia(0.1))
    link = osim.Body("link", 1.0, osim.Vec3(0), osim.Inertia(0.1))
    m.addBody(base)
    m.addBody(link)

    def vec(s):
        return osim.Vec3(*rng.uniform(-s, s, 3))

    m.addJoint(osim.FreeJoint("base_free", m.getGround(), vec(0.1), vec(1.0), base, vec(0.1), vec(1.0)))
    args = ("joint", base, vec(0.1), vec(1.0), link, vec(0.1), vec(1.0))
    m.addJoint(getattr(osim, joint)(*args, *(_extra(joint) if extra is None else extra)))
    m.addMarker(osim.Marker("on_base", base, vec(0.1)))
    m.addMarker(osim.Marker("on_link_1", link, vec(0.1)))
    m.addMarker(osim.Marker("on_link_2", link, vec(0.1)))
    m.finalizeConnections()
    m.printToXML(str(path))


@pytest.mark.parametrize("joint", STANDARD)
def test_joint_equals_opensim(tmp_path, joint):
    rng = np.random.default_rng(sum(map(ord, joint)))
    path = tmp_path / f"{joint}.osim"
    _tiny(joint, rng, path)
    model, _ = read_osim(path)
    assert model.n_pose == 6 + N_COORDS[joint]
    # +-1.2 rad keeps the Euler angles of Ball and Free joints away from their singular middle angle
    worst = opensim_marker_gap(model, osim.Model(str(path)), rng, 100, limit=1.2)
    assert worst <= 1e-6, f"{joint}: largest marker difference {worst:.2e} mm"


CUSTOM = """<?xml version="1.0" encoding="UTF-8" ?>
<OpenSimDocument Version="40000"><Model name="tiny_custom">
<BodySet><objects>
<Body name="base"><mass>1</mass><inertia>0.1 0.1 0.1 0 0 0</inertia></Body>
<Body name="link"><mass>1</mass><inertia>0.1 0.1 0.1 0 0 0</inertia></Body>
</objects></BodySet>
<JointSet><objects>
<FreeJoint name="base_free"><socket_parent_frame>ground_offset</socket_parent_frame>
<socket_child_frame>base_offset</socket_child_frame>
<coordinates><Coordinate name="r1"/><Coordinate name="r2"/><Coordinate name="r3"/>
<Coordinate name="t1"/><Coordinate name="t2"/><Coordinate name="t3"/></coordinates>
<frames>
<PhysicalOffsetFrame name="ground_offset"><socket_parent>/ground</socket_parent>
<translation>0.01 0.9 -0.02</translation><orientation>0.1 -0.2 0.3</orientation></PhysicalOffsetFrame>
<PhysicalOffsetFrame name="base_offset"><socket_parent>/bodyset/base</socket_parent>
<translation>0.02 -0.01 0.03</translation><orientation>-0.3 0.2 0.1</orientation></PhysicalOffsetFrame>
</frames></FreeJoint>
<CustomJoint name="joint"><socket_parent_frame>base_offset</socket_parent_frame>
<socket_child_frame>link_offset</socket_child_frame>
<coordinates>{coordinates}</coordinates>
<frames>
<PhysicalOffsetFrame name="base_offset"><socket_parent>/bodyset/base</socket_parent>
<translation>0.05 -0.2 0.04</translation><orientation>0.4 0.1 -0.7</orientation></PhysicalOffsetFrame>
<PhysicalOffsetFrame name="link_offset"><socket_parent>/bodyset/link</socket_parent>
<translation>-0.03 0.1 0.02</translation><orientation>-0.2 0.5 0.3</orientation></PhysicalOffsetFrame>
</frames>
<SpatialTransform>{axes}</SpatialTransform></CustomJoint>
</objects></JointSet>
<MarkerSet><objects>
<Marker name="on_base"><socket_parent_frame>/bodyset/base</socket_parent_frame><location>0.1 0 0.05</location></Marker>
<Marker name="on_link_1"><socket_parent_frame>/bodyset/link</socket_parent_frame><location>0 -0.2 0.03</location>
</Marker>
<Marker name="on_link_2"><socket_parent_frame>/bodyset/link</socket_parent_frame><location>0.04 -0.1 0</location>
</Marker>
</objects></MarkerSet></Model></OpenSimDocument>"""


def _axis(name, axis, coordinate="", function="<Constant><value>0</value></Constant>"):
    return (f'<TransformAxis name="{name}"><coordinates>{coordinate}</coordinates><axis>{axis}</axis>'
            f"<function>{function}</function></TransformAxis>")


def _custom(tmp_path, coordinates, axes):
    path = tmp_path / "custom.osim"
    path.write_text(CUSTOM.format(coordinates=coordinates, axes="".join(axes)))
    return path


def test_custom_joint_with_coupled_axes_equals_opensim(tmp_path):
    """One coordinate drives a rotation about a skew axis, a second rotation and a translation (a knee)."""
    spline = "<SimmSpline><x>-2 -1 0 1 2</x><y>-0.01 0.004 0 0.003 0.02</y></SimmSpline>"
    path = _custom(tmp_path, '<Coordinate name="flex"><range>-2 2</range></Coordinate>'
                   '<Coordinate name="ab"><range>-1 1</range></Coordinate>',
                   [_axis("rotation1", "0.3 0.2 0.9", "flex", "<LinearFunction><coefficients>1 0</coefficients>"
                          "</LinearFunction>"),
                    _axis("rotation2", "1 0 0", "ab", "<LinearFunction><coefficients>0.5 0.1</coefficients>"
                          "</LinearFunction>"),
                    _axis("rotation3", "0 1 0"),
                    _axis("translation1", "1 0 0", "flex", spline),
                    _axis("translation2", "0 1 0", "", "<Constant><value>0.02</value></Constant>"),
                    _axis("translation3", "0 0 1")])
    model, _ = read_osim(path)
    assert model.n_pose == 8
    worst = opensim_marker_gap(model, osim.Model(str(path)), np.random.default_rng(5), 100)
    assert worst <= 1e-6, f"largest marker difference {worst:.2e} mm"


def test_custom_joint_without_a_moving_axis_is_a_weld(tmp_path):
    """A CustomJoint whose axes are all constant attaches its child rigidly; its coordinate moves nothing.

    (OpenSim 4.6 cannot build a CustomJoint with no coordinate at all, so the joint keeps one.)
    """
    path = _custom(tmp_path, '<Coordinate name="idle"><range>-1 1</range></Coordinate>',
                   [_axis("rotation1", "1 0 0", "idle", "<Constant><value>0.3</value></Constant>"),
                                  _axis("rotation2", "0 1 0"), _axis("rotation3", "0 0 1"),
                                  _axis("translation1", "1 0 0"),
                                  _axis("translation2", "0 1 0", "", "<Constant><value>-0.05</value></Constant>"),
                                  _axis("translation3", "0 0 1")])
    model, _ = read_osim(path)
    assert model.n_pose == 6
    assert {s.joint.name: s.joint.coordinates for s in model.segments}["joint"] == ()
    worst = opensim_marker_gap(model, osim.Model(str(path)), np.random.default_rng(6), 100)
    assert worst <= 1e-6, f"largest marker difference {worst:.2e} mm"


@pytest.mark.parametrize("joint", ["ConstantCurvatureJoint", "ScrewJoint"])
def test_joint_skelid_cannot_follow_is_refused_in_one_line(tmp_path, joint):
    text = CUSTOM.format(coordinates="", axes="").replace("CustomJoint", joint)
    path = tmp_path / "m.osim"
    path.write_text(text)
    with pytest.raises(ModelError) as exc:
        read_osim(path)
    line = exc.value.one_line()
    assert f"joint 'joint' ({joint})" in line and "fix:" in line and "\n" not in line


@pytest.mark.parametrize("joint", ["EllipsoidJoint", "ScapulothoracicJoint", "CustomJoint"])
def test_jacobians_of_joint_equal_finite_differences(tmp_path, joint):
    """Pose and scale Jacobians of the joints whose translation follows their rotations (and a coupled knee)."""
    from skelid.io.osim import osim_parameters
    from skelid.model.kinematics import marker_jacobian, marker_positions

    rng = np.random.default_rng(7)
    path = tmp_path / "m.osim"
    if joint == "CustomJoint":
        path = _custom(tmp_path, '<Coordinate name="flex"><range>-2 2</range></Coordinate>',
                       [_axis("rotation1", "0.3 0.2 0.9", "flex", "<LinearFunction><coefficients>1 0</coefficients>"
                              "</LinearFunction>"), _axis("rotation2", "1 0 0"), _axis("rotation3", "0 1 0"),
                        _axis("translation1", "1 0 0", "flex", "<SimmSpline><x>-2 -1 0 1 2</x>"
                              "<y>-0.01 0.004 0 0.003 0.02</y></SimmSpline>"),
                        _axis("translation2", "0 1 0"), _axis("translation3", "0 0 1")])
    else:  # the winging axis through the joint centre, so that the link's scale is a parameter too
        _tiny(joint, rng, path, _extra(joint, (0.0, 0.0)))
    base, info = read_osim(path)
    model = osim_parameters(base, info, scale="axes", markers="offsets")
    assert "scale_base_x" in model.parameter_names and "scale_link_x" in model.parameter_names
    theta = model.theta_nominal + rng.normal(0, 0.05, model.n_params)
    q = rng.uniform(-0.8, 0.8, model.n_pose)
    x, Jq, Jt = marker_jacobian(model, theta, q)
    h = 1e-6
    for k in range(model.n_pose):
        e = np.zeros(model.n_pose)
        e[k] = h
        fd = (marker_positions(model, theta, q + e) - marker_positions(model, theta, q - e)) / (2 * h)
        np.testing.assert_allclose(Jq[..., k], fd, atol=1e-6 * (1 + np.abs(fd).max()), err_msg=f"pose {k}")
    for k in range(model.n_params):
        e = np.zeros(model.n_params)
        e[k] = h
        fd = (marker_positions(model, theta + e, q) - marker_positions(model, theta - e, q)) / (2 * h)
        np.testing.assert_allclose(Jt[..., k], fd, atol=1e-6 * (1 + np.abs(fd).max()),
                                   err_msg=model.parameters[k].name)


@pytest.mark.parametrize("joint", ["EllipsoidJoint", "ScapulothoracicJoint"])
def test_scaled_ellipsoid_written_back_equals_opensim(tmp_path, joint):
    """Scale factors on both bodies written back: OpenSim's markers on the written file equal skelid's."""
    from skelid.io.osim import osim_parameters, write_scaled_osim
    from skelid.model import model_from_dict
    from skelid.model.kinematics import marker_positions

    rng = np.random.default_rng(8)
    path = tmp_path / "m.osim"
    _tiny(joint, rng, path, _extra(joint, (0.0, 0.0)))
    base, info = read_osim(path)
    model = osim_parameters(base, info, scale="axes", markers="offsets")
    theta = np.array([rng.uniform(0.8, 1.25) if p.kind == "scale" else rng.normal(0, 5.0)
                      for p in model.parameters])
    out = tmp_path / "scaled.osim"
    write_scaled_osim(path, out, model, info, theta)
    again, _ = read_osim(out)
    q = rng.uniform(-0.8, 0.8, (20, model.n_pose))
    np.testing.assert_allclose(marker_positions(again, np.zeros(0), q), marker_positions(model, theta, q),
                               atol=1e-9)
    worst = opensim_marker_gap(again, osim.Model(str(out)), rng, 50, limit=1.2)
    assert worst <= 1e-6, f"largest marker difference {worst:.2e} mm"
    back = model_from_dict(model.to_dict())  # carried translations survive the model file
    np.testing.assert_allclose(marker_positions(back, theta, q), marker_positions(model, theta, q), atol=1e-9)


def test_scaling_a_scapula_with_an_offset_winging_axis_is_refused(tmp_path):
    from skelid.io.osim import osim_parameters

    path = tmp_path / "m.osim"
    _tiny("ScapulothoracicJoint", np.random.default_rng(9), path)
    base, info = read_osim(path)
    assert osim_parameters(base, info, scale="none").n_params > 0  # offsets only: fine
    with pytest.raises(ModelError) as exc:
        osim_parameters(base, info, scale="bodies")
    line = exc.value.one_line()
    assert "link" in line and "winging" in line and "fix:" in line


COUPLER = """<ConstraintSet><objects><CoordinateCouplerConstraint name="follow">
<isEnforced>true</isEnforced>
<coupled_coordinates_function><LinearFunction><coefficients>0.5 0</coefficients></LinearFunction>
</coupled_coordinates_function>
<independent_coordinate_names>r1</independent_coordinate_names>
<dependent_coordinate_name>flex</dependent_coordinate_name>
</CoordinateCouplerConstraint></objects></ConstraintSet>"""


@pytest.mark.parametrize("enforced", [True, False])
def test_a_coordinate_coupled_across_joints_is_refused_in_one_line(tmp_path, enforced):
    path = _custom(tmp_path, '<Coordinate name="flex"><range>-2 2</range></Coordinate>',
                   [_axis("rotation1", "0 0 1", "flex", "<LinearFunction><coefficients>1 0</coefficients>"
                          "</LinearFunction>"), _axis("rotation2", "1 0 0"), _axis("rotation3", "0 1 0"),
                    _axis("translation1", "1 0 0"), _axis("translation2", "0 1 0"), _axis("translation3", "0 0 1")])
    coupler = COUPLER if enforced else COUPLER.replace("<isEnforced>true", "<isEnforced>false")
    path.write_text(path.read_text().replace("</JointSet>", "</JointSet>" + coupler))
    if not enforced:  # a constraint switched off couples nothing
        assert read_osim(path)[0].n_pose == 7
        return
    with pytest.raises(ModelError) as exc:
        read_osim(path)
    line = exc.value.one_line()
    assert "'follow'" in line and "joint 'joint' (CustomJoint)" in line and "'r1'" in line and "fix:" in line
