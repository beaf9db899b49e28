"""`recoil-jax calibrate`: fit the model to measured firing traces, from a calibration
file (TOML) or one trace with `--fit`; the report, `result.json` and the figures."""

from __future__ import annotations

import dataclasses
import math
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np

import recoil_jax as rj
import recoil_jax.extend as rjx

from .._files.calibration_file import (
    MAX_SIGNAL,
    MAX_STARTS,
    check_experiments,
    load_calibration,
)
from .._files.describe import structure_line
from .._files.inputs import (
    check_not_input,
    design_warnings,
    output_folder,
    parse_assignments,
    results_folder,
    values_taken,
    warn,
)
from .._files.json_writer import dumps, write as write_json
from .._files.options import Commands, add_json, add_max_steps, add_store

__all__ = [
    "LOCAL_MINIMUM",
    "MODEL_MISFIT",
    "NOT_CONVERGED",
    "POSTERIOR_NOT_CONVERGED",
    "add_command",
    "posterior_report",
    "prediction_report",
    "run_calibrate",
    "run_calibration",
]

#: The exit status when the fit did not converge (0 fitted, 1 a solve failed, 2 bad
#: input).
NOT_CONVERGED = 4
#: The exit status when the fit converged but the model does not explain the traces:
#: residuals far above the traces' own noise, or far from white (`rjx.ModelCheck`).
MODEL_MISFIT = 5
#: The exit status when the model check failed at a best point only one start reached:
#: the fit may be stuck in a local minimum, not the model wrong (`result.verdict`).
LOCAL_MINIMUM = 6
#: The exit status when the posterior was sampled but its sampler did not converge
#: (split R-hat over 1.01, a bulk ESS under 400, or a divergent transition).
POSTERIOR_NOT_CONVERGED = 7
#: The starts `calibrate` suggests when its fit may be stuck.
SUGGESTED_STARTS = 16


def _quick(trace_path, fit_names: str | None, assignments, validate, force_table) -> rj.Calibration:
    """One trace with `--fit a,b,c` (bounds: each parameter's documented range), and the
    force table it fired (`--force-table`), if any."""
    if not fit_names:
        raise rj.ParameterError(
            f"calibrate {trace_path}: name the parameters to fit with --fit k,c_out,..."
        )
    fit = {}
    for name in (n.strip() for n in fit_names.split(",")):
        if name == "t_shift":
            fit[name] = rjx.T_SHIFT.documented
        elif name in rj.PARAMETERS and rj.PARAMETERS[name].documented is not None:
            fit[name] = rj.PARAMETERS[name].documented
        else:
            raise rj.PARAMETERS.unknown(name, also=("t_shift",))
    design = parse_assignments(assignments)
    known = {k: v for k, v in design.items() if k not in ("t_shift", "t1")}
    rj.params_from_values(known)  # checked as simulate checks it (m = 0: no absorber)
    experiment = rjx.Experiment(rj.read_trace(trace_path), design=design)
    validation = [rjx.Experiment(rj.read_trace(v), design=design) for v in validate]
    table = rj.ForceTable.from_csv(force_table) if force_table else None
    return rj.Calibration([experiment], fit=fit, validation=validation, force_table=table)


def _check_fit_names(fit_names: str | None, assignments) -> None:
    """`--fit a,b`: each name once, and none also given as a known value (`name=value`)."""
    names = [n.strip() for n in (fit_names or "").split(",")]
    twice = sorted({n for n in names if n and names.count(n) > 1})
    if twice:
        raise rj.ParameterError(f"--fit {fit_names}: {twice[0]} is given twice")
    for item in assignments:
        name = item.partition("=")[0]
        if name in names:
            raise rj.ParameterError(
                f"{name} is given both on the command line ({item}) and in --fit "
                f"{fit_names}: give it in one place"
            )


