"""Command line: parse, load, call the library, write. No maths here.

A :class:`~skelid.errors.SkelidError` or a usage mistake becomes one line on
stderr (``skelid: error: ...``) and exit status 2; Ctrl-C or SIGTERM exit with
130 or 143 and one line after removing any partial output, and a command that
runs past ``--max-time`` stops the same way with status 2 (:mod:`skelid._stop`);
any other exception is a bug and keeps its traceback (status 1). Warnings are printed once each as
``skelid: warning: ...`` and recorded in the JSON results. ``--json`` puts
only JSON on stdout; progress bars go to stderr and only to a terminal.
"""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import traceback
import warnings
from pathlib import Path

import click
import numpy as np

from skelid import __version__, _stop
from skelid._linalg import one_blas_thread
from skelid.errors import SkelidError, SkelidWarning

FIT_EXAMPLE = """\b
    skelid simulate case-a --frames 300 --seed 0 --out arm.trc
    skelid fit examples/case_a.toml arm.trc --method marker --out arm-fit
    skelid report arm-fit --out arm-report.html"""

EXAMPLES_EPILOG = f"Example (from the skelid repository root):\n\n{FIT_EXAMPLE}"

SEED = click.IntRange(min=0)
N_DRAWS_DEFAULT = 100  # skelid.angles.N_DRAWS, without importing the library at start-up


#: longest line a warning takes on the terminal (its full text is in the result folder and --json)
WARNING_WIDTH = 160
WARNING_PREFIX = "skelid: warning: "


def short_warning(message) -> str:
    """One line of at most :data:`WARNING_WIDTH` characters (with its prefix) for a warning's text
    (:func:`skelid.errors.headline`)."""
    from skelid.errors import headline

    return headline(message, WARNING_WIDTH - len(WARNING_PREFIX))


def _warning_line(message, category, filename, lineno, file=None, line=None):
    """Show a SkelidWarning as one line."""
    if issubclass(category, SkelidWarning):
        click.echo(WARNING_PREFIX + short_warning(message), err=True)
    else:  # pragma: no cover - library warnings keep their usual form
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def _quiet_warnings(ctx: click.Context) -> None:
    """``--quiet``: no warning reaches the terminal for the rest of the command (the results keep them)."""
    ctx.with_resource(warnings.catch_warnings())
    warnings.simplefilter("ignore", SkelidWarning)


def _command(ctx: click.Context) -> list[str]:
    obj = ctx.find_root().obj
    if isinstance(obj, dict) and "argv" in obj:
        return list(obj["argv"])
    return ["skelid", *sys.argv[1:]]


def _echo_warnings(messages, quiet: bool = False, full_in=None) -> None:
    """Each warning once, in order, in one line; ``full_in``: where the whole texts are written."""
    if quiet:
        return
    cut = False
    for w in dict.fromkeys(messages):
        line = short_warning(w)
        cut |= line != " ".join(str(w).split())
        click.echo(WARNING_PREFIX + line, err=True)
    if cut:
        where = f"{Path(full_in) / 'result.json'}" if full_in is not None else "--json, or --out DIR (result.json)"
        click.echo(f"skelid: the warnings in full: {where}", err=True)


def _echo_json(obj) -> None:
    from skelid.io.results import dumps

    click.echo(dumps(obj), nl=False)


def _finite(name: str, value):
    """:func:`skelid.checks.check_finite` (imported when a command runs, so that --help stays quick)."""
    from skelid.checks import check_finite

    return check_finite(name, value)


def _limit_options(f):
    """``--max-memory`` and ``--max-time``: the limits a job's estimated cost must stay under; a job
    that runs past ``--max-time`` all the same is stopped (:func:`_time_limited`)."""
    f = click.option("--max-time", default=None, metavar="DURATION",
                     help="Refuse a job estimated to take longer, and stop one that runs longer (e.g. 2h, "
                          "90m; default 30m or $SKELID_MAX_TIME).")(_time_limited(f))
    return click.option("--max-memory", default=None, metavar="SIZE",
                        help="Refuse a job estimated to need more memory (e.g. 8G, 512M; default 4G or "
                             "$SKELID_MAX_MEMORY).")(f)


def _time_limited(f):
    """Run command ``f`` under its ``--max-time``: past it, the command stops with one line (nothing
    half-written is left; a batch keeps the rows of the trials that finished)."""
    name = f.__name__.replace("model_", "model ")

    @functools.wraps(f)
    def limited(*args, **kwargs):
        from skelid.resources import ENV_TIME, ResourceError, format_seconds

        limits = _limits(kwargs.get("max_memory"), kwargs.get("max_time"))
        left = ("the trials that finished before it are in the table, if any did" if name == "batch"
                else "nothing half-written was left")
        fix = ("run the same command again to fit the rest (the trials in the table are skipped), or raise "
               f"the limit with --max-time or {ENV_TIME}" if name == "batch" else
               f"raise the limit with --max-time or {ENV_TIME}, or give it less work (fewer frames or trials)")
        error = ResourceError(f"skelid {name} ran past its time limit of {format_seconds(limits.seconds)} and was "
                              f"stopped; {left}", fix)
        with _stop.deadline(limits.seconds, error):
            return f(*args, **kwargs)

    return limited


def _limits(max_memory, max_time):
    from skelid.resources import Limits

    return Limits.from_settings(max_memory, max_time)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="skelid")
def cli():
    """skelid: segment lengths and joint centres from motion capture, with honest uncertainty."""
    warnings.showwarning = _warning_line


@cli.command(epilog="Example:\n\n\b\n    skelid demo --out demo-output --frames 500")
@click.option("--out", "out_dir", default="demo-output", show_default=True,
              help="Folder for figures and summary.json (appears only when complete; must be new, "
                   "or see --overwrite).")
