"""The CLI's one number format of its result tables (cli/app.py fmt_number)."""

from __future__ import annotations

import math

from heliocal.cli.app import fmt_number


def test_fmt_number_rounds_to_the_given_decimals_and_marks_missing_values():
    """Expected strings written out by hand: three decimals by default (error tables in mrad),
    two for split-knn's distances in degrees; a missing value (None, NaN, as a summary carries
    one for a split without rows) prints as '-', never 'nan'."""
    assert fmt_number(1.23456) == "1.235"
    assert fmt_number(0.5, 2) == "0.50"
    assert fmt_number(-0.0004) == "-0.000"
    assert fmt_number(None) == "-"
    assert fmt_number(math.nan) == "-"
    assert fmt_number(float("nan"), 2) == "-"