def _check_before_fit(calibration: rj.Calibration, starts, store) -> None:
    """What the fit cannot use or would not survive, refused (or warned of) before it
    starts: a signal with no variation or out of range, times that are probably not
    seconds from the firing, and starts whose arrays would not fit in memory."""
    experiments = [*calibration.experiments, *calibration.validation]
    fitted_ids = {id(e) for e in calibration.experiments}
    low, high = rjx.T1_LIMITS.documented or (0.1, 60.0)
    for e in experiments:
        t = e.trace.t
        if t[0] > high:
            warn([f"{e.trace.source} starts at t = {t[0]:g} s: are its times epoch seconds? "
                  "The model's t = 0 is the firing: give times from it (the documented "
                  f"range of t1 is {low:g} to {high:g} s)"])  # fmt: skip
        elif t[-1] - t[0] > high:
            warn([f"{e.trace.source} spans {t[0]:g} to {t[-1]:g} s, outside the documented "
                  f"range of t1 {low:g} to {high:g} s, where the model's accuracy is tested: "
                  "are its times in seconds (not milliseconds)?"])  # fmt: skip
        for name, values in e.trace.signals.items():
            present = values[np.isfinite(values)]
            if not present.size:
                continue
            largest = float(np.max(np.abs(present)))
            if largest > MAX_SIGNAL:
                raise rj.ParameterError(
                    f"{e.trace.source}, column {name}: a value of {largest:.3g} is beyond "
                    f"{MAX_SIGNAL:g}, where its square overflows: check the column's unit"
                )
            if id(e) in fitted_ids and name not in e.sigma and np.ptp(present) == 0:
                raise rj.ParameterError(
                    f"{e.trace.source}, column {name}: every sample is {present[0]:g}; a "
                    "signal with no variation cannot be fitted (its noise would be "
                    "estimated as zero): leave the column out, or give its sigma"
                )
    samples = sum(len(e.trace.t) * len(e.trace.signals) for e in calibration.experiments)
    count = starts if isinstance(starts, int) else len(starts)
    fitted = len(calibration.fit) + sum(
        len(e.per_experiment) for e in calibration.experiments
    )  # fmt: skip
    # Per start, one program holds the residuals, their Jacobian, its workspace and the
    # solves' saved states: measured, 1.0 GB above the rest for 1.88 M samples, 2 starts
    # and 2 fitted values (about 270 bytes a sample and start; this says 320).
    rjx.check_memory(
        min(count, 8) if store else count, 8 * samples * (4 * fitted + 32), "a calibration",
        "give fewer starts or shorter traces, or --store FILE.sqlite (its starts are "
        "fitted 8 at a time)", unit="starts at once",
    )  # fmt: skip


def run_calibration(args) -> int:
    """The `calibrate` command: checked, fitted, written, reported; its exit status."""
    source = Path(args.source)
    calibration, settings = _read_calibration(args, source)
    starts = args.starts if args.starts is not None else settings["starts"]
    _check_before_fit(calibration, starts, args.store)
    sampling = _posterior_settings(args, calibration, settings["posterior"])
    if args.predict is not None:
        _check_prediction(calibration, parse_assignments(args.predict))
    warn(design_warnings(values_taken(
        calibration.design, calibration.fit, calibration.start,
        *(e.design for e in [*calibration.experiments, *calibration.validation]),
    )))  # fmt: skip
    out = output_folder(args.out)
    traces = [e.trace.source for e in (*calibration.experiments, *calibration.validation)]
    check_not_input(out, ("result.json",), source, *traces)
    calibration = dataclasses.replace(
        calibration, options=dataclasses.replace(calibration.options, max_steps=args.max_steps)
    )
    result = rj.calibrate(
        calibration, starts=starts, seed=settings["seed"], max_steps=settings["fit_steps"],
        profiles=args.profile, progress=True, store=args.store,
    )  # fmt: skip
    report = {"source": str(source), "description": settings["description"], **result.to_json()}
    write_json(out / "result.json", report)
    from .._figures.calibration import calibration_figures, plot_prediction

    report["figures"] = [str(p) for p in calibration_figures(result, out)]
    if args.predict is not None and result.explains:
        prediction = rj.predict(
            result.hardware(), parse_assignments(args.predict), seed=settings["seed"],
            progress=True,
        )  # fmt: skip
        report["prediction"] = prediction.to_json()
        report["figures"].append(str(plot_prediction(prediction, out / "prediction.png")))
    write_json(out / "result.json", report)
    status = _exit_status(result, args.predict is not None)
    posterior = None
    if sampling is not None and status == 0:
        posterior = _sample_posterior(calibration, result, sampling, args.predict, report, out)
        write_json(out / "result.json", report)
    elif sampling is not None:
        print("recoil-jax: the posterior was not sampled: the fit above must converge and its "
              "model explain the traces first", file=sys.stderr)  # fmt: skip
    if args.json:
        print(dumps(report))
    else:
        print(fit_report(result))
        if "prediction" in report:
            print(prediction_report(report["prediction"]))
        if posterior is not None:
            print(posterior_report(posterior, report["posterior"]["predictive"]))
        if "posterior_prediction" in report:
            print(prediction_report(report["posterior_prediction"], "the posterior's draws"))
    if posterior is not None and not posterior.converged:
        for problem in posterior.problems:
            print(f"recoil-jax: the sampler has not converged: {problem}", file=sys.stderr)
        return POSTERIOR_NOT_CONVERGED
    return status


