"""The forces family: a force defined here, in the test file alone, flows through the
library with no other edit (simulate, its command, gradients, a sweep, a study), and the
built-in parts are the family's members.

The force is a linear spring from the barrel to the mount, `k_m x_M`. On the barrel it
acts exactly as more recoil spring, so every result must equal the same design with
`k + k_m` (to the rounding of a sum taken in another order): an independent check of
each path it flows through.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import jax
import numpy as np
import pytest

import recoil_jax as rj
import recoil_jax.extend as rjx
from recoil_jax import apps
from tests.conftest import SCRIPT_FORCE, study_text

K_BASE, K_ADDED = 20000.0, 7500.0  # the paper's k is 27,500 N/m: 20,000 + 7,500
#: One tolerance for both designs (a design with a part beyond the paper's gets a
#: tighter default than the paper's), tight enough that they agree to 1e-7.
TIGHT = rj.SolverOptions(rtol=1e-9, atol=1e-12)


@pytest.fixture(scope="module")
def mount_spring():
    """A force of one's own, defined as a user would (`docs/developers.md`), and taken
    out of the registry again after the module's tests."""

    class MountSpring(rjx.Force):
        """A linear spring from the barrel to the mount: `k_m x_M` into `F_AN`."""

        GROUP = rjx.Group(
            "mount_spring", "MountSpring", "Spring to the mount", "hardware",
            ("mount_spring_stiffness",),
        )  # fmt: skip
        ROWS = (
            rjx.Parameter(
                name="mount_spring_stiffness", group="mount_spring", default=0.0,
                unit="N/m", lower=0.0, documented=(0.0, 1e6),
                meaning="a spring from the barrel to the mount",
            ),
        )  # fmt: skip

        mount_spring_stiffness: Any = rjx.float_leaf(0.0)

        def anchoring(self, y, t, design, smoothing):
            return {"mount_spring": self.mount_spring_stiffness * y[0]}

        def potential(self, x_M, design):
            return 0.5 * self.mount_spring_stiffness * x_M**2

        def anchoring_bound(self, reach, two_energy, design):
            return self.mount_spring_stiffness * reach

        def held_change(self, design):
            return 0.0

    yield MountSpring
    rjx.forget_part(MountSpring)
    assert "mount_spring_stiffness" not in rj.PARAMETERS and "mount_spring" not in rjx.GROUPS


def _designs(**values):
    """The design with the added spring, and the same with it folded into `k`."""
    added = rj.params_from_values(k=K_BASE, mount_spring_stiffness=K_ADDED, **values)
    folded = rj.params_from_values(k=K_BASE + K_ADDED, **values)
    return added, folded


def _close(a, b, rtol=1e-7):
    np.testing.assert_allclose(np.asarray(a, float), np.asarray(b, float), rtol=rtol, atol=0)


def test_a_force_joins_the_registry_and_the_design(mount_spring):
    p = rj.PARAMETERS["mount_spring_stiffness"]
    assert p.owner == "MountSpring" and p.group == "mount_spring"
    design = rj.params_from_values(mount_spring_stiffness=K_ADDED)
    assert isinstance(design.part("mount_spring"), mount_spring)
    assert list(design.parts())[-1] == "mount_spring"  # after the built-in parts
    assert rj.params_to_values(design)["mount_spring_stiffness"] == K_ADDED
    moved = rj.with_values(design, ["mount_spring_stiffness"], np.array([1e4]))
    assert float(rj.values_of(moved, ["mount_spring_stiffness"])[0]) == 1e4
    # Its range is checked as every parameter's, naming it, before anything compiles.
    with pytest.raises(rj.ParameterError, match=r"MountSpring.mount_spring_stiffness = -1"):
        rj.params_from_values(mount_spring_stiffness=-1.0)
    # One of a group in a design; a group's name and a parameter's are not taken twice.
    with pytest.raises(rj.ParameterError, match="given twice"):
        rj.RecoilParams(added=(mount_spring(), mount_spring()))
    with pytest.raises(rj.ParameterError, match="exists already"):

        class Again(rjx.Force):
            GROUP = rjx.Group("mount_spring", "Again", "Again", "hardware")
            ROWS = mount_spring.ROWS

            def anchoring(self, y, t, design, smoothing):
                return {}


