"""The layout the code promises: the engine never imports the applications, the
applications use only the engine's public API, modules import from each other only what
the source module declares in `__all__` (never a private name), and every form of a
parameter or metric name derives from its registry."""

import ast
import dataclasses
import importlib
import importlib.util
import re
from pathlib import Path

import pytest

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax._model.bounds import future_metric_bounds, held_bounds
from recoil_jax._model.equations import initial_state, model_args, signals, tracked_metrics

PACKAGE = Path(rj.__file__).parent
#: The engine: the private modules at the top (`_version`) and in the capability folders
#: (`_model/`, `_campaigns/`, `_sweeps/`, `_design/`, `_calibration/`,
#: `_global_sensitivity/`).
ENGINE = sorted(
    p for p in [*PACKAGE.glob("_*.py"), *PACKAGE.glob("_*/**/*.py")] if p.name != "__init__.py"
)
#: The applications: every module of `apps/`'s folders (`_cli/`, `_files/`, ...).
APPS = sorted(
    p for p in (PACKAGE / "apps").glob("_*/*.py") if p.name not in ("__init__.py", "__main__.py")
)


def _module_name(path: Path) -> str:
    """`recoil_jax._model.solve` for `recoil_jax/_model/solve.py`."""
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path):
    """`(module, name)` for every `from module import name` in `path` (relative imports
    resolved to `recoil_jax...`), and every `import module`."""
    tree = ast.parse(path.read_text())
    package = (
        _module_name(path).rsplit(".", 1)[0] if path.name != "__init__.py" else _module_name(path)
    )
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{module}" if module else base
            for alias in node.names:
                yield module, alias.name
        elif isinstance(node, ast.Import):
            for alias in node.names:
                yield alias.name, None


def test_engine_never_imports_the_applications():
    for path in ENGINE:
        for module, _ in _imports(path):
            assert not module.startswith("recoil_jax.apps"), (path.name, module)


def test_applications_use_only_the_public_api():
    # The exceptions are named, with their reasons, in `recoil_jax.apps.READS_INTERNALS`.
    from recoil_jax.apps import READS_INTERNALS

    public = {"recoil_jax", "recoil_jax.extend"}
    for path in APPS:
        for module, name in _imports(path):
            if module.startswith("recoil_jax") and not module.startswith("recoil_jax.apps"):
                allowed = module in public and name is None
                where = path.relative_to(PACKAGE / "apps").as_posix()
                assert allowed or where in READS_INTERNALS, (where, module, name)
        # And every name they read from them is in its `__all__`.
        text = path.read_text()
        for prefix, source in (("rj", rj), ("rjx", rj.extend)):
            for name in re.findall(rf"\b{prefix}\.([a-zA-Z]\w*)", text):
                assert name in source.__all__, (path.name, f"{prefix}.{name}")


def test_the_public_api_is_small_and_declared():
    # 70 for the solver and the design layer (issue 43), 5 for calibration, 5 for global
    # sensitivity (the function, its result and its three methods), 4 for the firing
    # envelope's parameter groups (issue 54: Rails, BatteryStop, CounterRecoilBuffer, Mount)
    # and 1 for its firing conditions (`Condition`), 1 for the posterior (issue 67).
    assert len(rj.__all__) <= 91 and len(set(rj.__all__)) == len(rj.__all__)
    assert all(hasattr(rj, name) for name in rj.__all__)
    assert all(hasattr(rj.extend, name) for name in rj.extend.__all__)
    # A name is public in one place: the top level or `recoil_jax.extend`.
    assert not set(rj.__all__) & set(rj.extend.__all__)


#: The applications' folders from the bottom, each importing only those before it.
APP_LAYERS = {
    "_files": set(),
    "_figures": {"_files"},
    "_studies": {"_files", "_figures"},
    "_explore": {"_files", "_figures"},
    "_bench": {"_files", "_figures", "_studies"},
    "_cli": {"_files", "_figures", "_studies", "_explore", "_bench"},
}


