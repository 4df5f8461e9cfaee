"""A step's row is made and written while the soil computes the next step (cosim.runner).

On a GPU the host's records then overlap the device's DEM steps; on the CPU the order of the calls
is what can be checked: the row of macro step k is written after step k + 1's DEM steps were
launched and before their result is read, it holds what step k left (bit for bit the rows written at
once), and no row is lost when a later step fails. The SCM terrain, whose grid steps run on the
device too, does the same.
"""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from cosim import runner as runner_module
from cosim.dem_soil import DemSoil
from cosim.launch import run_plan
from cosim.output import ResultsWriter
from cosim.plan import load_plan
from helpers import SCM_TERRAIN, write_tiny
from soil.macro import MacroSums, StepGraphs
from soil.scm import ScmTerrain

pytestmark = pytest.mark.filterwarnings("ignore::cosim.coupler.CouplingEnergyWarning")  # the tiny scene's
# coarse coupling warns while it drives: not what these tests check

SHORT = ["run.duration=0.03", "landing.max_time=0.1", "landing.hold_time=0.05", "landing.speed_ratio=1e-9"]
"""The tiny scene cut short: its landing does not end in 0.1 s (59 macro steps; no hub is that still, and
a landing's max_time must exceed its hold_time): landing rows, then the end."""
VARIANTS = {
    "drive": ["landing.enabled=false", "run.duration=0.1"],  # fixed steps, driving from the start: travel
    "pid": [*SHORT, 'run.step_control="pid"'],  # landing rows under the PID substeps: one captured loop a step
}
"""The tiny scene's runs whose rows are checked, each 59 macro steps."""


@pytest.fixture(scope="module", params=sorted(VARIANTS))
def plan(request, tmp_path_factory, tiny_bed):
    scene = write_tiny(tmp_path_factory.mktemp("overlap"))
    return load_plan(scene, [f'bed.bed_file="{tiny_bed}"', *VARIANTS[request.param]])


def _events(monkeypatch, launches=(StepGraphs, "replay"), reads=(MacroSums, "read")) -> list:
    """Log the soil's steps launched, its reads after a macro step and the rows written, in their order."""
    events: list = []
    append = ResultsWriter.append_step

    def logged(owner, name, event):
        function = getattr(owner, name)

        def call(*args, **kwargs):
            events.append(event)
            return function(*args, **kwargs)

        monkeypatch.setattr(owner, name, call)

    def writing(self, row):
        events.append(("row", row["time"]))
        return append(self, row)

    logged(*launches, "launch")
    logged(*reads, "read")
    monkeypatch.setattr(ResultsWriter, "append_step", writing)
    return events


def _order(events) -> tuple[list, list]:
    """The rows written right after the next step's launches (during it) and right after a read (at once)."""
    rows = [i for i, e in enumerate(events) if isinstance(e, tuple)]
    return [i for i in rows if events[i - 1] == "launch"], [i for i in rows if events[i - 1] == "read"]


@pytest.fixture(scope="module")
def overlapped(plan, tmp_path_factory):
    """The run as the runner makes it, with its calls' order."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        events = _events(monkeypatch)
        out = tmp_path_factory.mktemp("overlapped") / "run"
        result = run_plan(plan, str(out))
    return out, result, events


def _write_rows_at_once(monkeypatch) -> None:
    """Make the runner write each step's row right after its step, as it did before the overlap."""
    after_step = runner_module.Runner._after_step

    def at_once(self, record):
        after_step(self, record)
        self._settle_row()

    monkeypatch.setattr(runner_module.Runner, "_after_step", at_once)


def _rows(folder) -> dict:
    with h5py.File(folder / "results.h5", "r") as f:
        return {
            f"{group}/{name}": f[group][name][()]
            for group in ("wheels", "rover", "soil", "boundaries", "particles")
            if group in f
            for name in f[group]
            if isinstance(f[group][name], h5py.Dataset)
        }


def test_a_row_is_written_while_the_next_step_computes(overlapped, plan):
    out, result, events = overlapped
    rows = [e for e in events if isinstance(e, tuple)]
    reads = events.count("read")
    assert len(rows) == reads == int(round(0.1 / plan.macro_step))  # a row per macro step, none lost
    assert [t for _, t in rows] == sorted(t for _, t in rows)  # in step order
    # a row written while the soil computes comes right after the next step's DEM steps were launched,
    # and before their read; the others (before a snapshot, a checkpoint, the end) right after their read
    during, at_once = _order(events)
    assert len(during) + len(at_once) == len(rows)
    interval = min(plan.output.snapshot_interval, plan.output.checkpoint_interval)
    occasions = 2 * (1 + len(rows) * plan.macro_step / interval) + 1  # snapshots, checkpoints, the end
    assert len(at_once) <= occasions and len(during) >= len(rows) - occasions, (len(during), len(at_once))
    assert len(during) > 0.8 * len(rows)
    for i in during:  # the row of the step before the one launched: its read came before these launches
        behind = events[:i]
        assert behind.count("read") == sum(1 for e in behind if isinstance(e, tuple)) + 1
    assert isinstance(events[-1], tuple)  # the last step's row is written before the run ends


