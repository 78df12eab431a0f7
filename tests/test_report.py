"""`skelid report`: one valid, self-contained HTML file with the expected sections.

The page's only scripts are inline: plotly.js (the interactive view's library)
and the view itself. A headless browser loads it in ``test_report_browser.py``.
"""

import base64
import html
import json
import struct
import zlib
from html.parser import HTMLParser

import numpy as np
import pytest

from skelid import registry
from skelid.cli import main
from skelid.errors import SkelidError
from skelid.estimators.base import RNG, Setting, positive_or_none
from skelid.estimators.paper import PaperFilter
from skelid.estimators.uncertainty.posterior import GridPosterior
from skelid.io import write_trc
from skelid.report import NOT_AVAILABLE, SECTIONS, write_report
from skelid.result import FitResult, FrameCounts, NoiseEstimate, ParameterEstimate
from skelid.simulate import builtin_model, simulate
from tests.conftest import EXAMPLES

HEADINGS = [title for _, title in SECTIONS]
VOID = {"img", "meta", "br", "hr", "link", "input", "col", "wbr"}


class _Scan(HTMLParser):
    """Headings, images, links, and whether every element is closed in order."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack, self.errors = [], []
        self.headings = {"h1": [], "h2": [], "h3": []}
        self.images, self.urls = [], []
        self.scripts, self.outside = [], []  # inline script bodies; text outside scripts
        self._text = None
        self._script = None
        self.doctype = False

    def handle_decl(self, decl):
        self.doctype |= decl.lower() == "doctype html"

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a.get("src", ""))
        self.urls += [(tag, k, v) for k, v in attrs if k in ("src", "href", "action", "data")]
        if tag in ("iframe", "link", "object", "embed") or (tag == "script" and "src" in a):
            self.errors.append(f"<{tag}> {a} is not allowed in a self-contained report")
        if tag == "script":
            self._script = []
        if tag not in VOID:
            self.stack.append(tag)
        if tag in self.headings:
            self._text = []

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1:] or 'nothing'}")
            return
        self.stack.pop()
        if tag == "script":
            self.scripts.append("".join(self._script))
            self._script = None
        if tag in self.headings and self._text is not None:
            self.headings[tag].append("".join(self._text).strip())
            self._text = None

    def handle_data(self, data):
        if self._script is not None:
            self._script.append(data)
            return
        self.outside.append(data)
        if self._text is not None:
            self._text.append(data)


def _png_ok(data: bytes):
    """A whole PNG: signature, IHDR first, every chunk's CRC right, IEND last."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, kinds = 8, []
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        (crc,) = struct.unpack(">I", data[pos + 8 + n:pos + 12 + n])
        assert zlib.crc32(kind + body) == crc, kind
        kinds.append(kind)
        if kind == b"IHDR":
            w, h = struct.unpack(">II", body[:8])
            assert w > 100 and h > 100
        pos += 12 + n
    assert kinds[0] == b"IHDR" and kinds[-1] == b"IEND" and pos == len(data)


def _check_html(path, min_images: int) -> tuple[str, _Scan]:
    text = path.read_text(encoding="utf-8")
    scan = _Scan()
    scan.feed(text)
    scan.close()
    assert scan.doctype and not scan.errors and not scan.stack, (scan.errors, scan.stack)
    assert scan.headings["h2"] == HEADINGS
    for tag, attr, url in scan.urls:  # nothing to fetch: in-page anchors and embedded images only
        if attr == "href":
            assert url.startswith("#"), url
        else:
            assert tag == "img" and url.startswith("data:image/png;base64,"), url
    assert len(scan.images) >= min_images
    for src in scan.images:
        _png_ok(base64.b64decode(src.split(",", 1)[1], validate=True))
    outside = "".join(scan.outside)
    assert "http://" not in outside and "https://" not in outside
    return text, scan


def _section(text: str, title: str) -> str:
    start = text.index(f">{title}</h2>")
    end = text.find("<h2", start)
    return text[start:end if end > 0 else None]


# ----------------------------------------------------------------------------- paper method, end to end
@pytest.fixture(scope="module")
def paper_fit(tmp_path_factory):
    d = tmp_path_factory.mktemp("paper")
    trial = simulate(builtin_model("case-a"), sigma=8.0, n_frames=160, rng=np.random.default_rng(3))
    y = np.array(trial.data.positions)
    y[40:60, 2] = np.nan  # a gap, to show in the overview
    write_trc(d / "arm.trc", trial.data.replace(positions=y))
    assert main(["fit", str(EXAMPLES / "case_a.toml"), str(d / "arm.trc"), "--method", "paper",
                 "--out", str(d / "fit"), "--quiet"]) == 0
    return d


