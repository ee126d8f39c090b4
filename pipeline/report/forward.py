"""The report's forward-in-time views of the rolling-origin evaluation (rolling_origin.parquet):
a heliostat's next-day error against the days since its model's last calibration row, drawn
as a small inline SVG on its page (no image file, nothing to render in a worker: a field of
thousands of heliostats costs a few milliseconds per page).
"""

from __future__ import annotations

import html
import math

import numpy as np
import pandas as pd

__all__ = ["svg_next_day", "next_day_mean"]

_W, _H, _L, _B, _T, _R = 420, 220, 46, 34, 10, 12   # size and margins [px]


def next_day_mean(h: dict) -> float:
    """A heliostat's mean next-day error from metrics.json's ``forward_in_time.next_day`` [mrad];
    NaN without a rolling-origin evaluation."""
    v = (((h.get("forward_in_time") or {}).get("next_day")) or {}).get("mean_error_mrad")
    return float("nan") if v is None else float(v)


def _ticks(top: float) -> list[float]:
    """About four round ticks from 0 to ``top``."""
    if top <= 0 or not math.isfinite(top):
        return [0.0]
    step = 10 ** math.floor(math.log10(top / 4))
    for m in (1, 2, 5, 10):
        if top / (m * step) <= 5:
            step *= m
            break
    return [k * step for k in range(int(top / step) + 1)]


def svg_next_day(rows: pd.DataFrame | None) -> str | None:
    """The heliostat's rolling-origin rows as an SVG scatter: next-day error_mrad (y, up to the
    99th percentile; a red dot lies above) against the days since the fit's last row (x, on a
    log(1 + d) axis), one dot per row; None without rows."""
    if rows is None or not len(rows):
        return None
    x = rows["days_since_last_row"].to_numpy(float)
    y = rows["error_mrad"].to_numpy(float)
    ok = np.isfinite(x) & np.isfinite(y)
    if not ok.any():
        return None
    x, y = x[ok], y[ok]
    x_top = max(float(x.max()) * 1.05, 1.0)
    y_top = max(float(np.percentile(y, 99)) * 1.1, 0.1)
    # days on a log(1 + d) axis: most gaps are a day or two, a few are months
    sx = lambda v: _L + (_W - _L - _R) * math.log1p(min(v, x_top)) / math.log1p(x_top)  # noqa: E731
    sy = lambda v: _H - _B - (_H - _B - _T) * min(v, y_top) / y_top   # noqa: E731
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{_W}" height="{_H}" '
           'role="img" aria-label="next-day error against days since the last calibration row">',
           f'<rect x="{_L}" y="{_T}" width="{_W - _L - _R}" height="{_H - _B - _T}" '
           'fill="none" stroke="#999"/>']
    for t in [d for d in (0, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000) if d <= x_top]:
        out.append(f'<text x="{sx(t):.1f}" y="{_H - _B + 14}" font-size="10" '
                   f'text-anchor="middle">{t:g}</text>')
    for t in _ticks(y_top):
        out.append(f'<text x="{_L - 4}" y="{sy(t) + 3:.1f}" font-size="10" '
                   f'text-anchor="end">{t:g}</text>')
        out.append(f'<line x1="{_L}" x2="{_W - _R}" y1="{sy(t):.1f}" y2="{sy(t):.1f}" '
                   'stroke="#eee"/>')
    out.append(f'<text x="{(_L + _W - _R) / 2:.0f}" y="{_H - 4}" font-size="11" '
               'text-anchor="middle">days since the model\'s last calibration row</text>')
    out.append(f'<text x="12" y="{(_T + _H - _B) / 2:.0f}" font-size="11" text-anchor="middle" '
               f'transform="rotate(-90 12 {(_T + _H - _B) / 2:.0f})">next-day error [mrad]</text>')
    for xv, yv in zip(x, y):
        clipped = yv > y_top
        out.append(f'<circle cx="{sx(xv):.1f}" cy="{sy(yv):.1f}" r="2.5" '
                   f'fill="{"#c33" if clipped else "#36c"}" fill-opacity="0.6">'
                   f'<title>{html.escape(f"{xv:.1f} d, {yv:.3f} mrad")}</title></circle>')
    return "".join(out) + "</svg>"