@click.option("--seed", type=SEED, default=0, show_default=True, help="Random seed.")
@click.option("--frames", type=click.IntRange(min=10), default=500, show_default=True)
@click.option("--sigma", type=click.FloatRange(min=0.0), default=15.0, show_default=True,
              help="Marker noise in mm.")
@click.option("--json", "as_json", is_flag=True, help="Print summary.json on stdout, nothing else.")
@click.option("--quiet", is_flag=True, help="No progress bar, no table.")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out folder whole (its old contents "
              "are removed).")
@_limit_options
def demo(out_dir, seed, frames, sigma, as_json, quiet, overwrite, max_memory, max_time):
    """Simulate the seed paper's cases A and B, fit them, write figures and summary.json."""
    from skelid import workflows
    from skelid.demo import demo as run_demo
    from skelid.demo import summary_document

    _finite("--sigma", sigma)
    runs = run_demo(out_dir, seed=seed, n_frames=frames, sigma=sigma, progress=not quiet,
                    limits=_limits(max_memory, max_time), overwrite=overwrite)
    if as_json:
        _echo_json(summary_document(runs))
    elif not quiet:
        click.echo(workflows.table(runs))
        click.echo(f"figures and summary.json written to {out_dir}")


@cli.command(epilog="Example:\n\n\b\n    skelid simulate case-a --sigma 15 --frames 500 --seed 0 --out data.trc")
@click.argument("model_name")
@click.option("--sigma", type=click.FloatRange(min=0.0), default=15.0, show_default=True,
              help="Marker noise standard deviation in model units.")
@click.option("--frames", type=click.IntRange(min=1), default=500, show_default=True)
@click.option("--rate", type=click.FloatRange(min=0.0, min_open=True), default=100.0, show_default=True)
@click.option("--seed", type=SEED, default=0, show_default=True)
@click.option("--hard-poses", is_flag=True, help="Make joints pass through straight positions.")
@click.option("--noise", type=click.Choice(["iid", "sta"]), default="iid", show_default=True,
              help="i.i.d. Gaussian noise, or that plus soft-tissue artefact.")
@click.option("--sta-amplitude", type=click.FloatRange(min=0.0), default=10.0, show_default=True)
@click.option("--out", "out_path", required=True, help="Output file: .trc or .csv.")
@click.option("--json", "as_json", is_flag=True, help="Print what was written and the truth as JSON.")
@_limit_options
def simulate(model_name, sigma, frames, rate, seed, hard_poses, noise, sta_amplitude, out_path, as_json,
             max_memory, max_time):
    """Simulate a trial of MODEL_NAME (case-a, case-b or a model .toml) and write it."""
    from skelid import io
    from skelid.simulate import BUILTIN_MODELS, resolve_model
    from skelid.simulate import simulate as run
    from skelid.workflows import check_input_file

    for name, v in (("--sigma", sigma), ("--rate", rate), ("--sta-amplitude", sta_amplitude)):
        _finite(name, v)
    suffix = Path(out_path).suffix.lower()
    if Path(out_path).is_dir():
        raise SkelidError(f"--out {out_path} is a folder", "give the name of the file to write, e.g. data.trc")
    if suffix not in (".trc", ".csv"):
        raise SkelidError(f"--out {out_path}: unsupported output type {suffix or '(none)'!r}",
                          "end the file name with .trc or .csv")
    if str(model_name).lower().replace("_", "-") not in BUILTIN_MODELS:
        check_input_file(model_name, "model file")
    model = resolve_model(model_name)
    from skelid import resources

    resources.check(resources.simulate_cost(model, frames), _limits(max_memory, max_time),
                    f"simulating {frames} frames")
    trial = run(model, n_frames=frames, rate=rate, sigma=sigma, rng=np.random.default_rng(seed),
                hard_poses=hard_poses, noise=noise, sta_amplitude=sta_amplitude)
    (io.write_csv if suffix == ".csv" else io.write_trc)(out_path, trial.data)
    if as_json:
        _echo_json({"out": out_path, "frames": trial.data.n_frames, "markers": list(trial.data.names),
                    "units": model.units, "truth": trial.truth})
        return
    click.echo(f"wrote {trial.data.n_frames} frames of {trial.data.n_markers} markers to {out_path}")
    for name, value in trial.truth.items():
        click.echo(f"true {name} = {value:g} {model.units}")


@cli.command(epilog=EXAMPLES_EPILOG)
@click.argument("model_path")
@click.argument("data_paths", nargs=-1, required=True)
@click.option("--method", "method_names", multiple=True,
              help="Estimator (repeat for several): marker (default), paper, marker-grid, marker-smc.")