def test_fit_out_writes_what_the_report_needs(paper_fit):
    res = json.loads((paper_fit / "fit" / "result.json").read_text())
    assert res["schema_version"] == 1 and set(res["results"]) == {"paper"}
    prov = res["context"]["provenance"]
    assert prov["command"][:2] == ["skelid", "fit"] and "--out" in prov["command"]
    assert set(prov["versions"]) >= {"python", "numpy", "scipy", "skelid", "ezc3d"}
    ov = res["context"]["data_overview"]
    assert (ov["n_frames"], ov["n_markers"], ov["rate_hz"], ov["units"]) == (160, 3, 100.0, "mm")
    gaps = {m["name"]: (m["frames_missing"], m["gaps"], m["longest_gap"]) for m in ov["markers"]}
    assert gaps == {"A": (0, 0, 0), "B": (0, 0, 0), "C": (20, 1, 20)}
    with np.load(paper_fit / "fit" / "arrays.npz") as z:
        assert z["run/markers"].shape == (160, 3, 2) and list(z["run/marker_names"]) == ["A", "B", "C"]
        assert float(z["run/rate"]) == 100.0 and str(z["run/units"]) == "mm"
        assert list(z["paper/posterior.history_steps"]) == [50, 100]
        assert z["paper/posterior.history.0"].shape == (2, z["paper/posterior.axis.0"].size)
        assert z["paper/measured"].shape == (160,)


def test_report_of_a_paper_fit(paper_fit, capfd):
    out = paper_fit / "report.html"
    assert main(["report", str(paper_fit / "fit"), "--out", str(out)]) == 0
    assert "report written to" in capfd.readouterr().out
    text, scan = _check_html(out, min_images=4)  # trajectories, gaps, posterior history, MAP per step, final
    assert "Method: paper" in scan.headings["h3"]
    assert NOT_AVAILABLE in _section(text, "Residuals per marker")
    assert NOT_AVAILABLE in _section(text, "Identifiability")
    assert NOT_AVAILABLE in _section(text, "Final posterior")  # no Cramér–Rao bound for the paper method
    assert "skelid fit " in _section(text, "How this result was made")
    assert "marker C is missing in 20 of 160 frames" in _section(text, "Warnings")
    assert "data:image/png;base64," in _section(text, "Posterior evolution")


def test_report_without_arrays_still_works(paper_fit, tmp_path):
    d = tmp_path / "only-json"
    d.mkdir()
    (d / "result.json").write_bytes((paper_fit / "fit" / "result.json").read_bytes())
    path, notes = write_report(d)
    assert path == d / "report.html" and any("no arrays.npz" in n for n in notes)
    text, _ = _check_html(path, min_images=1)  # the final posterior, from the JSON summary alone
    assert NOT_AVAILABLE in _section(text, "Marker trajectories")


# ----------------------------------------------------------------------------- a fuller result, by hand
def write_legacy(d, result: dict, arrays: dict):
    """Write a result given in the flat layout before schema version 1 through the serializer."""
    from skelid.io.legacy import run_from_legacy
    from skelid.io.results import write_run

    d.mkdir(parents=True)
    write_run(d, run_from_legacy(result, arrays))
    return d


