"""Command line: parse, load, call the library, write. No maths here.

A :class:`~skelid.errors.SkelidError` becomes one line on stderr and exit
status 2; any other exception is a bug and keeps its traceback (status 1).
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import click
import numpy as np

from skelid import __version__
from skelid.errors import SkelidError, SkelidWarning

FIT_EXAMPLE = "skelid fit examples/case_a.toml data.trc --method paper --json"


def _warning_line(message, category, filename, lineno, file=None, line=None):
    """Show a SkelidWarning as one line, once."""
    if issubclass(category, SkelidWarning):
        click.echo(f"skelid: warning: {message}", err=True)
    else:  # pragma: no cover - library warnings keep their usual form
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="skelid")
def cli():
    """skelid: segment lengths and joint centres from motion capture, with honest uncertainty."""
    warnings.showwarning = _warning_line


@cli.command()
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default="demo-output",
              show_default=True, help="Folder for figures and summary.json.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed.")
@click.option("--frames", type=click.IntRange(min=10), default=500, show_default=True)
@click.option("--sigma", type=click.FloatRange(min=0.0), default=15.0, show_default=True,
              help="Marker noise in mm.")
@click.option("--quiet", is_flag=True, help="No progress bar, no table.")
def demo(out_dir, seed, frames, sigma, quiet):
    """Simulate the seed paper's cases A and B, fit them, write figures and summary.json."""
    from skelid import workflows

    summary = workflows.demo(out_dir, seed=seed, n_frames=frames, sigma=sigma, progress=not quiet)
    if not quiet:
        click.echo(workflows.table(summary))
        click.echo(f"figures and summary.json written to {out_dir}")


@cli.command()
@click.argument("model_name")
@click.option("--sigma", type=click.FloatRange(min=0.0), default=15.0, show_default=True,
              help="Marker noise standard deviation in model units.")
@click.option("--frames", type=click.IntRange(min=1), default=500, show_default=True)
@click.option("--rate", type=click.FloatRange(min=0.0, min_open=True), default=100.0, show_default=True)
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--hard-poses", is_flag=True, help="Make joints pass through straight positions.")
@click.option("--noise", type=click.Choice(["iid", "sta"]), default="iid", show_default=True,
              help="i.i.d. Gaussian noise, or that plus soft-tissue artefact.")
@click.option("--sta-amplitude", type=click.FloatRange(min=0.0), default=10.0, show_default=True)
@click.option("--out", "out_path", type=click.Path(dir_okay=False), required=True,
              help="Output file: .trc or .csv.")
def simulate(model_name, sigma, frames, rate, seed, hard_poses, noise, sta_amplitude, out_path):
    """Simulate a trial of MODEL_NAME (case-a, case-b or a model .toml) and write it.

    Example: skelid simulate case-a --sigma 15 --frames 500 --seed 0 --out data.trc
    """
    from skelid import io
    from skelid.simulate import resolve_model
    from skelid.simulate import simulate as run

    model = resolve_model(model_name)
    trial = run(model, n_frames=frames, rate=rate, sigma=sigma, rng=np.random.default_rng(seed),
                hard_poses=hard_poses, noise=noise, sta_amplitude=sta_amplitude)
    suffix = Path(out_path).suffix.lower()
    if suffix == ".csv":
        io.write_csv(out_path, trial.data)
    elif suffix == ".trc":
        io.write_trc(out_path, trial.data)
    else:
        raise click.BadParameter(f"unsupported output type {suffix!r}; use .trc or .csv",
                                 param_hint="--out")
    click.echo(f"wrote {trial.data.n_frames} frames of {trial.data.n_markers} markers to {out_path}")
    for name, value in trial.truth.items():
        click.echo(f"true {name} = {value:g} {model.units}")


@cli.command(epilog=f"Example:\n\n    {FIT_EXAMPLE}")
@click.argument("model_path")
@click.argument("data_path", type=click.Path(dir_okay=False))
@click.option("--method", "method_names", multiple=True,
              help="Estimator (repeat for several): paper, marker. Default: the best available.")
@click.option("--sigma", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Marker noise in model units (default 15 mm for the paper method).")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON on stdout.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Folder for result.json and figures.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--quiet", is_flag=True, help="No table: only warnings and errors (and JSON with --json).")
def fit(model_path, data_path, method_names, sigma, as_json, out_dir, seed, quiet):
    """Fit MODEL_PATH (a .toml model or case-a/case-b) to the markers in DATA_PATH."""
    import json

    from skelid import io, workflows
    from skelid.simulate import resolve_model

    model = resolve_model(model_path)
    data = io.read_markers(data_path)
    names = list(method_names) or [workflows.DEFAULT_METHOD]
    result, fitted = workflows.fit_file(model, data, names, sigma=sigma, seed=seed)
    if out_dir:
        workflows.figures(model, data, fitted, out_dir)
        workflows.write_json(Path(out_dir) / "result.json", result)
    for w in sorted({w for m in result["methods"].values() for w in m.get("warnings", [])}):
        click.echo(f"skelid: warning: {w}", err=True)
    if as_json:
        click.echo(json.dumps(result, indent=2, default=workflows._json_default))
    elif not quiet:
        click.echo(workflows.table(result))


def main(argv=None) -> int:
    """Entry point: run the CLI, turning user errors into one line and exit status 2."""
    try:
        cli.main(args=argv, prog_name="skelid", standalone_mode=False)
    except SkelidError as exc:
        click.echo(f"skelid: error: {exc.one_line()}", err=True)
        return 2
    except click.exceptions.Abort:
        click.echo("skelid: interrupted", err=True)
        return 130
    except click.ClickException as exc:
        exc.show()
        return exc.exit_code
    except click.exceptions.Exit as exc:
        return exc.exit_code
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