@click.option("--sigma", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Marker noise in model units (default 15 mm for the paper method).")
@click.option("--json", "as_json", is_flag=True, help="Print the result as JSON on stdout, nothing else.")
@click.option("--out", "out_dir", default=None,
              help="Folder for result.json, arrays.npz and figures (read by 'skelid report'); must be new, "
                   "or see --overwrite.")
@click.option("--cutoff", type=float, default=None,
              help="Motion model of the marker methods: poses are smoothed above this frequency "
                   "(Hz; default: chosen per pose coordinate from the motion, at least 6; 0 = none).")
@click.option("--artefact-rms", type=float, default=None,
              help="Soft-tissue artefact of the marker method: root-mean-square displacement of a marker "
                   "coordinate against its bone (model units); its effect on the estimate widens the "
                   "interval (default: none).")
@click.option("--placement-sd", type=float, default=None,
              help="Marker method: sd of each marker's placement on its segment (model units, per coordinate); "
                   "its effect on every parameter widens the interval, shared by all trials (default: 5 mm for "
                   "a static trial, none otherwise; 0: none). OpenSim models estimate each marker's offset "
                   "instead.")
@click.option("--noise", type=click.Choice(["pooled", "per-marker"]), default="pooled", show_default=True,
              help="Marker method: one noise level for all markers, or each marker its own (estimated, "
                   "used as weights).")
@click.option("--alternative", "alternatives", multiple=True,
              help="Another model of the same body (repeat for several; another .osim for an .osim model): the "
                   "data are refitted under each; the spread of the shared quantities and the models' average "
                   "(stacking weights over blocks of frames) are reported.")
@click.option("--seed", type=SEED, default=0, show_default=True)
@click.option("--quiet", is_flag=True, help="No progress bar, no table, no warnings: only errors (the warnings are "
              "kept in --out's result.json and in --json).")
@click.option("--scale", "scale_kind", type=click.Choice(["linked", "bodies", "axes", "none"]), default="linked",
              show_default=True, help="OpenSim models: three scale factors per body with markers that lean towards "
              "one common factor (linked: their logs correlated 0.8 a priori), one factor per body, three "
              "independent ones, or none.")
@click.option("--markers", "marker_kind", type=click.Choice(["offsets", "none"]), default="offsets",
              show_default=True, help="OpenSim models: fit an offset of every free marker, or none.")
@click.option("--marker-set", default=None, help="OpenSim models: a MarkerSet .xml file for a model without markers.")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out folder whole (its old contents "
              "are removed).")
@click.option("--ik", "with_ik", is_flag=True, help="OpenSim models: also every coordinate of every trial with its "
              "sd (as 'skelid ik' writes them), in --out/ik.")
@click.option("--ik-draws", type=click.IntRange(min=0), default=None, metavar="N",
              help="With --ik: draws of the geometry (default 100; 0: its first-order effect).")
@click.option("--scaletool", "scaletool_setup", default=None, metavar="SETUP.xml",
              help="OpenSim models: also run OpenSim's ScaleTool on this Scale setup (as written; needs the opensim "
                   "package) and put its factor of every body and axis beside skelid's interval.")
@_limit_options
@click.pass_context
def fit(ctx, model_path, data_paths, method_names, sigma, cutoff, artefact_rms, placement_sd, noise, alternatives,
        as_json, out_dir, seed, quiet, scale_kind, marker_kind, marker_set, overwrite, with_ik, ik_draws,
        scaletool_setup, max_memory, max_time):
    """Fit MODEL_PATH (a .toml or OpenSim .osim model, or case-a/case-b) to the markers in DATA_PATHS.

    Several files are trials of one body: one geometry is fitted to all of them, with each
    trial's own estimate and a consistency test beside it. With an .osim model, every trial
    (a static one and movements) informs one set of body scales and marker offsets, and --out
    receives the scaled .osim, its ScaleSet and scaling.json with the intervals.
    """
    from skelid import workflows
    from skelid.checks import check_distinct_files

    if quiet:
        _quiet_warnings(ctx)
    check_distinct_files(data_paths)
    if str(model_path).lower().endswith(".osim"):
        _check_osim_options(with_ik, ik_draws, out_dir, placement_sd)
        _fit_osim(ctx, model_path, data_paths, method_names, sigma, out_dir, seed, scale_kind, marker_kind,
                  marker_set, as_json, quiet, overwrite, cutoff=cutoff, artefact_rms=artefact_rms, noise=noise,
                  alternatives=alternatives, limits=(max_memory, max_time),
                  ik_draws=(N_DRAWS_DEFAULT if ik_draws is None else ik_draws) if with_ik else None,
                  scaletool_setup=scaletool_setup)
        return
    if with_ik or ik_draws is not None or scaletool_setup is not None:
        raise click.UsageError("--ik and --scaletool are for OpenSim models; fit an .osim model to use them")
    _finite("--sigma", sigma)
    _finite("--cutoff", cutoff)
    _finite("--artefact-rms", artefact_rms)
    _finite("--placement-sd", placement_sd)
    if len(data_paths) > 1 or alternatives or noise != "pooled":
        from skelid.sensitivity import run_fit_trials

        _check_trials_cost(model_path, data_paths, alternatives, method_names, _limits(max_memory, max_time))
        run = run_fit_trials(model_path, data_paths, method_names, sigma=sigma, seed=seed,
                                out_dir=out_dir, command=_command(ctx), cutoff=cutoff,
                                artefact_rms=artefact_rms, noise=noise.replace("-", "_"),
                                alternatives=alternatives, overwrite=overwrite, placement_sd=placement_sd)
    else:
        run = workflows.run_fit(model_path, data_paths[0], method_names, sigma=sigma, seed=seed,
                                   out_dir=out_dir, command=_command(ctx), progress=not quiet,
                                   cutoff=cutoff, artefact_rms=artefact_rms, limits=_limits(max_memory, max_time),
                                   overwrite=overwrite, placement_sd=placement_sd)
    from skelid.io.results import run_to_dict

    _echo_warnings((w.message for w in run.warnings), quiet, out_dir)
    if as_json:
        _echo_json(run_to_dict(run))
    elif not quiet:
        click.echo(workflows.table(run))
        if (len(data_paths) > 1 or alternatives) and "marker" in run.results:
            from skelid.sensitivity import average_text, trials_text

            for text in (trials_text(run.results["marker"]), average_text(run.results["marker"])):
                if text:
                    click.echo(text)
        if out_dir:
            click.echo(f"result.json, arrays.npz and figures written to {out_dir}; "
                       f"next: skelid report {out_dir}")


def _check_osim_options(with_ik, ik_draws, out_dir, placement_sd) -> None:
    """The options an ``.osim`` fit reads differently from a ``.toml`` one, refused in one line where unusable."""
    if ik_draws is not None and not with_ik:
        raise click.UsageError("--ik-draws is for --ik; add --ik or leave it out")
    if with_ik and out_dir is None:
        raise click.UsageError("--ik writes the angles into the --out folder; give --out DIR")
    if placement_sd is not None:
        raise click.UsageError("--placement-sd is for .toml models: an OpenSim fit estimates each marker's "
                               "offset on its body (its placement) with the geometry; leave it out")


def _check_trials_cost(model_path, data_paths, alternatives, method_names, limits) -> None:
    """Refuse a joint fit of several trials estimated, over all its trials and models, to exceed ``limits``
    (:func:`skelid.resources.trials_cost`), before any trial is read. Only for the marker method: another
    is refused by :func:`skelid.sensitivity.run_fit_trials`."""
    from skelid import resources, workflows
    from skelid.simulate import BUILTIN_MODELS, resolve_model

    if tuple(method_names) not in ((), ("marker",)):
        return

    models = []
    for p in (model_path, *alternatives):
        if str(p).lower().replace("_", "-") not in BUILTIN_MODELS:
            workflows.check_input_file(p, "model file")
        models.append(resolve_model(p))
    for p in data_paths:
        workflows.check_input_file(p, "data file")
    resources.check(resources.trials_cost(models, data_paths), limits,
                    f"the marker fit of {len(data_paths)} trial{'s' if len(data_paths) > 1 else ''}")


def _fit_osim(ctx, model_path, data_paths, method_names, sigma, out_dir, seed, scale_kind, marker_kind, marker_set,
              as_json, quiet, overwrite=False, cutoff=None, artefact_rms=None, noise="pooled", alternatives=(),
              limits=(None, None), ik_draws=None, scaletool_setup=None):
    """``skelid fit MODEL.osim TRIAL...``: scale factors and marker offsets, written back for OpenSim.

    Every option of ``fit`` reaches the fit (the estimator's options as for a ``.toml`` model) or is
    refused here in one line.
    """
    from skelid import scaling
    from skelid.io import read_markers
    from skelid.io.atomic import atomic_dir
    from skelid.io.legacy import run_from_scaling
    from skelid.io.results import write_run
    from skelid.scaletool import run_scaletool, scaletool_entry

    _check_osim_fit(model_path, data_paths, method_names, sigma, out_dir, marker_set, overwrite, cutoff,
                    artefact_rms, alternatives)
    limits = _limits(*limits)
    if ik_draws is not None:
        from skelid.angles import check_trial_names

        stems = check_trial_names(data_paths)
    # ScaleTool first: it takes a fraction of a second, and a setup it cannot run stops before the fit
    peer = None if scaletool_setup is None else run_scaletool(scaletool_setup)
    trials = [read_markers(p) for p in data_paths]
    options = dict(marker_set=marker_set, scale=scale_kind, markers=marker_kind,
                   method=method_names[0] if method_names else "marker", seed=seed, sigma=sigma, cutoff=cutoff,
                   artefact_rms=artefact_rms, noise=noise, limits=limits)
    fit_ = scaling.fit_osim(model_path, trials, **options)
    if alternatives:
        fit_ = scaling.with_alternatives(fit_, alternatives, trials, **options)
    table = scaling.scaling_table(fit_)
    if peer is not None:
        table["scaletool"] = scaletool_entry(table, peer)
        if Path(peer["generic_model"]).resolve() != Path(model_path).resolve():
            table["warnings"] = [*table["warnings"], (
                f"the ScaleTool setup scales {Path(peer['generic_model']).name}, not the model fitted "
                f"({Path(model_path).name}): their factors are compared body by body and axis by axis")]
    _echo_warnings(table["warnings"], quiet, out_dir)
    if out_dir is not None:
        with atomic_dir(out_dir, protect=[model_path, *data_paths, *alternatives], overwrite=overwrite) as tmp:
            paths = scaling.write_outputs(fit_, tmp, table=table)
            if ik_draws is not None:
                from skelid import angles

                ik = angles.run_ik(angles.fitted_geometry(fit_), dict(zip(stems, trials, strict=True)), ik_draws,
                                   seed)
                angles.write_ik(tmp / "ik", ik)
                table["ik"] = angles.ik_document(ik)
            write_run(tmp, run_from_scaling(fit_, table, _command(ctx)))
        table["written"] = {k: str(Path(out_dir) / v.name) for k, v in paths.items()}
    if as_json:
        _echo_json(table)
    elif not quiet:
        _echo_scaling(table, out_dir, ik_draws is not None)


def _check_osim_fit(model_path, data_paths, method_names, sigma, out_dir, marker_set, overwrite, cutoff,
                    artefact_rms, alternatives):
    """The options and files of an ``.osim`` fit checked before any work (one line each)."""
    from skelid import workflows
    from skelid.errors import SettingError
    from skelid.io.atomic import check_output_dir

    if len(method_names) > 1:
        raise click.UsageError("an .osim model is fitted with one method; give --method once")
    for p in alternatives:
        if not str(p).lower().endswith(".osim"):
            raise SettingError(f"--alternative {p}: an OpenSim model's alternative must be an .osim model (the "
                               "scale factors are compared by body)", "give another .osim model of the same body")
    for name, v in (("--sigma", sigma), ("--cutoff", cutoff), ("--artefact-rms", artefact_rms)):
        _finite(name, v)
    if out_dir is not None:
        check_output_dir(out_dir, overwrite=overwrite)
    workflows.check_input_file(model_path, "model file")
    if marker_set is not None:
        workflows.check_input_file(marker_set, "marker-set file")
    for p in [*alternatives, *data_paths]:
        workflows.check_input_file(p, "model file" if p in alternatives else "data file")


def _echo_scaling(table: dict, out_dir, ik: bool) -> None:
    """The scale factors with their intervals (ScaleTool's beside them where it ran), and what was written where."""
    peer = {(r["body"], r["axis"]): r for r in (table.get("scaletool") or {}).get("compared", [])}
    avg = ((table.get("model_sensitivity") or {}).get("average") or {})
    if avg:
        click.echo("the models' average beside each factor (stacking weights over "
                   f"{avg['blocks']} blocks of {avg['unit']}: "
                   + ", ".join(f"{m} {w:.2f}" for m, w in avg["weights"].items()) + ")")
    for body, s in table["scales"].items():
        for ax, e in s.items():
            lo, hi = e["ci95"]
            r = peer.get((body, ax))
            beside = "" if r is None else f"  ScaleTool {r['scaletool']:.4f}{'' if r['inside'] else ' (outside)'}"
            a = avg.get("quantities", {}).get(f"scale_{body}" if ax == "xyz" else f"scale_{body}_{ax}")
            if a:
                beside += f"  average {a['value']:.4f} [{a['interval'][0]:.4f}, {a['interval'][1]:.4f}]"
            click.echo(f"scale {body:<12} {ax:<3} {e['value']:.4f}  [{lo:.4f}, {hi:.4f}]{beside}")
    for q, a in avg.get("quantities", {}).items():
        if q.startswith("length "):
            click.echo(f"{q} (mm): average {a['value']:.1f}  [{a['interval'][0]:.1f}, {a['interval'][1]:.1f}]")
    click.echo(f"{len(table['marker_offsets_mm'])} marker offsets; {table['seconds']:.1f} s")
    if out_dir:
        click.echo(f"scaled model, ScaleSet, scaling.json and report written to {out_dir}")
    if ik:
        click.echo(f"joint angles and their sd written to {Path(out_dir) / 'ik'}")


@cli.command(epilog="Example:\n\n\b\n"
             "    skelid fit gait2354_simbody.osim static.trc walk.trc --out /tmp/fit\n"
             "    skelid ik /tmp/fit walk.trc --draws 100")
@click.argument("result_dir")
@click.argument("trial_paths", nargs=-1, required=True)
@click.option("--draws", type=click.IntRange(min=0), default=N_DRAWS_DEFAULT, show_default=True,
              help="Draws of the geometry from the fit's posterior, each trial's poses refitted for each "
                   "(0: the geometry's first-order effect only).")
@click.option("--out", "out_dir", default=None,
              help="Folder for the .mot files and ik.json (default RESULT_DIR/ik); must be new, or see --overwrite.")
@click.option("--covariance", type=click.Choice(["reported", "laplace"]), default="reported", show_default=True,
              help="The geometry's covariance as the fit reports it (widened by its checks for model misfit and "
                   "correlated residuals), or the joint fit's Laplace covariance before that widening.")
@click.option("--seed", type=SEED, default=0, show_default=True)
@click.option("--json", "as_json", is_flag=True, help="Print each trial's summary as JSON on stdout, nothing else.")
@click.option("--quiet", is_flag=True, help="No table: only warnings and errors.")
@click.option("--overwrite", is_flag=True, help="Replace an existing --out folder whole.")
def ik(result_dir, trial_paths, draws, covariance, out_dir, seed, as_json, quiet, overwrite):
    """Every OpenSim coordinate of each TRIAL on the model fitted in RESULT_DIR, with its sd.

    RESULT_DIR is the folder 'skelid fit MODEL.osim ... --out DIR' wrote. For each trial,
    TRIAL.mot holds the coordinates (degrees for rotational ones, as OpenSim writes them),
    TRIAL_sd.mot their sd (the geometry's posterior and the frame's marker noise together),
    and ik.json each coordinate's mean sd and the share of its variance from the geometry.
    """
    from skelid import angles, workflows
    from skelid.io import read_markers
    from skelid.io.atomic import atomic_dir, check_output_dir

    geom = angles.read_geometry(result_dir)
    geom = geom.laplace() if covariance == "laplace" else geom
    out_dir = str(Path(result_dir) / "ik") if out_dir is None else out_dir
    check_output_dir(out_dir, overwrite=overwrite)
    stems = angles.check_trial_names(trial_paths)
    for p in trial_paths:
        workflows.check_input_file(p, "data file")
    trials = dict(zip(stems, (read_markers(p) for p in trial_paths), strict=True))
    results = angles.run_ik(geom, trials, draws, seed)
    with atomic_dir(out_dir, protect=[*trial_paths], overwrite=overwrite) as tmp:
        angles.write_ik(tmp, results)
    doc = angles.ik_document(results)
    if as_json:
        _echo_json(doc)
        return
    if quiet:
        return
    for stem, s in doc.items():
        click.echo(f"{stem}: {s['frames_fixed']} of {s['frames']} frames, marker noise {s['sigma_mm']:.2f} mm, "
                   f"{s['draws']} draws of the geometry ({s['covariance']} covariance)")
        click.echo(f"  {'coordinate':<20} {'mean':>9} {'mean sd':>8} {'geometry share':>15}")
        for name, c in s["coordinates"].items():
            if c["status"] != "fitted":
                click.echo(f"  {name:<20} {c['mean']:>9.3f} {'-':>8} {c['status']:>15}")
                continue
            out = c["frames_outside_range"]
            click.echo(f"  {name:<20} {c['mean']:>9.3f} {c['mean_sd']:>8.3f} {c['geometry_share']:>15.2f}  "
                       f"{c['unit']}" + (f"  ({out} frames outside its range)" if out else ""))
    click.echo(f"angles (.mot), their sd (_sd.mot) and ik.json written to {out_dir}")


@cli.group("model")
def model_group():
    """Inspect and convert model files."""


@model_group.command("import", epilog="Example:\n\n\b\n"
                     "    skelid model import gait2354_simbody.osim --marker-set gait2354_Scale_MarkerSet.xml "
                     "--out gait2354.toml")
@click.argument("osim_path")
@click.option("--out", "out_path", required=True, help="The .toml model file to write.")
@click.option("--marker-set", default=None, help="A MarkerSet .xml file for a model without markers.")
@click.option("--scale", "scale_kind", type=click.Choice(["bodies", "axes", "none"]), default="none",
              show_default=True, help="Scale parameters to declare.")
@click.option("--markers", "marker_kind", type=click.Choice(["offsets", "none"]), default="none",
              show_default=True, help="Marker-offset parameters to declare.")
@click.option("--all-bodies", is_flag=True, help="Keep bodies without markers too.")
@_limit_options
def model_import(osim_path, out_path, marker_set, scale_kind, marker_kind, all_bodies, max_memory, max_time):
    """Convert an OpenSim .osim model (4.x or older) into a skelid .toml model."""
    import tomli_w

    from skelid import resources, workflows
    from skelid.io.atomic import atomic_write
    from skelid.io.osim import osim_parameters, read_osim

    workflows.check_input_file(osim_path, "model file")
    for p in (osim_path, *([marker_set] if marker_set else [])):
        resources.check(resources.read_cost(p), _limits(max_memory, max_time), f"reading {p}")
    model, info = read_osim(osim_path, marker_set, keep="all" if all_bodies else "markers")
    if info.marker_set_found_by:
        _echo_warnings([f"{Path(osim_path).name} has no markers: {info.marker_set_found_by}"])
    model = osim_parameters(model, info, scale_kind, marker_kind)
    head = (f"# imported from {Path(osim_path).name} by skelid model import: frames keep the OpenSim bodies'\n"
            "# orientation with their origin at the joint centre; lengths in mm\n")
    text = head + tomli_w.dumps(model.to_dict())
    with atomic_write(out_path) as fh:
        fh.write(text)
    click.echo(f"{out_path}: {len(model.segments)} segments, {model.n_pose} coordinates, "
               f"{len(model.markers)} markers, {model.n_params} parameters")


@cli.command(epilog="Example:\n\n\b\n"
             "    skelid batch examples/case_a.toml 'trials/*.trc' --out results.parquet --workers 4")
@click.argument("model_path")
@click.argument("pattern")
@click.option("--out", "out_path", required=True, help="Table to write: .parquet or .csv (rows already "
              "there are kept and their trials skipped).")
@click.option("--method", default="marker", show_default=True,
              help="Estimator: marker, paper, marker-grid, marker-smc.")
@click.option("--sigma", type=click.FloatRange(min=0.0, min_open=True), default=None,
              help="Marker noise in model units (default: estimated, or 15 mm for the paper method).")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Worker processes of the local Dask cluster (default: one per CPU).")
@click.option("--scheduler", default=None, help="Address of an existing Dask scheduler (tcp://host:8786).")
@click.option("--seed", type=SEED, default=0, show_default=True)
@click.option("--retry-failed", is_flag=True, help="Fit again the trials whose rows hold an error.")
@click.option("--results", "results_dir", default=None,
              help="Folder for each fitted trial's result folder (result.json and arrays.npz, as 'skelid fit "
                   "--out' writes them; read by 'skelid report').")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON on stdout.")
@click.option("--quiet", is_flag=True, help="No progress bar, no summary line.")
@_limit_options
@click.pass_context
def batch(ctx, model_path, pattern, out_path, method, sigma, workers, scheduler, seed, retry_failed, results_dir,
          as_json, quiet, max_memory, max_time):
    """Fit MODEL_PATH to every trial matching PATTERN on a Dask cluster; one row per trial in --out.

    With an OpenSim model, a trial that lacks some of its markers is fitted with the markers it has.
    """
    from skelid.batch import run_batch

    _finite("--sigma", sigma)
    summary = run_batch(model_path, pattern, out_path, method=method, sigma=sigma, seed=seed, workers=workers,
                        scheduler=scheduler, retry_failed=retry_failed, progress=not quiet,
                        limits=_limits(max_memory, max_time), results_dir=results_dir, command=_command(ctx))
    if as_json:
        _echo_json(summary)
    elif not quiet:
        click.echo(f"{summary['trials']} trials: {summary['fitted']} fitted, {summary['failed']} failed, "
                   f"{summary['skipped']} already in {summary['out']} ({summary['seconds']:g} s)")


@cli.command(epilog=EXAMPLES_EPILOG)
@click.argument("result_dir")
@click.option("--out", "out_path", default=None,
              help="HTML file to write. Default: RESULT_DIR/report.html.")
@click.option("--json", "as_json", is_flag=True, help="Print the report's path as JSON.")
@click.option("--quiet", is_flag=True, help="No progress bar, no message.")
def report(result_dir, out_path, as_json, quiet):
    """Write one self-contained HTML report of the fit in RESULT_DIR (from 'skelid fit --out')."""
    from skelid.report import write_report

    path, notes = write_report(result_dir, out_path, progress=not quiet)
    _echo_warnings(notes, quiet)
    if as_json:
        _echo_json({"report": str(path)})
    elif not quiet:
        click.echo(f"report written to {path}")


LIVE_EXAMPLE = """\b
    skelid simulate case-a --frames 600 --sigma 1 --out arm.trc
    skelid replay arm.trc --lsl arm --loop &
    skelid live examples/case_a.toml --lsl arm --udp 127.0.0.1:9870 --out live.jsonl"""


def _labels(text):
    return None if text is None else [t.strip() for t in text.split(",") if t.strip()]


def _target_sd(text):
    """``--target-sd``: ``0.5`` (every parameter) or ``L2=0.5,scale_femur_r=0.01``, as Session takes it."""
    if text is None:
        return None
    from skelid.errors import SettingError

    fix = "give --target-sd 0.5 (every parameter) or --target-sd NAME=SD,NAME=SD"
    parts = [t.strip() for t in text.split(",") if t.strip()]
    try:
        if len(parts) == 1 and "=" not in parts[0]:
            return float(parts[0])
        pairs = [t.split("=") for t in parts]
        if not pairs or any(len(pq) != 2 or not pq[0].strip() for pq in pairs):
            raise ValueError
        return {k.strip(): float(v) for k, v in pairs}
    except ValueError:
        raise SettingError(f"--target-sd {text!r} is not a number or NAME=SD pairs", fix) from None


def _live_kernels(model, quiet: bool) -> None:
    """Build the compiled kernels a live session of ``model`` runs before it starts (:func:`skelid.live.build_kernels`),
    saying so on a cold cache."""
    from skelid.live import build_kernels

    build_kernels(model, lambda: quiet or click.echo(
        "building skelid's compiled kernels once (a minute or two; later runs start at once)", err=True))


def _live_model(model_path, marker_set, names):
    """The model of a live run; an OpenSim model keeps only the markers the stream carries (``names``)."""
    from skelid.loading import load_model
    from skelid.simulate import BUILTIN_MODELS, builtin_model

    if str(model_path).lower().replace("_", "-") in BUILTIN_MODELS:
        return builtin_model(model_path)
    return load_model(model_path, marker_set, marker_names=names)


@cli.command(epilog=f"Example:\n\n{LIVE_EXAMPLE}")
@click.argument("model_path")
@click.option("--lsl", "stream", required=True, metavar="NAME", help="Name of the LSL marker stream to read.")
@click.option("--labels", default=None, metavar="A,B,...",
              help="The stream's marker names in channel order (default: from the stream's metadata).")
@click.option("--units", type=click.Choice(["mm", "cm", "m"]), default=None,
              help="The stream's length unit (default: from the stream's metadata).")
@click.option("--rate", type=float, default=None, help="Frames per second (default: the stream's nominal rate).")
@click.option("--sigma", type=click.FloatRange(min=0.0), default=None,
              help="Marker noise in model units (default: estimated); residuals beyond it are reported.")
@click.option("--method", type=click.Choice(["auto", "gaussian", "grid"]), default="auto", show_default=True)
@click.option("--out", "out_path", default=None,
              help="JSON Lines file: every estimate as one skelid.live/1 message (written when the run ends).")
@click.option("--udp", default=None, metavar="HOST:PORT", help="Send every estimate as a JSON datagram here.")
@click.option("--lsl-out", default=None, metavar="NAME", help="Publish every estimate as a JSON string on an "
              "LSL stream of this name (type skelid.live).")
@click.option("--max-frames", type=click.IntRange(min=1), default=None, help="Stop after this many frames.")
@click.option("--timeout", type=float, default=5.0, show_default=True,
              help="Seconds to wait for the stream, and for each frame.")
@click.option("--marker-set", default=None, help="OpenSim models: a MarkerSet .xml file for a model without markers.")
@click.option("--target-sd", default=None, metavar="SD|NAME=SD,...",
              help="Stopping rule: the sd each parameter (or each one named) should reach; the run ends when "
                   "every one has (each message's 'done').")
@click.option("--quiet", is_flag=True, help="No summary line at the end.")
def live(model_path, stream, labels, units, rate, sigma, method, out_path, udp, lsl_out, max_frames, timeout,
         marker_set, target_sd, quiet):
    """Refine MODEL_PATH's geometry from a live LSL marker stream, sending each estimate on.

    Every frame's estimate (parameters with intervals, joint centres, health, advice) goes to --udp,
    --lsl-out and --out as a skelid.live/1 JSON message (docs/live-protocol.md). The run ends after
    --max-frames, on Ctrl-C, when the stream stops sending (one line says so; what came is kept), or,
    with --target-sd, when every requested parameter has reached its target sd.
    """
    from skelid.errors import StreamError
    from skelid.io import atomic_write
    from skelid.io.atomic import check_target
    from skelid.io.stream import JsonLines, LslFrames, LslMessages, UdpMessages
    from skelid.live import Session, run, target_sds

    _finite("--rate", rate)
    _finite("--sigma", sigma)
    _finite("--timeout", timeout)
    targets = _target_sd(target_sd)
    # what can be refused without the stream is refused before any wait for it
    target_sds(_live_model(model_path, marker_set, None), targets)
    sinks = [UdpMessages(udp)] if udp else []
    if out_path:
        check_target(out_path)
    source = LslFrames(stream, labels=_labels(labels), units=units, timeout=timeout)
    model = _live_model(model_path, marker_set, source.labels)
    rate = rate if rate is not None else source.rate
    if rate is None:
        raise SkelidError(f"stream {stream!r} has no nominal rate", "give the frames per second with --rate")
    _live_kernels(model, quiet)
    session = Session(model, labels=source.labels, units=source.units, rate=rate, method=method, sigma=sigma,
                      target_sd=targets)
    if lsl_out:
        sinks.append(LslMessages(lsl_out))
    stopped, est = None, None
    with contextlib.ExitStack() as stack:
        if out_path:
            sinks.append(JsonLines(stack.enter_context(atomic_write(out_path))))
        try:
            est = run(session, source, sinks, max_frames=max_frames, until_done=targets is not None)
        except StreamError as exc:
            if source.n_frames == 0:
                raise
            stopped = exc
        except KeyboardInterrupt:
            pass  # Ctrl-C ends a live run; what came is kept
        est = session.finish()  # the line at the end: every frame folded in
    if not quiet and est is not None:
        params = ", ".join(f"{p.name} {p.mean:.4g} ± {p.sd:.2g}" + ("" if p.unit == "1" else f" {p.unit}")
                           for p in est.parameters.values())
        click.echo(f"{est.frame} frames; {params}; health: {est.health}"
                   + ("; done: every requested parameter reached its target sd" if est.done else "")
                   + (f"; messages written to {out_path}" if out_path else ""), err=True)
    if stopped is not None:
        raise stopped


@cli.command(epilog=f"Example:\n\n{LIVE_EXAMPLE}")
@click.argument("trial_path")
@click.option("--lsl", "stream", required=True, metavar="NAME", help="Name of the LSL marker stream to publish.")
@click.option("--rate", type=float, default=None, help="Frames per second (default: the file's).")
@click.option("--loop", is_flag=True, help="Start again after the last frame.")
@click.option("--max-frames", type=click.IntRange(min=1), default=None, help="Stop after this many frames.")
@click.option("--wait", type=click.FloatRange(min=0.0), default=30.0, show_default=True,
              help="Seconds to wait for a receiver before the first frame (0: start at once).")
@click.option("--quiet", is_flag=True, help="No line at the end.")
def replay(trial_path, stream, rate, loop, max_frames, wait, quiet):
    """Publish the markers of TRIAL_PATH (TRC, C3D, CSV, TSV) as an LSL marker stream at its own rate.

    The channels are x, y, z of each marker in turn, labelled NAME_X, NAME_Y, NAME_Z with the file's unit,
    as skelid live reads them.
    """
    from skelid.io import read_markers
    from skelid.io.stream import publish

    _finite("--rate", rate)
    _finite("--wait", wait)
    data = read_markers(trial_path)
    try:
        sent = publish(data, stream, rate=rate, loop=loop, max_frames=max_frames, wait=wait)
    except KeyboardInterrupt:
        return
    if not quiet:
        click.echo(f"{sent} frames of {trial_path} sent on LSL stream {stream!r}", err=True)


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


#: the line a stop by a signal leaves on stderr, and the exit status
STOPPED = {signal.SIGINT: ("skelid: interrupted; no partial output was left", 130),
           signal.SIGTERM: ("skelid: terminated (SIGTERM); no partial output was left", 143)}


def _stopped(request) -> int:
    """One line for a stop request (:mod:`skelid._stop`) on stderr; its exit status."""
    if request in STOPPED:
        line, code = STOPPED[request]
        click.echo(line, err=True)
        return code
    click.echo(f"skelid: error: {request.one_line()}", err=True)
    return 2


def main(argv=None) -> int:
    """Entry point: run the CLI, turning user errors into one line and exit status 2.

    Without ``argv`` (the ``skelid`` program itself, whose process ends with it), SIGINT and SIGTERM
    are ignored once the command is over, while the interpreter shuts down (:func:`skelid._stop.handling`),
    freed memory is kept for reuse (:func:`skelid.resources.keep_freed_memory`), and a command stopped by
    a signal or its time limit ends the process at once, with its line and status, without the
    interpreter's shutdown.
    """
    args = list(sys.argv[1:] if argv is None else argv)
    if argv is None:  # the process ends with the command: freed arrays may stay for the next ones
        from skelid.resources import keep_freed_memory

        keep_freed_memory()
    with _stop.handling(process_ends=argv is None):
        code = _main(args)
        request = _stop.pending()  # also one that a library dropped on its way (see skelid._stop)
        if request is None:
            return code
        code = _stopped(request)
    if argv is None:
        # stopped part-way, the program ends here: its outputs are already removed, and the interpreter's
        # shutdown is skipped (an extension interrupted mid-call can abort it: "Fatal Python error")
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def _main(args) -> int:
    try:
        with one_blas_thread():
            cli.main(args=args, prog_name="skelid", standalone_mode=False, obj={"argv": ["skelid", *args]})
    except SkelidError as exc:
        click.echo(f"skelid: error: {exc.one_line()}", err=True)
        return 2
    except (click.exceptions.Abort, KeyboardInterrupt, SystemExit, _stop.DeadlineExceeded) as exc:
        if _stop.pending() is not None:
            return -1  # reported by main
        if isinstance(exc, SystemExit):
            raise
        return _stopped(signal.SIGINT)
    except click.UsageError as exc:
        where = exc.ctx.command_path if exc.ctx is not None else "skelid"
        click.echo(f"skelid: error: {_one_line(exc.format_message())} (fix: see '{where} --help')", err=True)
        return 2
    except click.ClickException as exc:
        click.echo(f"skelid: error: {_one_line(exc.format_message())}", err=True)
        return 2
    except click.exceptions.Exit as exc:
        return exc.exit_code
    except Exception:
        if _stop.pending() is not None:  # the stop's exception, turned into another on its way (numba's
            return -1  # compiled code reports it as a SystemError): reported by main as the stop it is
        traceback.print_exc()
        click.echo("skelid: internal error: the traceback above is a bug in skelid, not a problem with "
                   "your input; please report it with the command you ran", err=True)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