def test_a_force_flows_through_simulate_and_its_command(mount_spring, capsys, tmp_path):
    for values in (dict(m=0.0), dict(m=1500.0, gap=0.05)):
        added, folded = _designs(**values)
        a, b = rj.peaks(added, options=TIGHT), rj.peaks(folded, options=TIGHT)
        for name in ("peak_displacement", "peak_anchoring_force", "max_stroke"):
            _close(getattr(a, name), getattr(b, name))
        history = rj.simulate(added)
        shares = history.forces.shares[history.forces.names.index("mount_spring")]
        _close(shares, K_ADDED * np.asarray(history.x_M), rtol=1e-12)
    # The command line takes it by its flat name, as every parameter, and plots it.
    plot = tmp_path / "history.png"
    command = ["simulate", "--json", "--no-cache", "m=0", f"k={K_BASE}",
               f"mount_spring_stiffness={K_ADDED}", "--plot", str(plot)]  # fmt: skip
    assert apps.main(command) in (0, None)
    assert plot.stat().st_size > 10_000
    printed = json.loads(capsys.readouterr().out)
    _close(printed["peak_anchoring_force_N"], rj.peaks(_designs(m=0.0)[0]).peak_anchoring_force)


def test_a_force_flows_through_the_gradients(mount_spring):
    """The exact gradient in the added stiffness equals the gradient in `k` of the folded
    design (both multiply `x_M`), and a central difference."""
    added, folded = _designs(m=0.0)
    _, ours = rj.peak_gradients(added, wrt=("mount_spring_stiffness",))
    _, theirs = rj.peak_gradients(folded, wrt=("k",))
    step = 1.0
    up, down = (
        rj.peaks(rj.with_values(added, ["mount_spring_stiffness"], [K_ADDED + s]))
        for s in (step, -step)
    )
    for metric in ("peak_displacement", "peak_anchoring_force"):
        d_added = getattr(ours, metric)[0]
        _close(d_added, getattr(theirs, metric)[0], rtol=1e-6)
        difference = (float(getattr(up, metric)) - float(getattr(down, metric))) / (2 * step)
        _close(d_added, difference, rtol=1e-4)


def test_a_force_flows_through_a_sweep(mount_spring):
    stiffness = np.array([0.0, 5000.0, K_ADDED, 15000.0])
    common = dict(m=np.full(4, 1500.0), gap=np.full(4, 0.05))
    swept = rj.sweep(
        {**common, "k": np.full(4, K_BASE), "mount_spring_stiffness": stiffness}, options=TIGHT
    )
    assert (rjx.status_codes(swept.status) == rjx.OK_CODE).all()
    folded = rj.sweep({**common, "k": K_BASE + stiffness}, options=TIGHT)
    for name in ("peak_displacement", "peak_anchoring_force"):
        _close(swept.peaks[name], folded.peaks[name])
    one = rj.peaks(_designs(m=1500.0, gap=0.05)[0], options=TIGHT)  # a batch's point
    _close(swept.peaks["peak_anchoring_force"][2], one.peak_anchoring_force, rtol=1e-9)


