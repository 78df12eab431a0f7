"""The figures README.md and docs/*.md quote are the results files' (benchmarks/render_docs.py)."""

import json
import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from skelid import resources
from skelid.cli import cli
from tests.helpers import load_script

ROOT = Path(__file__).resolve().parents[1]


def _render_docs():
    return load_script(ROOT / "benchmarks" / "render_docs.py")


def _blocks(text, rd):
    return [(m.group(2), m.group(3), m.start(3)) for m in rd.BLOCK.finditer(text)]


def test_every_generated_block_is_what_the_results_files_give(capsys):
    rd = _render_docs()
    assert rd.main(["--check"]) == 0, capsys.readouterr().out


def test_a_figure_changed_by_hand_in_any_block_is_caught_and_put_back():
    rd = _render_docs()
    n = 0
    for doc in rd.documents():
        text = doc.read_text()
        for name, body, start in _blocks(text, rd):
            m = re.search(r"\d", body.split("<sub>")[0])  # a quoted figure, not the provenance line
            if m is None:  # a placeholder for a benchmark not run yet
                continue
            i = start + m.start()
            edited = text[:i] + ("7" if text[i] != "7" else "3") + text[i + 1:]
            assert rd.render(edited) != edited, f"{doc.name}: a changed figure in block {name} is not caught"
            assert rd.render(edited) == text
            n += 1
    assert n >= 10


def test_every_block_has_a_renderer_and_every_renderer_a_block():
    rd = _render_docs()
    used = [name for doc in rd.documents() for name, _, _ in _blocks(doc.read_text(), rd)]
    assert set(used) == set(rd.RENDERERS)


def test_the_readme_demo_table_is_the_committed_demo_run():
    # read independently of the renderer: each row's mean and interval against benchmarks/results/demo.json
    readme = (ROOT / "README.md").read_text()
    block = readme.split("<!-- results:demo -->", 1)[1].split("<!-- /results:demo -->", 1)[0]
    rows = re.findall(r"^(case_[ab])\s+(\w+)\s+(\w+)\s+([\d.]+)\s+([\d.]+)\s+\[\s*([\d.]+),\s*([\d.]+)\]\s+"
                      r"([\d.]+)\s+(\d+)$", block, re.M)
    demo = json.loads((ROOT / "benchmarks" / "results" / "demo.json").read_text())
    expected = {(c, m) for c in ("case_a", "case_b") for m in demo[c]["results"]}
    assert {(r[0], r[1]) for r in rows} == expected and len(rows) == len(expected)
    for case, method, param, mean, _, lo, hi, _, used in rows:
        r = demo[case]["results"][method]
        p = r["parameters"][param]
        assert float(mean) == pytest.approx(p["mean"], rel=1e-4)
        assert (float(lo), float(hi)) == pytest.approx(tuple(p["interval"]), rel=1e-4)
        assert int(used) == r["frames"]["used"]
    assert "skelid demo --json --seed 0 " in demo["provenance"]["command"]


def test_results_files_hold_the_current_table_only():
    acc = ROOT / "benchmarks" / "results" / "accuracy.json"
    if acc.exists():
        doc = json.loads(acc.read_text())
        assert {r.get("tag") for r in doc["rows"]} == {"current"}
    assert not list((ROOT / "benchmarks" / "results").glob("*_before.*"))


def test_the_readme_fits_in_a_few_screens_and_its_test_command_is_the_one_ci_runs():
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 250
    ci = (ROOT / ".ci" / "run").read_text()
    command = next(line for line in readme.splitlines() if "pip install \".[test]\"" in line)
    assert command in ci.splitlines()


def test_example_commands_write_outside_the_repository():
    # every --out in the docs' shell examples is a scratch path, except the demo command the README leads with
    n = 0
    for doc in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for block in re.findall(r"```(?:bash|sh|)\n(.*?)```", doc.read_text(), re.S):
            for target in re.findall(r"--out\s+(\S+)", block):
                if target == "demo-output":
                    continue
                assert target.startswith(("/tmp/", "$OUT", "DIR", "FILE")), f"{doc.name}: --out {target}"
                n += 1
    assert n >= 5


@pytest.mark.parametrize("command", ["demo", "simulate", "fit", "batch"])
def test_max_time_help_states_the_default_the_code_uses(command):
    out = CliRunner().invoke(cli, [command, "--help"], terminal_width=200).output
    said = re.search(r"--max-time.*?default (\d+)m", " ".join(out.split()), re.S)
    assert said and int(said.group(1)) * 60 == resources.DEFAULT_MAX_SECONDS