def test_rows_written_meanwhile_are_the_rows_written_at_once(overlapped, plan, tmp_path, monkeypatch):
    """What a row reads of the two sides is read when its step ends, not when the row is made."""
    out, _, _ = overlapped
    _write_rows_at_once(monkeypatch)
    run_plan(plan, str(tmp_path / "at_once"))
    ours, theirs = _rows(out), _rows(tmp_path / "at_once")
    assert set(ours) == set(theirs) and "wheels/force" in ours and "particles/position" in ours
    for name in ours:
        np.testing.assert_array_equal(ours[name], theirs[name], err_msg=name)  # bit for bit


@pytest.mark.parametrize("fail_at, after_meanwhile", [(7, False), (12, True)])
def test_a_step_that_fails_leaves_every_row_before_it(plan, tmp_path, monkeypatch, fail_at, after_meanwhile):
    """A failure in the soil's step, before or after the row was written meanwhile, loses no row."""
    advance = DemSoil.advance
    calls = [0]

    def failing(self, t_end, start, end=None, meanwhile=None):
        calls[0] += 1
        if calls[0] == fail_at:
            if after_meanwhile and meanwhile is not None:
                meanwhile()
            raise RuntimeError("the soil's step failed")
        return advance(self, t_end, start, end, meanwhile=meanwhile)

    monkeypatch.setattr(DemSoil, "advance", failing)
    out = tmp_path / "failed"
    with pytest.raises(RuntimeError, match="the soil's step failed"):
        run_plan(plan, str(out))
    times = _rows(out)["wheels/time"]
    assert len(times) == fail_at - 1  # every step that ended has its row
    np.testing.assert_allclose(np.diff(times), plan.macro_step, rtol=1e-9)


def test_an_scm_run_writes_its_rows_while_the_grid_steps_and_the_same_rows(tmp_path, monkeypatch):
    plan = load_plan(write_tiny(tmp_path, SCM_TERRAIN), ["wheel.grouser_count=0", *SHORT])
    with pytest.MonkeyPatch.context() as patch:  # the SCM steps launched by `advance`, read by `wheel_contact`
        events = _events(patch, launches=(ScmTerrain, "_pose"), reads=(ScmTerrain, "wheel_contact"))
        run_plan(plan, str(tmp_path / "meanwhile"))
    during, at_once = _order(events)
    assert len(during) + len(at_once) == int(round(0.1 / plan.macro_step)) and len(during) > 0.8 * len(at_once + during)

    _write_rows_at_once(monkeypatch)
    run_plan(plan, str(tmp_path / "at_once"))
    ours, theirs = _rows(tmp_path / "meanwhile"), _rows(tmp_path / "at_once")
    assert set(ours) == set(theirs) and "wheels/sinkage" in ours
    for name in ours:
        np.testing.assert_array_equal(ours[name], theirs[name], err_msg=name)


def test_a_batched_run_does_its_work_between_its_request_and_the_answer():
    """A world of a batch served by another process (cosim.batch.RemoteWorld): the run's request goes
    out, its own work is done while the batch steps, then the answer is read."""
    from cosim.batch import RemoteWorld

    calls: list = []

    class Pipe:
        def send(self, message):
            calls.append(("send", message[0]))

        def recv(self):
            calls.append("recv")
            return ("report", "the report", {"time": 0.01})

    description = dict.fromkeys(("boundary_kinds", "boundary_reports", "initial_boundary_geometry", "body_shapes"))
    description.update(index=0, time=0.0, gravity=(0, 0, -1), particle_count=1, body_count=1, boundary_count=0)
    world = RemoteWorld(Pipe(), description)
    report = world.advance_to(0.01, 0.001, path=True, meanwhile=lambda: calls.append("meanwhile"))
    assert calls == [("send", "advance"), "meanwhile", "recv"] and report == "the report" and world.time == 0.01


def test_a_soil_gets_the_meanwhile_work_when_its_advance_takes_it():
    """cosim.contract.advance_soil hands `meanwhile` to an advance that takes it (a method, a callable
    that cannot be hashed, asked once per class) and does the work after an advance that does not."""
    from cosim.contract import advance_soil

    calls: list = []

    class Taking:
        def advance(self, t_end, start, end=None, meanwhile=None):
            calls.append("step launched")
            meanwhile()
            calls.append("step read")
            return []

    class Without:
        def advance(self, t_end, start, end=None):
            calls.append("step")
            return []

    class Unhashable:
        __hash__ = None  # type: ignore[assignment]

        def __call__(self, t_end, start, end=None, meanwhile=None):
            return Taking.advance(None, t_end, start, end, meanwhile)

    unhashable = Without()
    unhashable.advance = Unhashable()  # type: ignore[method-assign]
    for soil, expected in (
        (Taking(), ["step launched", "row", "step read"]),
        (Taking(), ["step launched", "row", "step read"]),  # the class asked before: the same answer
        (Without(), ["step", "row"]),
        (unhashable, ["step launched", "row", "step read"]),
    ):
        calls.clear()
        assert advance_soil(soil, 1.0, [], meanwhile=lambda: calls.append("row")) == []
        assert calls == expected