def _sample_posterior(calibration, result, sampling: dict, predict, report: dict, out: Path):
    """The posterior sampled, written (`posterior.nc`, `posterior.png`,
    `posterior_predictive.png`) and reported (`report["posterior"]`), and with
    `--predict`, the design predicted from its draws (`report["posterior_prediction"]`,
    `posterior_prediction.png`)."""
    from .._figures.calibration import plot_posterior, plot_posterior_predictive, plot_prediction

    with warnings.catch_warnings():  # the priors were checked, and warned of, before the fit
        warnings.simplefilter("ignore")
        posterior = rj.sample_posterior(calibration, fit=result, progress=True, **sampling)
    posterior.to_netcdf(out / "posterior.nc")
    predictive = posterior.predictive(seed=sampling.get("seed", 0))
    report["posterior"] = posterior.to_json() | {"predictive": predictive.to_json()}
    report["figures"] += [
        str(plot_posterior(posterior, out / "posterior.png")),
        str(plot_posterior_predictive(predictive, out / "posterior_predictive.png")),
    ]
    if predict is not None:
        draws = posterior.draws.shape[0] * posterior.draws.shape[1]
        prediction = rj.predict(
            posterior.hardware(), parse_assignments(predict), samples=max(draws, 2),
            seed=sampling.get("seed", 0), progress=True,
        )  # fmt: skip
        report["posterior_prediction"] = prediction.to_json()
        report["figures"].append(str(plot_prediction(
            prediction, out / "posterior_prediction.png", "the posterior's draws"
        )))  # fmt: skip
    return posterior


def _posterior_settings(args, calibration: rj.Calibration, table: dict) -> dict | None:
    """`sample_posterior`'s settings: the file's `[posterior]` with `--draws`,
    `--warmup`, `--chains`, `--parallel-chains` and each `--prior` over it, checked
    before the fit; None without `--posterior`."""
    given = {k: getattr(args, k) for k in ("draws", "warmup", "chains", "parallel_chains",
                                           "prior") if getattr(args, k) is not None}  # fmt: skip
    if args.sample_noise:
        given["sample_noise"] = True
    if not args.posterior:
        if given:
            flag = next(iter(given)).replace("_", "-")
            raise rj.ParameterError(f"--{flag} is for --posterior")
        return None
    settings = table | given
    if "prior" in given:
        settings["priors"] = dict(table.get("priors", {})) | _priors_given(given["prior"])
        del settings["prior"]
    rjx.check_posterior_settings(calibration, **settings)
    return settings


