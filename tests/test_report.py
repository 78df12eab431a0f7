"""`skelid report`: one valid, self-contained HTML file with the expected sections."""

import base64
import json
import struct
import zlib
from html.parser import HTMLParser

import numpy as np
import pytest

from skelid import registry
from skelid.cli import main
from skelid.estimators.base import RNG, Setting, positive_or_none
from skelid.estimators.paper import PaperFilter
from skelid.estimators.posterior import GridPosterior
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
        self._text = None
        self.doctype = False

    def handle_decl(self, decl):
        self.doctype |= decl.lower() == "doctype html"

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a.get("src", ""))
        self.urls += [(tag, k, v) for k, v in attrs if k in ("src", "href", "action", "data")]
        if tag in ("script", "iframe", "link", "object", "embed"):
            self.errors.append(f"<{tag}> is not allowed in a self-contained report")
        if tag not in VOID:
            self.stack.append(tag)
        if tag in self.headings:
            self._text = []

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1:] or 'nothing'}")
            return
        self.stack.pop()
        if tag in self.headings and self._text is not None:
            self.headings[tag].append("".join(self._text).strip())
            self._text = None

    def handle_data(self, data):
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
    assert "http://" not in text and "https://" not in text
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
    assert res["command"][:2] == ["skelid", "fit"] and "--out" in res["command"]
    assert set(res["versions"]) >= {"python", "numpy", "scipy", "skelid", "ezc3d"}
    ov = res["data_overview"]
    assert (ov["n_frames"], ov["n_markers"], ov["rate_hz"], ov["units"]) == (160, 3, 100.0, "mm")
    gaps = {m["name"]: (m["frames_missing"], m["gaps"], m["longest_gap"]) for m in ov["markers"]}
    assert gaps == {"A": (0, 0, 0), "B": (0, 0, 0), "C": (20, 1, 20)}
    with np.load(paper_fit / "fit" / "arrays.npz") as z:
        assert z["markers"].shape == (160, 3, 2) and list(z["marker_names"]) == ["A", "B", "C"]
        assert float(z["rate"]) == 100.0 and str(z["units"]) == "mm"
        assert list(z["paper.posterior.history_steps"]) == [50, 100]
        assert z["paper.posterior.history.0"].shape == (2, z["paper.posterior.axis.0"].size)
        assert z["paper.measured"].shape == (160,)


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
    d.mkdir()
    (d / "result.json").write_text(json.dumps(result))
    np.savez(d / "arrays.npz", **arrays)
    return d


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
                                                           "status": "identified"}]})


def test_fit_and_report_with_a_fuller_estimator(tmp_path, monkeypatch, capfd):
    monkeypatch.setattr(registry, "estimators", lambda: {"paper": PaperFilter, "marker": _MarkerLike})
    trial = simulate(builtin_model("case-a"), sigma=5.0, n_frames=120, rng=np.random.default_rng(4))
    write_trc(tmp_path / "arm.trc", trial.data)
    out = tmp_path / "fit"
    assert main(["fit", str(EXAMPLES / "case_a.toml"), str(tmp_path / "arm.trc"), "--method", "marker",
                 "--method", "paper", "--out", str(out), "--quiet"]) == 0
    err = capfd.readouterr().err
    assert err.count("residuals of marker A (marker method") == 1 and "soft-tissue artefact" in err
    with np.load(out / "arrays.npz") as z:
        assert z["marker.residuals"].shape == (120, 3) and z["marker.crlb_sd"].shape == (1,)
        assert list(z["marker.posterior.history_steps"]) == [50, 100]
    res = json.loads((out / "result.json").read_text())
    assert any("residuals of marker A" in w for w in res["warnings"])
    path, _ = write_report(out)
    text, _ = _check_html(path, min_images=6)
    residuals = _section(text, "Residuals per marker")
    assert residuals.count(NOT_AVAILABLE) == 1  # the paper method has none, the marker method has them
    assert _section(text, "Identifiability").count(NOT_AVAILABLE) == 1