def test_no_application_import_runs_up_a_layer():
    """Each folder of `apps/` imports only the folders below it, and its `__init__` names
    them on its `May import:` line."""
    assert {p.name for p in (PACKAGE / "apps").glob("_*/")} == set(APP_LAYERS)
    for folder, allowed in APP_LAYERS.items():
        for path in sorted((PACKAGE / "apps" / folder).glob("*.py")):
            for module, _ in _imports(path):
                parts = module.split(".")
                if parts[:2] != ["recoil_jax", "apps"] or len(parts) < 3:
                    continue
                assert parts[2] in allowed | {folder}, (folder, path.name, module)
        doc = importlib.import_module(f"recoil_jax.apps.{folder}").__doc__ or ""
        line = doc[doc.index("May import:") :]
        assert all(f"`{name}`" in line for name in allowed), (folder, line)


@pytest.mark.parametrize("path", ENGINE + APPS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_cross_module_imports_are_declared(path):
    """Between the package's own modules, only names in the source module's `__all__`
    are imported, and never a private (underscored) name (a dunder such as `__version__`
    is public)."""
    for module, name in _imports(path):
        if not module.startswith("recoil_jax.") or name is None:
            continue
        if hasattr(importlib.import_module(module), "__path__") and importlib.util.find_spec(
            f"{module}.{name}"
        ):
            continue  # a module of a folder (`from . import sweep`)
        dunder = name.startswith("__") and name.endswith("__")
        assert dunder or not name.startswith("_"), (path.name, module, name)
        source = importlib.import_module(module)
        declared = getattr(source, "__all__", None)
        assert declared is not None, f"{module} declares no __all__"
        assert name in declared, (path.name, module, name)


def test_every_module_declares_what_it_exports():
    for path in ENGINE + [p for p in APPS if p.name != "__init__.py"]:
        module = importlib.import_module(_module_name(path))
        for name in module.__all__:
            assert hasattr(module, name), (path.stem, name)


def test_metric_names_derive_from_the_registry():
    # The JSON / CSV keys users read stay exactly as they were.
    assert list(rjx.PEAK_FIELDS.values()) == [
        "peak_displacement_m",
        "peak_displacement_time_s",
        "peak_anchoring_force_N",
        "peak_anchoring_force_time_s",
        "peak_contact_force_N",
        "peak_contact_force_time_s",
        "min_stroke_m",
        "max_stroke_m",
        "return_time_s",
        "battery_speed_m_per_s",
        "residual_displacement_m",
        "stability_margin",
        "stability_margin_time_s",
        "peak_pull_force_N",
        "peak_pull_force_time_s",
        "peak_mount_load_N",
        "peak_mount_load_time_s",
        "returned",
        "num_steps",
    ]
    peaks_fields = [f.name for f in dataclasses.fields(rj.Peaks)]
    assert peaks_fields == [*rjx.PEAK_FIELDS, "num_attempts", "status"]
    assert [f.name for f in dataclasses.fields(rj.PeakGradients)] == [*rj.METRICS, "wrt"]
    # The model tracks, and bounds, exactly the registered metrics.
    params, smoothing = rj.RecoilParams(), rj.Smoothing()
    args = model_args(params, smoothing)
    y = initial_state(args)
    extremes = [name for name, m in rj.METRICS.items() if m.kind == "extreme"]
    # (Each design tracks those its structure does not hold constant: here no pull, the
    # design having no envelope; without an absorber, no contact and no stroke.)
    assert list(tracked_metrics(0.0, y, args)) == [e for e in extremes if e != "peak_pull_force"]
    bare = model_args(rj.params_from_values(m=0.0, elevation=5.0), smoothing)
    assert list(tracked_metrics(0.0, initial_state(bare), bare)) == [
        "peak_displacement", "peak_anchoring_force", "stability_margin", "peak_pull_force"
    ]  # fmt: skip
    tracked = set(tracked_metrics(0.0, y, args))
    assert set(future_metric_bounds(y, args, 0.0, 1.0)) >= tracked
    assert set(held_bounds(y, args, 0.0, 1.0)) >= tracked
    assert {rj.METRICS[name].signal for name in extremes} <= set(signals(0.0, y, args))


def test_parameter_names_derive_from_the_registry():
    groups = {
        "barrel": rj.Barrel,
        "absorber": rj.Absorber,
        "contact": rj.Contact,
        "load": rj.Load,
        "buffer": rj.Buffer,
        "recuperator": rj.Recuperator,
        "rails": rj.Rails,
        "battery_stop": rj.BatteryStop,
        "counter_recoil_buffer": rj.CounterRecoilBuffer,
        "mount": rj.Mount,
    }
    arrays = {"table", "orifice"}  # not scalar parameters: the force table, the knots
    assert {p.group for p in rj.PARAMETERS.values()} == set(groups)
    assert all(p.owner == groups[p.group].__name__ for p in rj.PARAMETERS.values())
    for group, cls in groups.items():
        fields = [f.name for f in dataclasses.fields(cls) if f.name not in arrays]
        assert fields == [n for n, p in rj.PARAMETERS.items() if p.group == group], group
        for name in fields:
            assert float(getattr(cls(), name)) == rj.PARAMETERS[name].default
    # The paper's design has no load, buffer or recuperator: their names are absent.
    paper = [n for n, p in rj.PARAMETERS.items() if p.group in ("barrel", "absorber", "contact")]
    assert list(rj.params_to_values(rj.RecoilParams())) == paper
    # The orifice knots are a family of names, looked up like the others.
    knot = rj.PARAMETERS["orifice_7"]
    assert (knot.group, knot.index, knot.unit) == ("buffer", 7, "m^2")
    assert "orifice_32" not in rj.PARAMETERS and "orifice_07" not in rj.PARAMETERS


#: The public API, name for name (issue 53: a layout change must keep it): the top level
#: `rj`, `recoil_jax.extend` and `recoil_jax.apps`. A name added or removed is a change a
#: user sees, and is made here on purpose.
RJ_NAMES = (
    "Absorber",
    "Agreement",
    "AugmentedLagrangian",
    "Barrel",
    "BasinHopping",
    "BatteryStop",
    "Buffer",
    "Calibration",
    "CalibrationResult",
    "sample_posterior",
    "CampaignProgress",
    "Condition",
    "Constraint",
    "Contact",
    "CounterRecoilBuffer",
    "DESIGN_PARAMETERS",
    "DGSM",
    "DesignProblem",
    "EpigraphMinimax",
    "FEASIBILITY_TOLERANCE",
    "ForceTable",
    "GRADIENT_OPTIONS",
    "History",
    "Load",
    "METRICS",
    "MetricSeries",
    "MorrisEffects",
    "Mount",
    "Objective",
    "OptaxLocal",
    "OptimiseResult",
    "PARAMETERS",
    "ParameterError",
    "PeakGradients",
    "Peaks",
    "Rails",
    "peaks_hazards",
    "RecoilParams",
    "Recuperator",
    "SLSQP",
    "SensitivityResult",
    "SmoothMax",
    "Smoothing",
    "SobolIndices",
    "SobolStarts",
    "SolveError",
    "SolverOptions",
    "Status",
    "Stopping",
    "SweepResult",
    "TrustRegionLP",
    "calibrate",
    "campaign_progress",
    "case_params",
    "closest_miss",
    "constraint_report",
    "default_optimiser",
    "differentiable_peaks",
    "enable_compilation_cache",
    "failure_message",
    "feasible",
    "grid",
    "load_sweep",
    "metric_violations",
    "minimise",
    "optimise",
    "paper_cases",
    "parameter_scale",
    "params_from_values",
    "params_to_values",
    "peak_gradients",
    "peak_jacobian",
    "peak_metrics",
    "peaks",
    "predict",
    "read_trace",
    "reference_peaks",
    "search",
    "sensitivity",
    "simulate",
    "sweep",
    "sweep_grid",
    "sweep_to_store",
    "use_avx2_codegen",
    "values_of",
    "with_table",
    "with_values",
    "FiringPlan",
    "PlanProblem",
    "Sensor",
    "plan_firings",
)
RJX_NAMES = (
    "DEFAULT_CONTINUATION",
    "BatchEvaluation",
    "BatchEvaluator",
    "Continuation",
    "DEFAULT_STARTS",
    "DesignEvaluation",
    "Experiment",
    "Fitted",
    "ModelMisfitError",
    "Posterior",
    "PosteriorPredictive",
    "Prior",
    "FittedParameters",
    "Force",
    "Forces",
    "GlobalPhase",
    "GROUPS",
    "Group",
    "GradientEvaluator",
    "Grid",
    "HAZARDS",
    "Hazard",
    "LOSSES",
    "LocalEvaluation",
    "LocalMethod",
    "LocalRun",
    "MAX_TEXT_BYTES",
    "Metric",
    "MinimaxEvaluator",
    "MinimaxMethod",
    "MinimaxWindow",
    "ModelCheck",
    "OK_CODE",
    "PEAK_FIELDS",
    "Parameter",
    "Part",
    "design_hazards",
    "hazard_flags",
    "Prediction",
    "RunRecord",
    "SENSITIVITY_METHODS",
    "SIGNALS",
    "SearchSpace",
    "SensitivityMethod",
    "SignalCheck",
    "StoredEvaluator",
    "StoredSweep",
    "T1_LIMITS",
    "T_SHIFT",
    "Trace",
    "batch_params",
    "check_integer",
    "check_memory",
    "default_local",
    "default_workers",
    "end_time",
    "evaluate_design",
    "fit_many",
    "float_leaf",
    "forget_part",
    "gradient_key",
    "live_programs",
    "log_coordinates",
    "minimax_metric",
    "read_text",
    "written",
    "reference_history",
    "run_local",
    "sensitivity_box",
    "set_max_programs",
    "shard_batch",
    "signal_sensitivities",
    "status_codes",
    "status_messages",
    "status_table",
    "structure_jit",
    "trace_noise",
    "validate",
    "worst_case",
    "PlanCheck",
    "PlanReport",
    "candidate_information",
    "check_plan",
    "check_posterior_settings",
    "check_tests_memory",
    "plan_calibration",
)
APPS_NAMES = (
    "READS_INTERNALS",
    "explorer",
    "load_study",
    "main",
    "plot_convergence",
    "plot_heatmap",
    "plot_history",
    "plot_plan_information",
    "plot_plan_intervals",
    "plot_series",
    "reproduce",
    "resolve_study",
    "run_bench",
    "run_study",
    "run_tuning_bench",
)


def test_the_public_api_is_what_it_was_name_for_name():
    import recoil_jax.apps as apps

    assert sorted(rj.__all__) == sorted(RJ_NAMES)
    assert sorted(rjx.__all__) == sorted(RJX_NAMES)
    assert sorted(apps.__all__) == sorted(APPS_NAMES)
    for module, names in ((rj, RJ_NAMES), (rjx, RJX_NAMES)):
        for name in names:
            assert getattr(module, name) is not None, name


def test_the_docs_count_the_public_api_as_it_is():
    """The README's and the developers' guide's size of the top level is the size of
    `rj.__all__`: a figure in the docs that drifts from the code fails here."""
    root = PACKAGE.parent
    readme = re.findall(r"\(`rj`, (\d+) names\)", (root / "README.md").read_text())
    guide = re.findall(
        r"the public API: (\d+) names", (root / "docs" / "developers.md").read_text()
    )
    assert readme and guide
    assert {int(n) for n in readme + guide} == {len(rj.__all__)}


def test_no_module_imports_the_version_from_the_top_level():
    """The version has a module of its own (`_version`): a part of the package that took
    it from the top level would import upward, against the layers."""
    for path in [*ENGINE, *APPS]:
        for module, name in _imports(path):
            if name == "__version__":
                assert module == "recoil_jax._version", (path.name, module)


def test_calibration_stands_without_the_optimiser():
    """Calibration imports the model, the campaigns and the sweeps (the batches, the search
    space), never the optimisation layer."""
    for path in sorted((PACKAGE / "_calibration").glob("*.py")):
        for module, _ in _imports(path):
            assert not module.startswith("recoil_jax._design"), (path.name, module)
    # And its command: the calibration through the public API, the inputs and the figures.
    command = PACKAGE / "apps" / "_cli" / "calibrate.py"
    for module, _ in _imports(command):
        if module.startswith("recoil_jax.apps."):
            folder = module.split(".")[2]
            assert folder in ("_files", "_figures", "_cli") and "study" not in module, module
    used = {name for name in re.findall(r"\brjx?\.([a-zA-Z]\w*)", command.read_text())}
    assert not used & {"search", "optimise", "sensitivity", "DesignProblem"}, used


#: The engine's folders from the bottom: each may import only those before it (and
#: `_version`); `_design` and `_calibration` stand side by side.
LAYERS = {
    "_model": set(),
    "_campaigns": {"_model"},
    "_sweeps": {"_model", "_campaigns"},
    "_design": {"_model", "_campaigns", "_sweeps"},
    "_calibration": {"_model", "_campaigns", "_sweeps"},
    "_global_sensitivity": {"_model", "_campaigns", "_sweeps", "_design"},
    "_planning": {"_model", "_sweeps", "_calibration"},
}


def test_no_engine_import_runs_up_a_layer():
    """Each folder imports only the folders below it (module-level and in functions),
    and its `__init__` names them on its `May import:` line."""
    assert {p.name for p in PACKAGE.glob("_*/")} == set(LAYERS)
    for folder, allowed in LAYERS.items():
        for path in sorted((PACKAGE / folder).rglob("*.py")):
            for module, _ in _imports(path):
                parts = module.split(".")
                if parts[0] != "recoil_jax" or len(parts) < 2 or parts[1] == "_version":
                    continue
                assert parts[1] in allowed | {folder}, (folder, path.name, module)
        doc = importlib.import_module(f"recoil_jax.{folder}").__doc__ or ""
        line = doc[doc.index("May import:") :]
        assert all(f"`{name}`" in line for name in allowed), (folder, line)


def test_no_module_imports_itself_through_others():
    """The package's modules import each other without a cycle (imports inside functions
    included): each could be loaded first."""
    paths = sorted(PACKAGE.rglob("*.py"))
    modules = {_module_name(p): p for p in paths}
    graph = {}
    for name, path in modules.items():
        targets = set()
        for module, imported in _imports(path):
            full = f"{module}.{imported}"
            target = full if full in modules else module
            if target in modules and target != name:
                targets.add(target)
        graph[name] = targets
    finished: set[str] = set()

    def visit(name: str, stack: list[str]) -> None:
        for target in sorted(graph[name]):
            assert target not in stack, " -> ".join([*stack[stack.index(target) :], target])
            if target not in finished:
                visit(target, [*stack, target])
        finished.add(name)

    for name in sorted(graph):
        if name not in finished:
            visit(name, [name])


def test_the_package_cites_only_its_own_documents():
    """The code's comments and docstrings cite `docs/model.md` and the other pages of
    `docs/`, never a design note outside the repository (`envelope.md`,
    `extensions.md`, `model.md` of `../shared`), which a user does not have."""
    outside = re.compile(r"(?<![\w/])(envelope|extensions)\.md|\.\./shared")
    cited = [f"{path.relative_to(PACKAGE)}:{number}: {line.strip()}"
             for path in sorted(PACKAGE.rglob("*.py"))
             for number, line in enumerate(path.read_text().splitlines(), 1)
             if outside.search(line)]  # fmt: skip
    assert not cited, cited


def _group_lists(path: Path):
    """`(line, names)` of each literal in `path` that lists two or more parameter groups:
    a tuple, list or set of their names, or a dict whose keys are all group names."""
    from recoil_jax.extend import GROUPS

    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Tuple | ast.List | ast.Set):
            items = node.elts
        elif isinstance(node, ast.Dict) and all(k is not None for k in node.keys):
            items = [k for k in node.keys if k is not None]
            if not all(isinstance(k, ast.Constant) and k.value in GROUPS for k in items):
                continue
        else:
            continue
        names = [e.value for e in items if isinstance(e, ast.Constant) and e.value in GROUPS]
        if len(names) >= 2:
            yield node.lineno, names