def _priors_given(items: list[str]) -> dict[str, rjx.Prior]:
    """`--prior NAME=KIND` or `NAME=KIND:MEAN,SD` (repeatable) as priors by name."""
    priors = {}
    for item in items:
        name, equals, spec = item.partition("=")
        name = name.strip()
        kind, _, numbers = spec.partition(":")
        words = f"--prior {item}: give NAME=uniform, NAME=normal:MEAN,SD or NAME=lognormal:MEAN,SD"
        if not equals or not name or name in priors:
            raise rj.ParameterError(words if name not in priors else f"--prior {name} given twice")
        try:
            values = [float(x) for x in numbers.split(",")] if numbers else []
        except ValueError:
            raise rj.ParameterError(words) from None
        if len(values) not in (0, 2):
            raise rj.ParameterError(words)
        mean, sd = values or (None, None)
        try:
            priors[name] = rjx.Prior(kind.strip(), mean, sd)
        except rj.ParameterError as error:
            raise rj.ParameterError(f"--prior {item}: {error}") from None
    return priors


def posterior_report(posterior: rjx.Posterior, predictive: dict | None = None) -> str:
    """The posterior's summary: per value its mean, sd, 2.5/50/97.5 % quantiles, R-hat
    and bulk ESS beside the fit's Laplace interval; then the gates, and the share of
    each trace inside its predictive band (`PosteriorPredictive.to_json`)."""
    chains, draws = posterior.draws.shape[:2]
    lines = [
        f"posterior: {chains} chains × {draws} draws (NUTS), {posterior.divergences} "
        f"divergent, {posterior.ess_per_second:.0f} ESS/s",
        f"  {'value':<16} {'mean':>12} {'sd':>10} {'2.5%':>12} {'50%':>12} {'97.5%':>12} "
        f"{'R-hat':>6} {'ESS':>6}  Laplace 95 %",
    ]
    for label, row in posterior.summary.items():
        laplace = ("none" if row["ci95"] is None
                   else f"[{row['ci95'][0]:.6g}, {row['ci95'][1]:.6g}]")  # fmt: skip
        r_hat = "" if row["r_hat"] is None else f"{row['r_hat']:.3f}"
        lines.append(
            f"  {label:<16} {row['mean']:>12.6g} {row['sd']:>10.4g} {row['q2.5']:>12.6g} "
            f"{row['q50']:>12.6g} {row['q97.5']:>12.6g} {r_hat:>6} {row['ess_bulk']:>6.0f}  "
            f"{laplace}{'  (differs)' if row['disagree'] else ''}"
        )
    noise = [f"{name} {n['sigma']:.3g} ({'given' if n['given'] else 'estimated by the fit'})"
             for experiment in posterior.noise for name, n in experiment.items()]  # fmt: skip
    sampled = [(e, name, n["sampled"]) for e, experiment in enumerate(posterior.noise)
               for name, n in experiment.items() if "sampled" in n]  # fmt: skip
    if not sampled:
        lines.append(f"  the likelihood's noise, held fixed: {', '.join(noise)}")
    else:
        lines.append(f"  the noise, sampled from the fit's: {', '.join(noise)}")
        for e, name, row in sampled:
            r_hat = "" if row["r_hat"] is None else f"{row['r_hat']:.3f}"
            label = f"σ {name} ({e})"
            lines.append(
                f"  {label:<16} {row['mean']:>12.6g} {row['sd']:>10.4g} {row['q2.5']:>12.6g} "
                f"{row['q50']:>12.6g} {row['q97.5']:>12.6g} {r_hat:>6} {row['ess_bulk']:>6.0f}  "
                f"half-normal prior, scale {row['half_normal_scale']:.3g}"
            )
    if posterior.left_out:
        lines.append(f"  {posterior.left_out} samples on or either side of a jump in the "
                     "model's signals left out of the likelihood")  # fmt: skip
    if predictive is not None:
        inside = [f"{name} {share:.1%}" for experiment in predictive["coverage"]
                  for name, share in experiment.items()]  # fmt: skip
        lines.append(f"  measured samples inside the 95 % predictive band "
                     f"({predictive['draws']} draws): {', '.join(inside)}")  # fmt: skip
    lines += [f"  {line}" for line in (*posterior.unseparated, *posterior.disagreements)]
    lines.append("  converged" if posterior.converged else "  NOT converged: see below")
    return "\n".join(lines)