def _handmade(d):
    rng = np.random.default_rng(0)
    F, t = 200, np.arange(200) / 100.0
    markers = rng.normal(0, 100, (F, 3, 3)) + np.array([0, 300, 600])[None, :, None]
    markers[30:60, 1] = np.nan
    L_axis, o_axis = np.linspace(240, 260, 81), np.linspace(-20, 40, 61)

    def bump(x, m, s):
        w = np.exp(-0.5 * ((x - m) / s) ** 2)
        return w / w.sum()

    params = {"L": {"map": 250.25, "mean": 250.1, "sd": 0.8, "ci95": [248.5, 251.7], "crlb_sd": 0.75},
              "off": {"map": 11.0, "mean": 12.5, "sd": 9.0, "ci95": [-5.0, 30.0], "crlb_sd": 9.5}}
    result = {
        "model": "handmade", "data": "trial.c3d", "units": "mm", "frames_total": F,
        "truth": {"L": 250.0, "off": 12.0},
        "methods": {
            "marker": {**params, "frames_used": F, "sigma": {"value": 2.1, "ci95": [1.9, 2.3], "fixed": False},
                       "identifiability": [{"parameter": "L", "crlb_sd": 0.75, "status": "identified"},
                                           {"parameter": "off", "crlb_sd": 9.5, "status": "poorly identified"}],
                       "warnings": ["parameter off is poorly identified (marker method)"]},
            "laplace": {**params, "sigma": {"value": 2.0, "fixed": True}},
        },
        "warnings": ["marker M2 is missing in 30 of 200 frames (15 %, 1 gaps, longest 30 frames)"],
        "command": ["skelid", "fit", "arm.toml", "trial.c3d", "--method", "marker", "--out", str(d)],
        "cwd": "/home/someone", "versions": {"python": "3.11", "numpy": "2", "scipy": "1", "skelid": "0.1",
                                             "ezc3d": "1.5"},
        "data_overview": {"source": "trial.c3d", "format": "c3d", "n_frames": F, "n_markers": 3, "dim": 3,
                          "rate_hz": 100.0, "units": "m", "duration_s": 2.0,
                          "model_markers": {"M1": "S:M1", "M2": "S:M2", "M3": "S:M3"},
                          "markers": [{"name": f"S:M{k}", "used_by_model": True, "frames_missing": 30 * (k == 2),
                                       "gaps": int(k == 2), "longest_gap": 30 * (k == 2)} for k in (1, 2, 3)]},
        "model_parameters": {"L": {"kind": "length", "prior": {"type": "uniform", "lower": 200, "upper": 300},
                                   "nominal": 255.0}},
    }
    arrays = {
        "markers": markers, "marker_names": np.array(["M1", "M2", "M3"]), "rate": np.array(100.0),
        "units": np.array("mm"),
        "marker.posterior.names": np.array(["L", "off"]), "marker.posterior.kind": np.array("grid"),
        "marker.posterior.axis.0": L_axis, "marker.posterior.axis.1": o_axis,
        "marker.posterior.marginal.0": bump(L_axis, 250.1, 0.8),
        "marker.posterior.marginal.1": bump(o_axis, 12.5, 9.0),
        "marker.posterior.history_steps": np.array([50, 100]),
        "marker.posterior.history.0": np.stack([bump(L_axis, 251, 2.5), bump(L_axis, 250.5, 1.5)]),
        "marker.posterior.history.1": np.stack([bump(o_axis, 8, 15), bump(o_axis, 10, 12)]),
        "marker.residuals": np.abs(rng.normal(0, 2, (F, 3))) + np.array([0, 0, 1])[None] * 6 * np.sin(t)[:, None],
        "marker.crlb_sd": np.array([0.75, 9.5]),
        "laplace.posterior.names": np.array(["L", "off"]), "laplace.posterior.kind": np.array("gaussian"),
        "laplace.posterior.mean": np.array([250.1, 12.5]), "laplace.posterior.cov": np.diag([0.64, 81.0]),
        "laplace.posterior.history_steps": np.array([50, 100, 200]),
        "laplace.posterior.history_mean": np.array([[251.0, 8.0], [250.5, 10.0], [250.1, 12.5]]),
        "laplace.posterior.history_cov": np.stack([np.diag([4.0, 200.0]), np.diag([2.0, 120.0]),
                                                   np.diag([0.64, 81.0])]),
    }
    return write_legacy(d, result, arrays)


def test_report_of_a_fuller_result(tmp_path):
    d = _handmade(tmp_path / "full")
    path, notes = write_report(d, tmp_path / "sub" / "full.html")
    assert notes == []
    # trajectories, gaps, 2 + 2 evolution, 2 final, 1 residuals
    text, scan = _check_html(path, min_images=9)
    assert {"Method: marker", "Method: laplace"} <= set(scan.headings["h3"])
    res = _section(text, "Residuals per marker")
    assert res.count(NOT_AVAILABLE) == 1 and "lag-1 autocorrelation" in res  # laplace has none
    ident = _section(text, "Identifiability")
    assert "poorly identified" in ident and ident.count(NOT_AVAILABLE) == 1
    final = _section(text, "Final posterior")
    assert "0.75" in final and "9.5" in final and NOT_AVAILABLE not in final
    assert "[1.9, 2.3]" in final and "estimated" in final
    warn = _section(text, "Warnings")
    assert "M2 is missing" in warn and "poorly identified (marker method)" in warn
    prov = _section(text, "How this result was made")
    assert "skelid fit arm.toml trial.c3d --method marker" in prov and "ezc3d" in prov
    assert "S:M2" in _section(text, "Data overview")


