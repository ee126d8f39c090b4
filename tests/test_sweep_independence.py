"""A heliostat's sweep results do not depend on the heliostats trained beside it (issue 36 part
3: the update trains only the heliostats whose inputs changed, so the sweep's unit of reuse is the
heliostat). The sweep stacks a chunk's networks in one batched float32 program; with the aligned
layout (``training.MEMBER_ALIGN``: rows and parameters padded to multiples of 32) every network
trains to the same bits alone, first or last in a chunk, beside shorter or longer heliostats and
in chunks of any size. Without it the last networks of a chunk fall in torch's scalar tail and a
heliostat's row reductions follow its chunk's longest heliostat; the rounding differs by an ulp
and Adam amplifies it (docs/experiments/incremental-updates.md).

The field is the bundled synthetic sample; SP13 (114 training and validation rows) and SS48 (130)
share the static-20 preset, so they train in one chunk. 17 heliostats of 2 networks are 34
networks: SP13 last puts its networks past the 32-element vector blocks of a per-network tensor.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
import torch

from heliocal.pipeline.io.staged import IngestOptions
from heliocal.pipeline.models.config import FineConfig, PathConfig, ScreenConfig
from heliocal.pipeline.models.selection import SelectionRule
from heliocal.pipeline.stages import sweep
from heliocal.pipeline.stages.fit_coarse import run_fit_coarse
from heliocal.pipeline.stages.ingest import run_ingest
from heliocal.pipeline.stages.split import run_split
from heliocal.pipeline.stages.sweep_inputs import read_sweep_inputs

SYNTH = Path(__file__).resolve().parents[1] / "sample_data" / "synthetic"

#: Chunks SP13 is trained in ("T": SP13, "M": SS48, its longer chunk-mate).
CHUNKS = {"first of two": "TM", "after a longer heliostat": "MT", "middle of five": "MMTMM",
          "first of 17": "T" + "M" * 16, "last of 17": "M" * 16 + "T"}


@pytest.fixture(scope="module")
def items(tmp_path_factory):
    wd = tmp_path_factory.mktemp("independence") / "wd"
    run_ingest([SYNTH / "calibration_log.csv"], wd,
               IngestOptions(properties=SYNTH / "paint", tower=SYNTH / "tower-measurements.json"))
    run_split(wd)
    run_fit_coarse(wd, workers=1)
    return read_sweep_inputs(wd, None)


def _sp13_results(items, chunk: str) -> tuple[pd.DataFrame, dict, dict | None]:
    """SP13's sweep rows (without ``wall_time_s``, the chunk's own timing), selection and
    selected weights when it is trained in ``chunk``. Small settings (30 epochs per weight
    decay, 2 networks per ensemble, both band sets, screen on): 60 Adam steps are enough for an
    ulp to reach the rows (tests fail without the alignment, see the module's docstring)."""
    config = FineConfig(max_epochs=30, ensemble=2)
    heliostats = [items["SP13" if c == "T" else "SS48"] for c in chunk]
    results = sweep._select_chunk(heliostats, sweep.hybrid_variants(config), [1e-2, 1e-4, 0.0],
                                  [0], PathConfig(stage_epochs=30), None, None, SelectionRule(),
                                  ScreenConfig())
    res = results[chunk.index("T")]
    rows = pd.DataFrame(res["rows"]).drop(columns="wall_time_s")
    selection = {k: v for k, v in res["selection"].items() if k != "wall_time_s"}
    state = res["selected_state"]
    return rows, selection, None if state is None else state["state"]


@pytest.mark.slow
def test_a_heliostats_sweep_results_are_the_same_bits_alone_and_in_any_chunk(items):
    torch.use_deterministic_algorithms(True, warn_only=True)   # as the sweep's tasks run
    rows, selection, state = _sp13_results(items, "T")
    assert rows["model"].str.startswith("hybrid").sum() >= 3   # networks were trained
    for name, chunk in CHUNKS.items():
        other_rows, other_selection, other_state = _sp13_results(items, chunk)
        pd.testing.assert_frame_equal(other_rows, rows, check_exact=True, obj=name)
        assert str(other_selection) == str(selection), name     # NaN-safe, every value
        assert (other_state is None) == (state is None), name
        if state is not None:
            assert sorted(other_state) == sorted(state), name
            for key, tensor in state.items():
                assert torch.equal(other_state[key], tensor), (name, key)


def test_an_update_of_a_few_heliostats_is_cut_into_a_chunk_per_worker():
    """The chunk size the sweep trains with (``sweep_increment.chunk_size``): ``batch_size`` (32)
    for a field, fewer when a few heliostats would leave a worker idle. The issue's update, 20
    heliostats on 2 workers, is 2 chunks of 10 (one chunk of 20 kept one of the 2 workers idle for
    the whole update, 44.2 s of training in docs/benchmarks.md); the results do not depend on it
    (the test above)."""
    from heliocal.pipeline.stages.sweep_increment import chunk_size

    assert chunk_size(20, 32, 2) == 10
    assert chunk_size(21, 32, 2) == 11          # ceil: 2 chunks, never 3
    assert chunk_size(200, 32, 2) == 32         # a field: batch_size
    assert chunk_size(20, 32, 1) == 20
    assert chunk_size(20, 8, 2) == 8            # never above batch_size
    assert chunk_size(1, 32, 2) == 1
    assert chunk_size(0, 32, 2) == 1            # no heliostat: a valid size all the same


def _fake_field(rows_by_group: dict) -> tuple[dict, dict, pd.DataFrame]:
    """(items, selected, helio) as :func:`sweep_chunks` reads them: per heliostat its row count,
    kinematic and actuator type and free mask (one group per key of ``rows_by_group``)."""
    from types import SimpleNamespace

    items, selected, types = {}, {}, {}
    for g, counts in rows_by_group.items():
        free = torch.tensor([True] * (20 if g == "a" else 14) + [False] * (8 if g == "a" else 14))
        for i, n in enumerate(counts):
            hid = f"{g.upper()}{i:03d}"
            items[hid] = SimpleNamespace(rows=range(n))
            selected[hid] = {"free": free}
            types[hid] = {"kinematic_type": "juelich", "actuator_type": "linear"}
    return items, selected, pd.DataFrame.from_dict(types, orient="index")


def test_chunks_are_a_whole_number_of_rounds_of_the_workers_of_equal_cost_costliest_first():
    """``sweep_chunks``: a group larger than a chunk is cut, in row-count order, into a multiple
    of the workers of consecutive pieces of about equal cost per epoch (``CHUNK_OVERHEAD_ROWS``
    + heliostats x the longest one's rows), the costliest first. The numbers: the 200-heliostat
    benchmark field's update (20 heliostats of one group with 125 to 398 rows, on 2 workers) was
    cut by bands of 100 rows into 3 chunks of 6, 7 and 7, so one of the 2 workers trained two of
    them, and 2 chunks of 10 still cost 1.4x apart (4,850 against 3,410 heliostat-rows); a
    200-heliostat field at 32 into 9 chunks (docs/benchmarks.md, "Daily updates"). Now 12 and 8
    (4,266 and 4,054), and 8 chunks."""
    from heliocal.pipeline.stages.sweep_increment import (CHUNK_OVERHEAD_ROWS, chunk_size,
                                                          sweep_chunks)

    def costs(items, chunks):
        return [CHUNK_OVERHEAD_ROWS + len(c) * len(items[c[-1]].rows) for c in chunks]

    update = [125 + (398 - 125) * i // 19 for i in range(20)]
    items, selected, helio = _fake_field({"a": update})
    chunks = sweep_chunks(items, selected, helio, 32, 2, chunk_size(20, 32, 2))
    assert [len(c) for c in chunks] == [12, 8]
    assert [len(items[h].rows) for h in chunks[0]] == update[:12]      # each in row order
    assert [len(items[h].rows) for h in chunks[1]] == update[12:]
    assert costs(items, chunks) == [870 + 12 * 283, 870 + 8 * 398] == [4266, 4054]

    field = [100 + (i * 37) % 301 for i in range(200)]                 # 100..400 rows, shuffled
    items, selected, helio = _fake_field({"a": field})
    chunks = sweep_chunks(items, selected, helio, 32, 2, chunk_size(200, 32, 2))
    assert len(chunks) == 8 and max(map(len, chunks)) <= 32            # 7 of 32 would idle one
    assert sorted(h for c in chunks for h in c) == sorted(items)       # each heliostat once
    lengths = [[len(items[h].rows) for h in c] for c in chunks]
    assert all(x == sorted(x) for x in lengths)
    ends = sorted((x[0], x[-1]) for x in lengths)
    assert all(a[1] <= b[0] for a, b in zip(ends, ends[1:]))           # consecutive row counts
    cost = costs(items, chunks)
    assert max(cost) == 8094 and sorted(cost)[2] >= 0.98 * max(cost)  # 6 of 8 within 2 %
    assert [len(c) * x[-1] for c, x in zip(chunks, lengths)] == sorted(
        (len(c) * x[-1] for c, x in zip(chunks, lengths)), reverse=True)   # costliest first

    # two groups (other free parameters never share a chunk): 3 alone, 40 at 32 -> 2 of 20
    items, selected, helio = _fake_field({"a": [150] * 40, "b": [300] * 3})
    chunks = sweep_chunks(items, selected, helio, 32, 2, chunk_size(43, 32, 2))
    assert sorted(len(c) for c in chunks) == [3, 20, 20]
    assert all(len({h[0] for h in c}) == 1 for c in chunks)
    # one worker: the fewest chunks of at most batch_size (21 at 11: 11 and 10)
    items, selected, helio = _fake_field({"a": list(range(100, 121))})
    assert [len(c) for c in sweep_chunks(items, selected, helio, 11, 1)] == [11, 10]
