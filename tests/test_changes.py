"""Tests of the simulator's change events (pipeline/models/changes.py): regime steps, episodes and
drift as ground truth for issue 17's detection.

Expected values are the definitions of models/changes.py: an event offsets its parameters by
exactly ``parameters`` (rad) on the rows it covers (steps from ``start`` on, episodes in
[start, end), drifts by years since ``start``), and nothing else changes.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch

from heliocal.pipeline.errors import ParameterError
from heliocal.pipeline.models.changes import Changes
from heliocal.pipeline.models.simulator import simulate_field
from heliocal.pipeline.physics.parameters import PARAMETER_INDEX
from heliocal.pipeline.stages.simulate import write_field

ALL = Changes(step_fraction=1.0, episode_fraction=1.0, drift_fraction=1.0)


@pytest.fixture(scope="module")
def field_():
    return simulate_field(3, seed=5, measurements=(200, 200), dynamic_fraction=0.0, changes=ALL)


def _expected_offsets(events: list[dict], times: pd.DatetimeIndex) -> np.ndarray:
    """Offsets (N, 28) [rad] from the events' definitions (module docstring), written out here
    row by row and independently of models/changes.py: a step adds its ``parameters`` from
    ``start`` on, an episode on [start, end), a drift ``parameters`` times the years (of 365.25
    days) since ``start``."""
    out = np.zeros((len(times), len(PARAMETER_INDEX)))
    for row, t in enumerate(times):
        for e in events:
            if e["kind"] == "step":
                share = 1.0 if t >= e["start"] else 0.0
            elif e["kind"] == "episode":
                share = 1.0 if e["start"] <= t < e["end"] else 0.0
            else:
                share = max((t - e["start"]).total_seconds(), 0.0) / (365.25 * 24 * 3600)
            for name, value in e["parameters"].items():
                out[row, PARAMETER_INDEX[name]] += share * value
    return out


def test_true_parameters_follow_the_events(field_):
    meas = field_.measurements
    for hid, h in field_.heliostats.items():
        kinds = [e["kind"] for e in h.changes]
        assert {"step", "episode", "drift"} <= set(kinds), kinds  # every fraction is 1
        times = meas.loc[meas["heliostat_id"] == hid, "timestamp"]
        times = pd.DatetimeIndex(times)
        offsets = (h.params - h.true).numpy()
        for e in h.changes:
            assert e["start"] >= times.min().normalize() - np.timedelta64(1, "D")
            size = np.linalg.norm(list(e["parameters"].values())) * 1e3
            if e["kind"] == "drift":
                assert 1.0 <= e["rate_mrad_per_year"] <= 3.0
                assert size == pytest.approx(e["rate_mrad_per_year"], rel=1e-12)
            else:
                lo, hi = (1.0, 4.0) if e["kind"] == "step" else (2.0, 15.0)
                assert lo <= e["size_mrad"] <= hi
                assert size == pytest.approx(e["size_mrad"], rel=1e-12)
        # the per-measurement geometry is true + the sum of the events' offsets, nothing else
        np.testing.assert_allclose(offsets, _expected_offsets(h.changes, times), atol=1e-15)
        step = next(e for e in h.changes if e["kind"] == "step")
        name = next(iter(step["parameters"]))
        i = PARAMETER_INDEX[name]
        before = np.asarray(times < step["start"])
        others = [e for e in h.changes if e is not step]
        rest = _expected_offsets(others, times)[:, i]
        np.testing.assert_allclose(offsets[~before, i] - rest[~before], step["parameters"][name],
                                   atol=1e-15)
        np.testing.assert_allclose(offsets[before, i] - rest[before], 0.0, atol=1e-15)
        # a step of s mrad on zero points/tilts turns the normal by at most s mrad (rotation)
        assert 0.0 < step["effect_mrad"] <= step["size_mrad"] * 1.001


def test_noise_floor_is_the_changing_true_model(field_):
    # the true model includes the changes: its error is the noise (noise 0.2 mrad: Rayleigh
    # mean of the normal's noise about 0.2 / 2 * sqrt(pi / 2) = 0.125), while the static truth
    # is pulled off by the steps and episodes
    for h in field_.heliostats.values():
        assert h.noise_floor_mrad == pytest.approx(0.125, rel=0.25)
        assert h.error_true_static_mrad > 2 * h.noise_floor_mrad


def test_ground_truth_json_lists_the_events_only_when_asked(tmp_path, field_):
    write_field(field_, tmp_path / "a")
    truth = json.loads((tmp_path / "a" / "ground_truth.json").read_text())
    assert truth["settings"]["changes"]["step_fraction"] == 1.0
    for hid, h in field_.heliostats.items():
        written = truth["heliostats"][hid]["changes"]
        assert [e["kind"] for e in written] == [e["kind"] for e in h.changes]
        assert [e["start"] for e in written] == [str(e["start"].date()) for e in h.changes]
    plain = simulate_field(1, seed=5, measurements=(20, 20), dynamic_fraction=0.0)
    write_field(plain, tmp_path / "b")
    truth = json.loads((tmp_path / "b" / "ground_truth.json").read_text())
    assert "changes" not in truth["settings"]
    assert "changes" not in next(iter(truth["heliostats"].values()))


def test_changes_do_not_move_the_other_draws():
    # the changes have their own generator: the same seed gives the same schedule and geometry
    a = simulate_field(2, seed=9, measurements=(30, 30), dynamic_fraction=0.0)
    b = simulate_field(2, seed=9, measurements=(30, 30), dynamic_fraction=0.0, changes=ALL)
    assert (a.measurements["timestamp"] == b.measurements["timestamp"]).all()
    for hid in a.heliostats:
        assert torch.equal(a.heliostats[hid].true, b.heliostats[hid].true)


@pytest.mark.parametrize("kwargs", [{"step_fraction": 1.5}, {"episode_mrad": (3.0, 2.0)}])
def test_bad_changes_are_refused(kwargs):
    with pytest.raises(ParameterError, match="parameter of Changes"):
        Changes(**kwargs)
