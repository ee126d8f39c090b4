"""No process-wide setting leaks out of a library call (runtime/process_state.py).

heliocal switches torch to deterministic algorithms and one thread while it fits, and worker
pools set one-thread BLAS variables; a program that calls the library must find torch's flags,
its thread count and os.environ as they were. The fit below runs its tasks in this process
(``workers=1``), where the training task sets the deterministic flag: without the guard the flag
stays on after the call (checked: removing ``@restores_process_state`` from ``run_fit_hybrid``
makes ``test_a_fit_leaves_torch_and_the_environment_as_they_were`` fail).
"""

from __future__ import annotations

import os

import pytest
import torch

from heliocal.pipeline.models.config import FineConfig
from heliocal.pipeline.models.simulator import simulate_field
from heliocal.pipeline.runtime.process_state import (ProcessState, one_thread,
                                                     restored_process_state)
from heliocal.pipeline.stages.aim import aim_steps
from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
from heliocal.pipeline.stages.fit_hybrid import run_fit_hybrid
from heliocal.pipeline.stages.ingest import run_ingest
from heliocal.pipeline.stages.simulate import write_field
from heliocal.pipeline.stages.split import run_split

MARKER = "HELIOCAL_TEST_PROCESS_STATE"


def _state() -> ProcessState:
    """The state now, without the variable pytest itself rewrites between test phases."""
    state = ProcessState.capture()
    state["environ"].pop("PYTEST_CURRENT_TEST", None)
    return state


@pytest.fixture
def unusual_state():
    """A state unlike what heliocal sets (deterministic off, 3 threads, a marker variable), and
    the caller's own state restored afterwards whatever the test did."""
    with restored_process_state():
        torch.use_deterministic_algorithms(False)
        torch.set_num_threads(3)
        os.environ[MARKER] = "caller's value"
        os.environ.pop("OMP_NUM_THREADS", None)
        yield _state()


def test_the_guard_undoes_flag_threads_and_environment(unusual_state):
    with restored_process_state():
        torch.use_deterministic_algorithms(True, warn_only=True)
        torch.set_num_threads(1)
        os.environ[MARKER] = "changed"
        os.environ["OMP_NUM_THREADS"] = "1"
    assert _state() == unusual_state
    assert not torch.are_deterministic_algorithms_enabled() and torch.get_num_threads() == 3
    assert os.environ[MARKER] == "caller's value" and "OMP_NUM_THREADS" not in os.environ


def test_the_guard_restores_after_an_exception(unusual_state):
    with pytest.raises(RuntimeError), restored_process_state():
        torch.use_deterministic_algorithms(True)
        del os.environ[MARKER]
        raise RuntimeError("a failing stage")
    assert _state() == unusual_state


def test_one_thread_restores_the_thread_count(unusual_state):
    with one_thread():
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 3


def test_a_fit_leaves_torch_and_the_environment_as_they_were(tmp_path, unusual_state):
    field = simulate_field(1, seed=3, measurements=(70, 70), dynamic_fraction=0.0)
    write_field(field, tmp_path / "field")
    wd = tmp_path / "wd"
    run_ingest([tmp_path / "field"], wd)
    run_split(wd, n_test=10, n_val=10)
    run_fit_coarse(wd, preset="static-6", workers=1)
    assert _state() == unusual_state
    summary = run_fit_hybrid(wd, mode="hybrid", config=FineConfig(max_epochs=5, patience=5,
                                                                   ensemble=1), workers=1)
    assert [h["heliostat_id"] for h in summary["heliostats"]] == list(field.heliostats)
    assert _state() == unusual_state
    hid = next(iter(field.heliostats))
    aim_steps(wd, hid, aim_point_enu=[0.0, 0.0, 40.0], time_utc="2023-06-21T10:00:00Z")
    assert _state() == unusual_state


def test_a_guard_in_a_process_without_torch_does_not_import_it(tmp_path):
    """``info`` and ``report`` ask aim_choice.aim_models, which is guarded: the guard must not
    import torch (about a second of every such command's start). Run in a fresh interpreter,
    since this one has torch; the same process then imports torch inside a guard, turns the
    deterministic flag on, and must find it off again after the guard (torch's own default)."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from heliocal.pipeline.runtime.process_state import restored_process_state\n"
        "with restored_process_state():\n"
        "    pass\n"
        "print('torch' in sys.modules)\n"
        "with restored_process_state():\n"
        "    import torch\n"
        "    torch.use_deterministic_algorithms(True)\n"
        "print(torch.are_deterministic_algorithms_enabled())\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["False", "False"]