def _check_prediction(calibration: rj.Calibration, given: dict[str, Any]) -> None:
    """`--predict`'s design, checked before the fit as the whole design it will be (the
    calibration's, the shared fitted values at the fit's start, the given values): a value
    out of range, a design that cannot be, or a shared fitted value given."""
    start = calibration.shared_start()
    for name, value in given.items():
        if name in start:
            raise rj.ParameterError(
                f"--predict {name}={value}: {name} is fitted, its value comes from the "
                "calibration; leave it out"
            )
    try:
        known = {k: v for k, v in calibration.design.items() if k in rj.PARAMETERS}
        rj.params_from_values(known | start | given)
    except rj.ParameterError as error:
        raise rj.ParameterError(f"--predict: {error}") from None


def _read_calibration(args, source: Path) -> tuple[rj.Calibration, dict[str, Any]]:
    """The calibration `args` ask for (a file, or the quick form on one trace) and its
    settings. Every check of the command line before any file is read."""
    if args.predict is not None:
        try:  # its names and numbers, not after the whole fit
            parse_assignments(args.predict)
        except rj.ParameterError as error:
            raise rj.ParameterError(f"--predict: {error}") from None
    if args.starts is not None and not 1 <= args.starts <= MAX_STARTS:
        raise rj.ParameterError(f"--starts {args.starts}: give an integer from 1 to {MAX_STARTS:,}")
    check_experiments(1 + len(args.validate or []), "the command line")
    if source.suffix.lower() != ".toml":
        _check_fit_names(args.fit, args.assignments)
        calibration = _quick(
            source, args.fit, args.assignments, args.validate or [], args.force_table
        )
        return calibration, {"starts": rjx.DEFAULT_STARTS, "seed": 0, "fit_steps": 200,
                             "description": "", "posterior": {}}  # fmt: skip
    if args.fit:
        raise rj.ParameterError("--fit is for a trace (.csv); a calibration file has [fit]")
    if args.assignments:
        item = args.assignments[0]
        raise rj.ParameterError(
            f"{item} is given on the command line beside the calibration file {source}: "
            "give it in one place (its [design], or an experiment's table)"
        )
    calibration, settings = load_calibration(source)
    if args.force_table:
        raise rj.ParameterError(
            "--force-table is for a trace (.csv); a calibration file has force_table"
        )
    if args.validate:
        extra = [rjx.Experiment(rj.read_trace(v), design={}) for v in args.validate]
        calibration = dataclasses.replace(calibration, validation=(*calibration.validation, *extra))
    return calibration, settings


def _exit_status(result: rj.CalibrationResult, predicted: bool) -> int:
    """The warnings of a fit (values on their bounds), and its exit status: 1 a failed
    solve, `NOT_CONVERGED`, `MODEL_MISFIT`, else 0; each said on stderr."""
    for name, f in result.fitted.items():
        if f.at_bound is not None and result.explains:
            print(f"recoil-jax: warning: {name} = {f.value:.6g} ended on its {f.at_bound} "
                  "bound: the data may want it beyond, so it has no confidence interval; "
                  "widen its bounds if the hardware allows", file=sys.stderr)  # fmt: skip
    if not result.solved:
        print("recoil-jax: solver failed at the fitted values", file=sys.stderr)
        return 1
    if not result.converged:
        print(
            "recoil-jax: the fit did not converge; the best point reached is in result.json "
            "(try starts = 16 or tighter bounds)",
            file=sys.stderr,
        )
        return NOT_CONVERGED
    if not result.explains:
        failing = ", ".join(dict.fromkeys(c.signal for c in result.check.failing))
        said = "; no prediction was made" if predicted else ""
        bounds = [f"{n} = {f.value:.6g} ended on its {f.at_bound} bound"
                  for n, f in result.fitted.items() if f.at_bound is not None]  # fmt: skip
        if bounds:  # the other way a fit fails to explain: bounds that leave out the truth
            said += (f"; {', '.join(bounds)} (bounds that leave out the true values "
                     "do this too)")  # fmt: skip
        if result.verdict == "local_minimum":
            print(f"recoil-jax: {_stuck_line(result)}{said}", file=sys.stderr)
            return LOCAL_MINIMUM
        print(f"recoil-jax: the model does not explain the traces ({failing}) at the best "
              f"point, reached from {result.starts_at_best} of {result.starts} starts: its "
              "values are the best a wrong model gives, and have no intervals; check what "
              f"the design says of the test: {WRONG_MODEL_SUSPECTS}{said}",
              file=sys.stderr)  # fmt: skip
        return MODEL_MISFIT
    return 0