# ----------------------------------------------------------------------------- a fuller estimator through fit
class _MarkerLike:
    """Stands in for an estimator with every attribute the report can use."""

    name = "marker"
    settings = (Setting("sigma", positive_or_none, "a positive noise level", cli="sigma"), RNG)

    def __init__(self, model, sigma=None, rng=None):
        self.model = model
        self.sigma = sigma
        self.rng = rng

    def fit(self, y, progress=None):
        from skelid.estimators.base import prepare

        y = prepare(self.model, y) if hasattr(y, "positions") else y
        p = self.model.parameters[0]
        grid = p.grid
        post = GridPosterior.from_log_prior((p.name,), (grid,), p.prior.log_pdf(grid))
        F = len(y)
        for t in range(F):
            post = post.update(-0.5 * ((grid - 250.0) / 40.0) ** 2, snapshot=t + 1 in (50, 100))
        self.posterior_ = post
        self.crlb_sd_ = np.array([post.sd[0] * 0.9])
        self.sigma_ = 3.0
        drift = 20.0 * np.sin(np.arange(F) / 15.0)  # slow drift on marker A: soft-tissue artefact
        self.residuals_ = np.abs(np.random.default_rng(0).normal(0, 3, (F, y.shape[1])))
        self.residuals_[:, 0] += np.abs(drift)
        return self

    def result(self):
        name, post = self.model.parameter_names[0], self.posterior_
        ci = post.credible_interval(0.95)[0]
        p = ParameterEstimate(name, "mm", post.map[0], post.mean[0], post.sd[0], tuple(ci),
                              crlb_sd=float(self.crlb_sd_[0]))
        F = len(self.residuals_)
        return FitResult("marker", {name: p}, noise=NoiseEstimate(self.sigma_, (2.8, 3.2)), frames=FrameCounts(F, F),
                         diagnostics={"identifiability": [{"parameter": name, "crlb_sd": float(self.crlb_sd_[0]),
                                                           "status": "identified"}]},
                         arrays={"residuals": self.residuals_})


def test_fit_and_report_with_a_fuller_estimator(tmp_path, monkeypatch, capfd):
    monkeypatch.setattr(registry, "estimators", lambda: {"paper": PaperFilter, "marker": _MarkerLike})
    trial = simulate(builtin_model("case-a"), sigma=5.0, n_frames=120, rng=np.random.default_rng(4))
    write_trc(tmp_path / "arm.trc", trial.data)
    out = tmp_path / "fit"
    assert main(["fit", str(EXAMPLES / "case_a.toml"), str(tmp_path / "arm.trc"), "--method", "marker",
                 "--method", "paper", "--out", str(out)]) == 0
    err = capfd.readouterr().err
    assert err.count("residuals of marker A (marker method") == 1  # once, one short line; in full below
    with np.load(out / "arrays.npz") as z:
        assert z["marker/residuals"].shape == (120, 3)
        assert list(z["marker/posterior.history_steps"]) == [50, 100]
    res = json.loads((out / "result.json").read_text())
    assert res["results"]["marker"]["parameters"]["L2"]["crlb_sd"] > 0
    assert any("residuals of marker A" in w["message"] and "soft-tissue artefact" in w["message"]
               for w in res["warnings"])
    path, _ = write_report(out)
    text, _ = _check_html(path, min_images=6)
    residuals = _section(text, "Residuals per marker")
    assert residuals.count(NOT_AVAILABLE) == 1  # the paper method has none, the marker method has them
    assert _section(text, "Identifiability").count(NOT_AVAILABLE) == 1


# ----------------------------------------------------------------------------- names, summary, the fitted body
ODD = {"marker": ["$\\foo$", "<script>alert(1)</script>", "a&b"], "parameter": "$\\alpha$"}