def test_the_groups_are_listed_once(tmp_path):
    """The parameter groups are listed in one place, the registry's `GROUPS` (each with
    its pytree, title, part of the gun and switches); every other form derives from it
    (`PAPER_GROUPS`, a design's `Structure`, the explorer's cards; each group's part is
    a member of the forces family, `tests/test_forces_family.py`). No other module lists
    two or more of them by hand."""
    sample = tmp_path / "sample.py"  # what the check finds, and what it leaves
    sample.write_text('A = ("rails", "mount")\nB = {"load": 1, "buffer": 2}\n'
                      'C = {"load": 1, "shots": 2}\nD = ("rails",)\n')  # fmt: skip
    assert [line for line, _ in _group_lists(sample)] == [1, 2]
    registry = PACKAGE / "_model" / "registry.py"
    assert list(_group_lists(registry)) == []  # `Group(...)` calls, not a literal list
    found = [f"{path.relative_to(PACKAGE)}:{line}: {names}"
             for path in sorted(PACKAGE.rglob("*.py"))
             for line, names in _group_lists(path)]  # fmt: skip
    assert not found, found
    from recoil_jax._model.params import RecoilParams

    fields = [f.name for f in dataclasses.fields(RecoilParams)]
    assert fields == [*rjx.GROUPS, "added"]  # a field a built-in group, in its order