def test_a_force_flows_through_a_study(mount_spring, tmp_path):
    """A study tunes the added stiffness by its flat name, and finds what tuning `k`
    finds for the folded design: the stiffest spring (the least displacement) whose peak
    anchoring force keeps within 9 kN (about 45 kN/m in all, the limit met)."""
    found = {}
    for name, base in (("mount_spring_stiffness", 0.0), ("k", K_BASE)):
        study = tmp_path / f"{name}.toml"
        study.write_text(study_text(
            design=f"m = 0.0\nk = {K_BASE}",
            tune=f"{name} = [{base}, {base + 60000.0}]",
            objective="peak_displacement = 1.0",
            constraints="peak_anchoring_force = { max = 9000.0 }",
            optimiser="starts = 4\nsteps = 80",
        ))  # fmt: skip
        result = apps.run_study(study, out=tmp_path / name, progress=False)
        assert result["feasible"], result.get("message")
        found[name] = (result["best"][name] - base, result["objective"])
    (added, displacement), (folded, folded_displacement) = found.values()
    assert 15000.0 < folded < 35000.0  # inside the range: the limit holds it
    # The same optimum to the optimiser's stopping (80 steps; the added part also
    # tightens the solver's default tolerances): 0.5 % of the range, 0.1 % of the value.
    assert abs(added - folded) < 5e-3 * 60000.0
    _close(displacement, folded_displacement, rtol=1e-3)


def test_the_forces_of_a_state_are_the_familys_sum():
    """`F_AN` is the members' shares summed in order, less the reactions: checked against
    the laws written out, at a state of the envelope design."""
    from recoil_jax._model.forces.system import forces

    design = rj.params_from_values(
        m=0.0, elevation=35.0, friction_force=800.0, stop_stiffness=1e8,
        recuperator_force=5e3, recuperator_length=1.2, recuperator_preload=2e4,
        buffer_damping=3e4,
    )  # fmt: skip
    y = jax.numpy.array([-1e-4, -0.3, 0.0, 0.0])
    f = forces(y, design, rj.Smoothing(), t=0.0)
    assert f.names == (
        "recoil_spring", "recoil_damper", "recuperator", "preload", "counter_recoil",
        "friction", "stop",
    )  # fmt: skip
    assert float(f.stop) > 0
    expected = sum(float(s) for s in f.shares[:-1]) - float(f.stop)
    _close(f.anchoring, expected, rtol=1e-12)
    _close(f.recoil_spring, design.barrel.k * y[0], rtol=1e-15)


def test_the_developers_walkthrough_runs(tmp_path):
    """`docs/developers.md`'s *Adding a force* runs as written (in a process of its own:
    it registers its force for good there)."""
    import subprocess
    import sys

    guide = (Path(__file__).parents[1] / "docs" / "developers.md").read_text()
    section = guide[guide.index("## Adding a force") :]
    start = section.index("```python") + len("```python")
    code = section[start : section.index("```", start)]
    script = tmp_path / "walkthrough.py"
    script.write_text(code + "\nassert 'mount_spring_stiffness' in rj.PARAMETERS\n")
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]


def _bare_spring():
    """A spring to the mount that says nothing of the early stops (every hook None)."""

    class BareSpring(rjx.Force):
        GROUP = rjx.Group("bare_spring", "BareSpring", "Bare spring", "hardware")
        ROWS = (rjx.Parameter(name="bare_stiffness", group="bare_spring", default=0.0,
                              unit="N/m", lower=0.0, documented=(0.0, 1e6)),)  # fmt: skip
        bare_stiffness: Any = rjx.float_leaf(0.0)

        def anchoring(self, y, t, design, smoothing):
            return {"bare_spring": self.bare_stiffness * y[0]}

    return BareSpring


def test_a_force_that_does_not_bound_itself_runs_to_the_end(mount_spring):
    """Without its share of the energy bound the solve cannot stop early: it runs to
    `t1`, and finds the peaks the bounded force's early-stopped solve found. A part is
    forgotten and defined again; its code is in a store's identity."""
    from recoil_jax._campaigns.store import fingerprint

    bare = _bare_spring()
    try:
        with_hooks = rj.peaks(_designs(m=0.0)[0], options=TIGHT)
        without = rj.peaks(
            rj.params_from_values(m=0.0, k=K_BASE, bare_stiffness=K_ADDED), options=TIGHT
        )
        assert int(without.num_steps) > int(with_hooks.num_steps)  # (to t1)
        for name in ("peak_displacement", "peak_anchoring_force"):
            _close(getattr(without, name), getattr(with_hooks, name), rtol=1e-12)
        added, folded = _designs(m=0.0)
        bare_design = rj.params_from_values(m=0.0, k=K_BASE, bare_stiffness=K_ADDED)
        identities = {fingerprint(d) for d in (added, folded, bare_design)}
        assert len(identities) == 3
    finally:
        rjx.forget_part(bare)
    again = _bare_spring()  # forgotten: its group and rows may be given again
    try:
        assert "bare_stiffness" in rj.PARAMETERS
    finally:
        rjx.forget_part(again)