def odd_result(d, n_frames: int = 90, with_pose: bool = True):
    """A hand-made fit of a 3-D tree whose names are not safe as HTML or figure text.

    The poses are the simulation's (no fit runs); the marker method's result did not
    converge and its first parameter is poorly identified.
    """
    from skelid.model import model_from_dict
    from tests.helpers import tree_3d

    spec = tree_3d().to_dict()
    for k, name in enumerate(ODD["marker"]):
        spec["markers"][k]["name"] = name
    spec["parameters"][0]["name"] = ODD["parameter"]
    model = model_from_dict(spec, "odd")
    trial = simulate(model, n_frames=n_frames, sigma=2.0, rng=np.random.default_rng(5))
    y = np.array(trial.data.positions)
    y[10:20, 4] = np.nan
    names = model.parameter_names
    est = {n: {"map": float(v), "mean": float(v), "sd": 1.0, "ci95": [float(v) - 2, float(v) + 2], "crlb_sd": 0.9}
           for n, v in zip(names, trial.theta, strict=True)}
    others = [{"name": f"extra{k}", "used_by_model": False, "frames_missing": 5 * k, "gaps": int(k > 0),
               "longest_gap": 5 * k} for k in range(4)]
    result = {
        "model": "odd", "data": "odd.trc", "units": "mm", "frames_total": n_frames,
        "methods": {"marker": {**est, "frames_used": n_frames,
                               "sigma": {"value": 2.0, "ci95": [1.9, 2.1], "fixed": False},
                               "lengths": {"hip-knee": {"value": 400.0, "sd": 1.0, "ci95": [398.0, 402.0]}},
                               "identifiability": [{"parameter": n, "crlb_sd": 0.9,
                                                    "status": "poor" if k == 0 else "identified"}
                                                   for k, n in enumerate(names)],
                               "warnings": ["the joint fit stopped before converging; the estimate may be off",
                                            f"parameter {names[0]} is poorly identified for this motion"]}},
        "warnings": [f"marker {ODD['marker'][1]} is missing in 10 of {n_frames} frames"],
        "data_overview": {"source": "odd.trc", "format": "trc", "n_frames": n_frames, "n_markers": 14, "dim": 3,
                          "rate_hz": 100.0, "units": "mm", "duration_s": n_frames / 100,
                          "model_markers": {m: m for m in model.marker_names},
                          "markers": [{"name": m, "used_by_model": True, "frames_missing": 10 * (k == 4),
                                       "gaps": int(k == 4), "longest_gap": 10 * (k == 4)}
                                      for k, m in enumerate(model.marker_names)] + others},
        "model_description": model.to_dict(),
    }
    arrays = {"markers": y, "marker_names": np.array(model.marker_names), "rate": np.array(100.0),
              "units": np.array("mm"), "marker.crlb_sd": np.full(len(names), 0.9)}
    if with_pose:
        arrays["marker.pose"] = trial.pose
    return write_legacy(d, result, arrays)


def test_summary_answers_first(tmp_path):
    path, _ = write_report(odd_result(tmp_path / "odd"), tmp_path / "odd.html")
    text, scan = _check_html(path, min_images=3)
    assert scan.headings["h2"][:2] == ["Summary", "The fitted body"]
    summary = _section(text, "Summary")
    # every estimate, its interval and bound are on the first screen, with its warnings beside it
    for name in ("$\\alpha$", "hip_x", "s1_z", "hip-knee", "marker noise σ"):
        assert html.escape(name) in summary, name
    assert summary.count("0.9") >= 3 and "[1.9, 2.1]" in summary
    row = summary[summary.index(html.escape(ODD["parameter"])):]
    row = row[:row.index("</tr>")]
    assert "poorly identified" in row and "status-poor" in row
    fit_row = summary[summary.index('<tr class="fit">'):]
    assert "stopped before converging" in fit_row[:fit_row.index("</tr>")]
    assert 'class="severe">the joint fit stopped before converging' in summary
    assert "missing in 10 of 90 frames" in summary  # a warning about no parameter: below the table


def test_gap_table_lists_the_model_markers_only(tmp_path):
    path, _ = write_report(odd_result(tmp_path / "odd"), tmp_path / "odd.html")
    text, _ = _check_html(path, min_images=3)
    gaps = _section(text, "Data overview")
    gaps = gaps[gaps.index("Gaps of the model"):]
    assert gaps.count("<tr") == 1 + 10 + 1  # head, the model's 10 markers, one line for the rest
    assert "4 other markers in the file, not used by the model (3 with gaps)" in gaps


def test_names_are_shown_as_written(tmp_path):
    path, _ = write_report(odd_result(tmp_path / "odd"), tmp_path / "odd.html")
    text, scan = _check_html(path, min_images=3)
    outside = "".join(scan.outside)
    for name in [*ODD["marker"], ODD["parameter"]]:
        assert name in outside, name  # the parser unescapes: the page shows the name itself
    assert "<script>alert(1)" not in text  # nowhere as markup, not even inside the view's data
    view = next(s for s in scan.scripts if "Plotly.newPlot" in s)
    # plotly's pseudo-HTML escaped (&lt;), then the JSON's & escaped for the script element
    assert "\\u0026lt;script\\u0026gt;alert(1)" in view and '"typesetMath":false' in view