#: Every part of the model a wrong design can get wrong, named when the model does not
#: explain the traces.
WRONG_MODEL_SUSPECTS = (
    "an absorber or none (m, gap, k), the load (v0, a pulse or a force table, the rounds), "
    "the trigger delay t_shift, the elevation, the rails' friction (friction_force, "
    "friction_coefficient), the recuperator (its preload, length and index), the battery "
    "stop and the counter-recoil buffer (their stiffness, length and damping)"
)


def _stuck_line(result: rj.CalibrationResult) -> str:
    """What to say, and to try, when the fit's best point was reached from one start."""
    others = result.starts - result.starts_at_best
    fits = (f"fits ({result.starts // 2} starts through both continuation paths)"
            if result.fallback else "starts")  # fmt: skip
    reached = (f"reached from 1 of {result.starts} {fits}, the other{'s' if others > 1 else ''} "
               "ending elsewhere" if result.starts > 1 else "from the one start run")  # fmt: skip
    pace = result.seconds / max(result.starts, 1)
    stages = result.continuation
    widths = ", ".join(f"{n} {v[0]:g} to the calibration's" for n, v in stages.items())
    count = len(next(iter(stages.values()), [])) + 1
    ran = f"; each start ran {count} stages of continuation ({widths})" if stages else ""
    return (
        f"the fit may be in a local minimum: its best point, where the model check "
        f"fails, was {reached}{ran}. A stuck fit and a wrong model look alike until "
        f"more starts reach the same point: try --starts {SUGGESTED_STARTS} (about "
        f"{pace * SUGGESTED_STARTS:.0f} s at this fit's pace of {pace:.0f} s a start) "
        "or tighter bounds around what you know"
    )


def _check_line(check: rjx.ModelCheck) -> str:
    """The model check's verdict, with each signal's residual RMS beside its noise."""
    several = len({c.experiment for c in check.signals}) > 1
    noises = "; ".join(
        f"{c.signal}{' in ' + c.experiment if several else ''} rms "
        f"{c.rms:.3g} against noise {c.noise:.3g}{' (given)' if c.noise_given else ''}"
        for c in check.signals
    )
    verdict = "explains the traces" if check.explains else "does NOT explain the traces"
    return f"  model check: the model {verdict} ({noises})"


def prediction_report(prediction: dict, source: str = "the fit's normal") -> str:
    """The prediction's bands as text, for the design it names, sampled from `source`."""
    given = ", ".join(f"{k}={v:g}" for k, v in prediction["given"].items())
    lines = [
        f"prediction for {given or 'the design of the calibration'} "
        f"({prediction['count']} samples of {source}, {prediction['failed']} failed, "
        f"{prediction['clipped']} moved to the bounds, {prediction['seconds']:.1f} s):"
    ]
    for name, sampled in prediction["sampled"].items():
        linear = prediction["linear"][name]
        unit = rj.METRICS[name].unit
        lines.append(
            f"  {name:22s} {prediction['nominal'][name]:.6g} {unit}, 95% sampled "
            f"[{sampled['ci95'][0]:.6g}, {sampled['ci95'][1]:.6g}], linear "
            f"[{linear['ci95'][0]:.6g}, {linear['ci95'][1]:.6g}]"
        )
    return "\n".join(lines)