def test_a_share_is_one_forces():
    """Two forces that name the same share are refused, naming it."""

    class Doubled(rjx.Force):
        GROUP = rjx.Group("doubled", "Doubled", "Doubled", "hardware")
        ROWS = (rjx.Parameter(name="doubled_stiffness", group="doubled", default=0.0,
                              unit="N/m", lower=0.0),)  # fmt: skip
        doubled_stiffness: Any = rjx.float_leaf(0.0)

        def anchoring(self, y, t, design, smoothing):
            return {"recoil_spring": self.doubled_stiffness * y[0]}

    try:
        with pytest.raises(rj.ParameterError, match="'recoil_spring' is another force's"):
            rj.peaks(rj.params_from_values(m=0.0, doubled_stiffness=1.0))
    finally:
        rjx.forget_part(Doubled)
    with pytest.raises(rj.ParameterError, match="not fields"):

        class Misnamed(rjx.Force):  # a row that is not a field
            GROUP = rjx.Group("misnamed", "Misnamed", "Misnamed", "hardware")
            ROWS = (rjx.Parameter(name="stiff", group="misnamed", default=0.0, lower=0.0,
                                  unit="N/m"),)  # fmt: skip

            def anchoring(self, y, t, design, smoothing):
                return {}


def test_a_force_defined_in_a_script_is_whole_where_it_is_sent(mount_spring, tmp_path):
    """A force defined in a script's `__main__` and sent by value (cloudpickle, as to a
    Dask worker) solves there as where it was made, to the bit: its class is made again
    where it lands (equinox registers a module's pytree fields when its class is made,
    and a class sent by value is made empty: its spring would read its default, 0).
    Also where the receiving process has its own copy of the class (a worker started by
    `spawn` runs the script again). In the process that made it, a design copied or
    pickled keeps its part's class."""
    import copy
    import pickle
    import subprocess
    import sys

    cloudpickle = pytest.importorskip("cloudpickle")
    sent = tmp_path / "design.pkl"
    send = (
        SCRIPT_FORCE
        + f"""
import cloudpickle, pickle, copy
design = rj.params_from_values(k_r=20000.0, main_spring_stiffness=7500.0)
assert type(pickle.loads(cloudpickle.dumps(design)).added[0]) is MainSpring
assert type(copy.deepcopy(design).added[0]) is MainSpring
value = float(rj.peaks(design).peak_anchoring_force)
plain = float(rj.peaks(rj.params_from_values(k_r=20000.0)).peak_anchoring_force)
open({str(sent)!r}, "wb").write(cloudpickle.dumps((design, value, plain)))
"""
    )
    receive = f"""
import dataclasses, pickle, jax
import recoil_jax as rj
design, value, plain = pickle.loads(open({str(sent)!r}, "rb").read())
(part,) = design.added
assert len(jax.tree.leaves(part)) == 1, jax.tree.leaves(part)
assert [f.name for f in dataclasses.fields(part)] == ["main_spring_stiffness"]
assert part.potential(0.1, design) is None  # through `super()`
assert float(part.main_spring_stiffness) == 7500.0
assert "main_spring_stiffness" in rj.PARAMETERS
here = float(rj.peaks(design).peak_anchoring_force)
assert here == value != plain, (here, value, plain)
again, _, _ = pickle.loads(open({str(sent)!r}, "rb").read())
assert type(again.added[0]) is type(part)
print("whole")
"""
    for script in (send, receive, SCRIPT_FORCE + receive):
        done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip() == "whole"

    # In the process that made it: copied, or pickled by value, its class is its own.
    design = rj.params_from_values(k_r=20000.0, mount_spring_stiffness=7500.0)
    for back in (copy.deepcopy(design), pickle.loads(cloudpickle.dumps(design))):
        assert type(back.added[0]) is mount_spring
        assert jax.tree.leaves(back) == jax.tree.leaves(design)


