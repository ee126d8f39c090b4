"""What ``fit-coarse --incremental`` computes again, and the previous rows it keeps
(:mod:`heliocal.pipeline.artifacts.incremental` holds the digests and the plan).

A heliostat's coarse fits, regimes, regime-aware candidates and rolling origins are computed from
its own rows (measurements with its split and time-split labels), its heliostats.parquet row and
the field prior it is given (``--prior field``: estimated from the other heliostats' fits, so it
moves when theirs do; ``--prior-from``: another work directory's, fixed), so those three are its
inputs. The prior is estimated again on every run (from at most
:data:`~.coarse_prior.SAMPLE_SIZE` heliostats per group, most rows first); a heliostat whose prior
did not move, and whose rows did not, is kept. The batched solver stacks heliostats of one type in chunks; which heliostats share a
chunk changes the floating-point rounding of a fit, never its model, so a heliostat fitted in
another chunk agrees with a full run's fit to the solver's convergence tolerance, not bit for bit
(the incremental test states the tolerance).
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from ..artifacts.incremental import (Increment, field_key, heliostat_digests, plan_increment,
                                     reused_rows)
from ..artifacts.manifests import current_transaction
from ..artifacts.store import read_artifact
from ..artifacts.table import ArtifactSchema
from ..errors import ParameterError

__all__ = ["coarse_plan", "with_previous"]


def coarse_plan(workdir: Path, helio: pd.DataFrame, rows_of: dict, options: dict,
                incremental: bool, heliostats, priors: pd.DataFrame) -> Increment | None:
    """The plan of a ``fit-coarse`` run over ``rows_of`` (heliostat -> its rows as it fits
    them; ``helio``: heliostats.parquet indexed by id; ``priors``: the field prior each is given,
    :func:`~.coarse_prior.prior_frame`). A run restricted to ``heliostats`` records no digests
    (they would cover part of the field) and cannot be incremental."""
    if heliostats:
        if incremental:
            raise ParameterError("--incremental works out itself which heliostats to fit again; "
                                 "leave out --heliostat, or leave out --incremental")
        return None
    ids = sorted(rows_of)
    rows = pd.concat([rows_of[h] for h in ids], ignore_index=True)
    props = helio.loc[ids].reset_index(drop=True)
    frames = [rows, props, priors]
    return plan_increment(current_transaction(workdir, "fit-coarse"),
                          field_key("fit-coarse", options, frames),
                          heliostat_digests(frames), incremental)


def with_previous(workdir: Path, schema: ArtifactSchema, new: pd.DataFrame,
                  plan: Increment | None) -> pd.DataFrame:
    """``new`` (this run's rows) plus the previous committed rows of the heliostats ``plan``
    reuses."""
    if plan is None or not plan.partial:
        return new
    kept = reused_rows(read_artifact(workdir, schema), plan.reuse)
    parts = [p for p in (kept, new) if len(p)]
    if not parts:
        return new
    return pd.concat(parts, ignore_index=True) if len(parts) > 1 else parts[0]