def fit_report(result: rj.CalibrationResult) -> str:
    """The fit as text, in the style of lmfit's report."""
    lines = [
        f"fit: {'converged' if result.converged else 'NOT converged'} in {result.steps} steps "
        f"({result.starts_at_best} of {result.starts} starts reached the best), "
        f"{result.seconds:.1f} s",
        f"  samples {result.samples}, dof {result.dof}, chi2 {result.chi2:.6g}, "
        f"reduced chi2 {result.reduced_chi2:.4g}, AIC {result.aic:.6g}, BIC {result.bic:.6g}",
        "  rms: " + ", ".join(f"{k} {v:.4g}" for k, v in result.rms.items()),
        f"  model fitted: {structure_line(result.structure)}",
    ]
    if result.defaults:
        lines.append("  defaults taken (not given, not fitted): " + ", ".join(
            f"{k} {v:g} {rj.PARAMETERS[k].unit}".rstrip() for k, v in result.defaults.items()
        ))  # fmt: skip
    if result.check.tested:
        lines.append(_check_line(result.check))
        lines.extend(f"    {c.reason()}" for c in result.check.failing)
    else:
        lines.append("  model check: not run (no signal has the 20 samples a test needs)")
    for experiment in result.experiments:  # empty or NaN samples, left out of the fit
        skipped = {k: n for k, n in experiment["skipped"].items() if n}
        if skipped:
            counts = ", ".join(f"{n} of {k}" for k, n in skipped.items())
            lines.append(f"  skipped (empty or NaN) in {experiment['name']}: {counts}")
    withheld = " (no intervals: the model does not explain the traces)"
    lines.append("  fitted:" + (withheld if not result.explains else ""))
    for name, f in result.fitted.items():
        if f.withheld:
            line = f"    {name:12s} {f.value:.6g}"
            if f.at_bound is not None:
                line += f"  (on its {f.at_bound} bound)"
        elif f.at_bound is not None:
            line = f"    {name:12s} {f.value:.6g}  (on its {f.at_bound} bound"
            if f.identifiable and f.stderr is not None:
                line += f"; the curvature there +/- {f.stderr:.3g}"
            line += ")" if f.identifiable else "; not determined by the data)"
        elif f.identifiable and f.ci95 is not None and f.stderr is not None:
            relative = abs(f.stderr / f.value) if f.value else math.inf
            line = (
                f"    {name:12s} {f.value:.6g} +/- {f.stderr:.3g} ({relative:.2%}), "
                f"95% [{f.ci95[0]:.6g}, {f.ci95[1]:.6g}]"
            )
        else:
            line = f"    {name:12s} {f.value:.6g}  (not determined by the data)"
        if f.profile_ci95 is not None:
            low, high = (f"{x:.6g}" if x is not None else "bound" for x in f.profile_ci95)
            line += f"; profile 95% [{low}, {high}]"
        lines.append(line)
    for text in result.unidentifiable:
        lines.append(f"  not identifiable: {text}")
    if result.unresolved:
        where = ", ".join(f"{u['signal']} at {u['t']:.6g} s of {u['experiment']}"
                          for u in result.unresolved[:3])  # fmt: skip
        more = len(result.unresolved) - 3
        lines.append(
            f"  left out of the standard errors ({len(result.unresolved)} samples on an event "
            f"the sampling does not resolve): {where}" + (f" and {more} more" if more > 0 else "")
        )
    names = [n for n, f in result.fitted.items() if f.identifiable]
    pairs = [
        (a, b, result.correlation[i, j])
        for i, a in enumerate(result.fitted)
        for j, b in enumerate(result.fitted)
        if i < j and a in names and b in names and abs(result.correlation[i, j]) >= 0.5
    ]
    if pairs and result.explains:
        lines.append(
            "  correlations >= 0.5: " + ", ".join(f"{a}~{b} {c:+.3f}" for a, b, c in pairs)
        )
    for v in result.validation:
        lines.append(
            f"  validation {v['name']}: reduced chi2 {v['reduced_chi2']:.4g}, rms "
            + ", ".join(f"{k} {x:.4g}" for k, x in v["rms"].items())
        )
        if not v["model_check"]["explains"]:
            lines.append("    the fitted model does not explain this trace:")
            lines.extend(f"      {reason}" for reason in v["model_check"]["failing"])
    return "\n".join(lines)


def run_calibrate(args) -> int:
    """Run `recoil-jax calibrate` with the parsed `args`; its exit status."""
    from .calibrate import run_calibration

    args.out = results_folder(args.out, "calibrate", args.source)
    return run_calibration(args)