def test_the_view_follows_the_fitted_poses(tmp_path):
    from skelid.model import model_from_dict
    from skelid.model.kinematics import forward_kinematics
    from skelid.viewer import figure_spec

    d = odd_result(tmp_path / "odd")
    res = json.loads((d / "result.json").read_text())
    model = model_from_dict(res["context"]["model_description"])
    with np.load(d / "arrays.npz") as z:
        pose, y = z["marker/pose"], z["run/markers"]
    theta = [res["results"]["marker"]["parameters"][n]["mean"] for n in model.parameter_names]
    spec = figure_spec(model, theta, pose, y, max_frames=30)
    assert spec["meta"] == {"dim": 3, "frames_total": 90, "frames_shown": 30, "stride": 3, "n_segments": 5,
                            "n_markers": 10}
    kin = forward_kinematics(model, np.array(theta), pose[[0, 3, 87]])
    joints = {f["name"]: f["data"][4] for f in spec["frames"]}
    for k, t in enumerate((0, 3, 87)):
        got = np.array([joints[str(t)][a] for a in "xyz"], float).T
        np.testing.assert_allclose(got, kin.p_world_seg[k], atol=0.051)  # rounded to 0.1 mm
        markers = np.array([spec["frames"][t // 3]["data"][1][a] for a in "xyz"], float).T
        np.testing.assert_allclose(markers, kin.markers[k], atol=0.051)  # rounded to 0.1 mm
    assert [t["name"] for t in spec["data"]] == ["measured markers", "model markers", "residual", "segments",
                                                 "joint centres", "marker offsets"]


def test_report_of_a_typed_result(tmp_path):
    """A folder the serializer wrote: parameters named like reserved keys, structured warnings."""
    from skelid.io.results import write_run
    from skelid.result import FitResult, FitRun, FrameCounts, NoiseEstimate, ParameterEstimate
    from skelid.result import Warning as FitWarning

    def est(name, mean, status="identified"):
        return ParameterEstimate(name, "mm", mean, mean, 1.5, (mean - 3, mean + 3), 1.2, status)

    r = FitResult("marker", {"sigma": est("sigma", 101.0), "warnings": est("warnings", 202.0, "poor")},
                  {"lengths": est("lengths", 303.0)}, NoiseEstimate(2.5, (2.4, 2.6)), FrameCounts(50, 48),
                  warnings=(FitWarning("not-converged", "the joint fit stopped before converging"),
                            FitWarning("poorly-identified", "this one is poorly identified", ("warnings",))),
                  arrays={"residuals": np.abs(np.random.default_rng(0).normal(size=(50, 2)))})
    run = FitRun({"marker": r}, {"model": "typed", "data": "t.trc", "units": "mm"},
                 arrays={"markers": np.zeros((50, 2, 2)), "marker_names": np.array(["a", "b"]),
                         "rate": np.array(50.0), "units": np.array("mm")})
    write_run(tmp_path / "fit", run)
    path, notes = write_report(tmp_path / "fit")
    text, _ = _check_html(path, min_images=2)
    summary = _section(text, "Summary")
    for name, value in (("sigma", "101"), ("warnings", "202"), ("lengths", "303")):
        row = summary[summary.index(f"<td class=\"l\">{name}"):]
        assert value in row[:row.index("</tr>")], name
    row = summary[summary.index('<td class="l">warnings'):]
    assert "this one is poorly identified" in row[:row.index("</tr>")] and "status-poor" in row[:row.index("</tr>")]
    assert 'class="severe">the joint fit stopped before converging' in summary
    assert "[2.4, 2.6]" in summary and "Frames used: 48 of 50" in _section(text, "Final posterior")


def test_a_warning_stays_with_its_method(tmp_path):
    """A run-level copy of one method's warning is not shown beside another method's estimates."""
    from skelid.io.results import read_run, write_run
    from skelid.result import FitRun
    from skelid.result import Warning as FitWarning

    d = odd_result(tmp_path / "odd")
    run = read_run(d)
    dropped = FitWarning("frames-skipped", "paper method dropped 9 of 90 frames (no converged solution inside "
                         "the interval)")
    paper = FitResult("paper", {"L": ParameterEstimate("L", "mm", 1.0, 1.0, 0.1, (0.8, 1.2))}, warnings=(dropped,))
    results = {**run.results, "paper": paper}
    write_run(d, FitRun(results, run.context, (*run.warnings, *run.results["marker"].warnings, dropped),
                        run.arrays))
    path, _ = write_report(d, tmp_path / "two.html")
    text, _ = _check_html(path, min_images=3)
    summary = _section(text, "Summary")
    paper = summary[summary.index("Method: paper"):]
    assert "stopped before converging" not in paper and "dropped 9 of 90 frames" in paper
    assert 'class="severe">paper method dropped' not in paper  # frames dropped: a warning, not a broken fit


def test_summary_shows_model_spread_and_noise_per_marker(tmp_path):
    """With model alternatives, each estimate's spread over the models sits in its row; the noise of
    each marker is listed under the table, highest first."""
    from skelid.io.results import write_run
    from skelid.result import FitRun

    def est(name, mean):
        return ParameterEstimate(name, "mm", mean, mean, 1.0, (mean - 2, mean + 2), 0.9)

    spread = {"L": {"values": {"main": 250.0, "other": 256.0}, "spread": 6.0, "sd_over_models": 4.2,
                    "largest_sd": 1.0},
              "off": {"values": {"main": 10.0, "other": 10.5}, "spread": 0.5, "sd_over_models": 0.35,
                      "largest_sd": 1.0}}
    sens = {"models": ["main", "other"], "estimates": {m: {k: {"value": v["values"][m], "sd": 1.0}
                                                           for k, v in spread.items()} for m in ("main", "other")},
            "spread": spread,
            "average": {"method": "stacking", "unit": "1 s of a trial's frames", "blocks": 12,
                        "weights": {"main": 0.75, "other": 0.25},
                        "quantities": {"L": {"value": 251.5, "sd": 3.0, "interval": [248.0, 257.5],
                                             "models": ["main", "other"]}}}}
    r = FitResult("marker", {"L": est("L", 250.0), "off": est("off", 10.0)},
                  noise=NoiseEstimate(2.0, (1.9, 2.1), per_marker={"KNE": 1.5, "<ANK>": 4.5, "HIP": 2.0}),
                  diagnostics={"model_sensitivity": sens})
    write_run(tmp_path / "fit", FitRun({"marker": r}, {"model": "m", "units": "mm"}))
    path, _ = write_report(tmp_path / "fit")
    text, _ = _check_html(path, min_images=1)
    summary = _section(text, "Summary")
    assert "spread over models [mm]" in summary
    row = summary[summary.index('<td class="l">L</td>'):]
    row = row[:row.index("</tr>")]
    assert 'class="warn" title="main: 250, other: 256">6<' in row  # wider than any model's own sd
    assert "average 251.5 [248, 257.5]" in row  # the models' average under the spread
    assert "stacking over 12 blocks" in summary and "main 0.75, other 0.25" in summary
    row = summary[summary.index('<td class="l">off</td>'):]
    assert 'class="" title="main: 10, other: 10.5">0.5<' in row[:row.index("</tr>")]
    noise = summary[summary.index("Marker noise per marker"):]
    assert noise.index("&lt;ANK&gt; 4.5") < noise.index("HIP 2") < noise.index("KNE 1.5")
    assert '<span class="warn">&lt;ANK&gt; 4.5</span>' in noise  # above 1.5 times the pooled level
    # a malformed spread record is refused before the report is written
    doc = json.loads((tmp_path / "fit" / "result.json").read_text())
    doc["results"]["marker"]["diagnostics"]["model_sensitivity"]["spread"]["L"]["spread"] = "wide"
    (tmp_path / "fit" / "result.json").write_text(json.dumps(doc))
    with pytest.raises(SkelidError, match=r"model_sensitivity\.spread\.L\.spread: expected a number"):
        write_report(tmp_path / "fit")
    doc["results"]["marker"]["diagnostics"]["model_sensitivity"]["spread"]["L"]["spread"] = 6.0
    doc["results"]["marker"]["diagnostics"]["model_sensitivity"]["average"]["weights"]["main"] = "most"
    (tmp_path / "fit" / "result.json").write_text(json.dumps(doc))
    with pytest.raises(SkelidError, match=r"model_sensitivity\.average\.weights\.main: expected a number"):
        write_report(tmp_path / "fit")


def test_old_layout_and_demo_folders_are_refused_in_one_line(tmp_path, capfd):
    old = tmp_path / "old"
    old.mkdir()
    (old / "result.json").write_text(json.dumps({"units": "mm", "methods": {"marker": {
        "L2": {"map": 250.0, "mean": 250.0, "sd": 1.0, "ci95": [248.0, 252.0]}}}}))
    demo = tmp_path / "demo"
    demo.mkdir()
    (demo / "summary.json").write_text("{}")
    for folder, needle in ((old, "before result schema version 1"), (demo, "holds demo output")):
        assert main(["report", str(folder), "--out", str(tmp_path / "r.html")]) == 2
        err = capfd.readouterr().err.strip().splitlines()
        assert len(err) == 1 and needle in err[0] and "skelid fit" in err[0], err
    assert not (tmp_path / "r.html").exists()


# ----------------------------------------------------------------------------- arrays that do not hang together
def _with_paper_arrays(src, dst, change):
    """A copy of result folder ``src`` in ``dst`` with the paper method's arrays edited by ``change(arrays)``
    in ``arrays.npz`` and in the index of ``result.json`` alike (so that each array has the size the index says)."""
    res = json.loads((src / "result.json").read_text())
    with np.load(src / "arrays.npz") as z:
        own = {k.removeprefix("paper/"): z[k] for k in z.files if k.startswith("paper/")}
        rest = {k: z[k] for k in z.files if not k.startswith("paper/")}
    change(own)
    res["results"]["paper"]["arrays"] = {k: {"shape": list(v.shape), "dtype": v.dtype.str} for k, v in own.items()}
    dst.mkdir()
    (dst / "result.json").write_text(json.dumps(res))
    np.savez(dst / "arrays.npz", **rest, **{f"paper/{k}": v for k, v in own.items()})
    return dst


def _drop(key):
    return lambda a: a.pop(key)


def _set(key, value):
    return lambda a: a.__setitem__(key, value(a) if callable(value) else value)


#: how the arrays are damaged, and what the one line says
DAMAGED_ARRAYS = {
    "marginal-missing": (_drop("posterior.marginal.0"),
                         r"paper/posterior.axis.0\] is there but paper/posterior.marginal.0 is not"),
    "axis-missing": (_drop("posterior.axis.0"),
                     r"paper/posterior.marginal.0\] is there but paper/posterior.axis.0 is not"),
    "axis-shorter": (_set("posterior.axis.0", lambda a: a["posterior.axis.0"][:5]),
                     r"posterior.marginal.0\] has shape \(201,\), not \(5,\)"),
    "axis-not-finite": (_set("posterior.axis.0", np.full(201, np.nan)),
                        r"posterior.axis.0\] holds values that are not finite"),
    "history-steps-short": (_set("posterior.history_steps", np.array([50])),
                            r"posterior.history.0\] has shape \(2, 201\), not \(1, 201\)"),
    "names-scalar": (_set("posterior.names", np.array("L2")), r"posterior.names\] is a 0-d array"),
    "measured-short": (_set("measured", lambda a: a["measured"][:10]),
                       r"paper/measured\] has shape \(10,\), not \(160,\)"),
    "cov-without-mean": (_set("posterior.cov", np.ones((1, 1))),
                         r"posterior.cov\] is there but paper/posterior.mean is not"),
    "samples-too-wide": (_set("samples", np.ones((10, 2))), r"paper/samples\] has shape \(10, 2\), not \(10, 1\)"),
    "weights-without-samples": (_set("sample_weights", np.ones(10)),
                                r"sample_weights\] is there but paper/samples is not"),
    "residuals-empty": (_set("residuals", np.zeros((0, 3))), r"paper/residuals\] has no frames"),
    "map-path-2d": (_set("map_path", np.zeros((160, 1))),
                    r"paper/map_path\] is a 2-d array of dtype float64, not the 1-d array"),
}


@pytest.mark.parametrize("damage", list(DAMAGED_ARRAYS))
def test_a_result_whose_arrays_do_not_hang_together_is_refused_in_one_line(paper_fit, tmp_path, capfd, damage):
    import re

    change, needle = DAMAGED_ARRAYS[damage]
    d = _with_paper_arrays(paper_fit / "fit", tmp_path / "edited", change)
    capfd.readouterr()
    assert main(["report", str(d), "--quiet"]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(needle, err[0]) and "(fix: " in err[0], err
    assert not (d / "report.html").exists()


def test_extra_arrays_that_hang_together_are_accepted(paper_fit, tmp_path):
    def add_samples(a):
        a["samples"] = np.linspace(240.0, 260.0, 30)[:, None]
        a["sample_weights"] = np.full(30, 1.0 / 30)

    d = _with_paper_arrays(paper_fit / "fit", tmp_path / "with-samples", add_samples)
    path, _ = write_report(d)
    _check_html(path, min_images=4)