class _Workers:
    """A Dask client as `_check_importable_on_workers` sees it: its workers by address,
    and `run` answering for each worker asked (those in `without` lack the module
    `springs_on_path`), recording whom it asked."""

    def __init__(self, workers, without=()):
        self.workers, self.without, self.asked = list(workers), set(without), []

    def nthreads(self):
        return {address: 1 for address in self.workers}

    def run(self, function, classes, workers):
        self.asked.append(sorted(workers))
        lacking = {c: "ModuleNotFoundError: no springs_on_path" for c in classes
                   if c[0] == "springs_on_path"}  # fmt: skip
        return {w: lacking if w in self.without else function(classes) for w in workers}


def test_a_sweep_asks_its_workers_for_the_classes_its_parts_are_sent_by(
    mount_spring, tmp_path, monkeypatch
):
    """Before a chunk goes to a Dask cluster, each worker is asked, once, for the classes
    that cloudpickle sends its outside parts by reference with (a module's top-level
    class and its bases), not for one made in a function or from a module registered
    by value (sent by value) nor for the package's own; a worker that lacks one is
    named with the module and why, where it would otherwise leave the sweep waiting for
    ever; a worker that joins is asked before the next chunk, and a cluster with no
    workers yet is asked nothing."""
    from recoil_jax._sweeps.dispatch import _check_importable_on_workers, _classes_by_reference

    made_in_a_function = rj.params_from_values(mount_spring_stiffness=K_ADDED)
    assert _classes_by_reference(made_in_a_function) == {}
    (tmp_path / "springs_on_path.py").write_text(SCRIPT_FORCE)
    monkeypatch.syspath_prepend(str(tmp_path))
    import springs_on_path  # type: ignore[import-not-found]

    try:
        design = rj.params_from_values(k_r=K_BASE, main_spring_stiffness=K_ADDED)
        needed = _classes_by_reference(design)
        assert needed == {("springs_on_path", "MainSpring"): "MainSpring"}

        verified: dict = {}
        cluster = _Workers([])
        _check_importable_on_workers(cluster, design, verified)  # no worker yet
        assert cluster.asked == [] and verified == {}
        cluster.workers = ["tcp://a", "tcp://b"]
        _check_importable_on_workers(cluster, design, verified)
        _check_importable_on_workers(cluster, design, verified)  # asked once
        assert cluster.asked == [["tcp://a", "tcp://b"]]
        cluster.workers.append("tcp://c")  # joins: asked alone
        _check_importable_on_workers(cluster, design, verified)
        assert cluster.asked[1:] == [["tcp://c"]]

        lacking = _Workers(["tcp://a", "tcp://b"], without={"tcp://b"})
        with pytest.raises(ImportError, match="no springs_on_path") as error:
            _check_importable_on_workers(lacking, design, {})
        assert error.value.name == "springs_on_path"
        assert "worker tcp://b cannot import springs_on_path.MainSpring" in str(error.value)
        assert "tcp://a" not in str(error.value)
        cloudpickle = pytest.importorskip("cloudpickle")
        cloudpickle.register_pickle_by_value(springs_on_path)  # then sent by value
        try:
            assert _classes_by_reference(design) == {}
        finally:
            cloudpickle.unregister_pickle_by_value(springs_on_path)
    finally:
        rjx.forget_part(springs_on_path.MainSpring)
        sys.modules.pop("springs_on_path", None)