def add_command(commands: Commands) -> None:
    """`recoil-jax calibrate`'s arguments."""
    calibrate = commands.add(
        "calibrate",
        run_calibrate,
        help="fit the model to measured firing traces",
        description="Fit parameters to measured traces: a calibration file (TOML: "
        "[design], [fit], [[experiment]]), or one trace (CSV: t and signal columns) with "
        "--fit. Writes result.json (values, standard errors, 95% intervals, "
        "correlation, identifiability, chi2, AIC, BIC), fit.png and correlation.png. "
        "Exit 0 fitted, 1 a solve failed, 2 bad input, 4 the fit did not converge, 5 the "
        "model does not explain the traces (residuals far above the traces' own noise, "
        "or far from white) at a best point two starts reached, 6 the same at a best point "
        "one start reached (the fit may be in a local minimum: try more --starts), 7 "
        "(--posterior) the sampler has not converged.",
    )
    calibrate.add_argument("source", help="a calibration file (.toml) or a trace (.csv)")
    calibrate.add_argument("assignments", nargs="*", metavar="name=value",
                           help="known values, with a trace (e.g. v0=0.69)")  # fmt: skip
    calibrate.add_argument(
        "--fit",
        metavar="NAMES",
        help="with a trace: the parameters to fit, comma-separated (bounds: each one's "
        "documented range; t_shift: the trigger delay, -0.01 to 0.01 s)",
    )
    calibrate.add_argument(
        "--out", help="output folder (default results/calibrate/<file name, no suffix>)"
    )
    calibrate.add_argument(
        "--starts",
        type=int,
        metavar="N",
        help=f"fit from N starts (the given, then Sobol; default {rjx.DEFAULT_STARTS})",
    )
    calibrate.add_argument(
        "--validate",
        action="append",
        metavar="TRACE",
        help="a trace to score the fit on, not fitted (repeatable)",
    )
    calibrate.add_argument(
        "--profile",
        action="store_true",
        help="also profile-likelihood intervals: each value held at 12 points while the "
        "others are refitted (profiles.png)",
    )
    calibrate.add_argument(
        "--predict",
        nargs="*",
        metavar="name=value",
        help="then predict this design's peaks with 95%% bands from the fitted "
        "uncertainty (10,000 samples and linear propagation; prediction.png)",
    )
    add_store(calibrate, "commit each finished part of the fit (8 starts, or the points "
              "they met at, a stage; the profiles)", "calibration")  # fmt: skip
    calibrate.add_argument(
        "--force-table",
        metavar="FILE.csv",
        help="with a trace: the breech force of one round it fired (header t_s,F_N)",
    )
    calibrate.add_argument(
        "--posterior",
        action="store_true",
        help="then sample the posterior (NUTS, the file's [posterior] settings; "
        "posterior.nc, posterior.png, posterior_predictive.png; with --predict, also "
        "from its draws); exit 7 when its sampler has not converged",
    )
    calibrate.add_argument(
        "--prior",
        action="append",
        metavar="NAME=KIND[:MEAN,SD]",
        help="with --posterior: a fitted value's prior, uniform (over its bounds, the "
        "default), normal:MEAN,SD or lognormal:MEAN,SD (repeatable; over the file's)",
    )
    calibrate.add_argument(
        "--sample-noise",
        action="store_true",
        help="with --posterior: sample each trace's noise too (a half-normal prior, twice "
        "the fit's noise in scale unless the file's [posterior.noise_scale] says)",
    )
    for name, words in (("draws", "draws per chain (default 1000)"),
                        ("warmup", "warm-up steps per chain (default 1000)"),
                        ("chains", "chains (default 4)"),
                        ("parallel_chains", "chains at once (default: one per core)")):  # fmt: skip
        calibrate.add_argument(f"--{name.replace('_', '-')}", type=int, metavar="N",
                               help=f"with --posterior: {words}, over the file's")  # fmt: skip
    add_json(calibrate)
    add_max_steps(calibrate)