def test_every_force_module_is_a_member_of_the_family():
    """Every module of `_model/forces` but the family's own, the smoothed switches and
    the system that sums them defines a part of the gun, found through the family
    (`FAMILY`), with its group in the registry; and every built-in group has its part:
    no list of forces is kept by hand (`tests/test_forces_family.py` adds one)."""
    import importlib
    import pkgutil

    from recoil_jax._model.forces import family

    folder = PACKAGE / "_model" / "forces"
    tools = {"family", "smoothing", "system"}
    members = {cls.__module__.rsplit(".", 1)[-1] for cls in family.FAMILY.values()}
    for module in pkgutil.iter_modules([str(folder)]):
        importlib.import_module(f"recoil_jax._model.forces.{module.name}")
        assert module.name in tools or module.name in members, module.name
    built_in = {g for g, cls in family.FAMILY.items() if not cls.ROWS}
    assert built_in == set(rjx.GROUPS) - {g for g, cls in family.FAMILY.items() if cls.ROWS}
    for group, cls in family.FAMILY.items():
        assert rjx.GROUPS[group].pytree == cls.__name__


def test_a_programs_structure_is_resolved_once(monkeypatch):
    """Which parts a design has (`Structure`) is resolved once as a program is traced
    and carried in its `args`, not asked again by every signal and bound (the envelope's
    check ran 28 times in a peak program's trace, 33 in a gradient program's): once for
    the peaks, twice for the gradients (the setup and the loop's wiring)."""
    import jax

    from recoil_jax._model.derivatives import tangent_solve
    from recoil_jax._model.forces import system
    from recoil_jax._model.solve import peak_metrics

    calls = []
    resolve = system.Structure.of.__func__
    monkeypatch.setattr(
        system.Structure, "of", classmethod(lambda cls, p: calls.append(1) or resolve(cls, p))
    )
    design = rj.params_from_values(
        elevation=35.0, friction_force=800.0, stop_stiffness=1e8, recuperator_force=5e3,
        recuperator_length=1.2, recuperator_preload=2e4, buffer_damping=3e4, mount_mass=9e3,
    )  # fmt: skip
    smoothing, options = rj.Smoothing(), rj.SolverOptions()
    jax.jit(lambda p: peak_metrics(p, smoothing, options)).lower(design)
    assert len(calls) == 1
    calls.clear()
    jax.jit(lambda p: tangent_solve(p, smoothing, options, ("k", "c_out")).gradients).lower(design)
    assert len(calls) == 2
    # `args` built by hand without it (as the model internals page shows) resolve it
    # where it is read, to the same signals.
    from recoil_jax._model.equations import ModelArgs

    args = model_args(design, smoothing)
    by_hand = ModelArgs(design, smoothing, args.contact_width, args.rest)
    y = initial_state(args)
    assert signals(0.0, y, by_hand).keys() == signals(0.0, y, args).keys()
    assert tracked_metrics(0.0, y, by_hand) == tracked_metrics(0.0, y, args)
