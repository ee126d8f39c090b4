"""Structural comparison of generated files with committed golden copies.

A golden file (``sample_data/synthetic`` written by ``heliocal simulate``, say) is a check of the
*science*: the same keys, columns, row order, strings and, within a tolerance, the same numbers.
Comparing bytes instead breaks whenever numpy, pandas or scipy change a summation order or the
shortest round-trip repr of a float, although nothing physical changed (``5.931404151891251`` vs
``5.93140415189125``).

:func:`compare_trees` compares two folders file by file and returns one readable line per
difference (an empty list means equal):

* the same relative file names;
* ``.json``: the same structure (object keys in the same order, arrays of the same length), equal
  strings, booleans and nulls, equal integers, and floats within tolerance;
* ``.csv``: the same header, the same number of rows in the same order, the same dtype per column
  as pandas infers it, equal text and integer columns, float columns within tolerance (NaN where
  the golden copy has NaN);
* any other file: equal bytes.

The tolerance is ``|a - b| <= rel * max(|a|, |b|) + abs_``, default ``rel = 1e-9`` and
``abs_ = 1e-12``. Float64 carries about 16 significant digits; a library update that reorders a sum
or changes a transcendental function moves a result that went through a few thousand operations by
about 1e-15 to 1e-12 relative, so 1e-9 leaves three orders of magnitude of margin above that noise,
while the smallest physical change we care about in these files (0.001 mrad on a milliradian
quantity, a millimetre on a position of tens of metres) is 1e-6 relative or more and is caught.
``abs_`` only matters for values that are zero in one copy and rounding noise in the other.
"""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import pandas as pd

__all__ = ["DEFAULT_REL", "DEFAULT_ABS", "close", "compare_json", "compare_csv", "compare_trees"]

DEFAULT_REL = 1e-9  #: relative tolerance for floats [1]; reasoning in the module docstring
DEFAULT_ABS = 1e-12  #: absolute tolerance for floats that are zero in one copy [unit of the value]


def close(a: float, b: float, rel: float = DEFAULT_REL, abs_: float = DEFAULT_ABS) -> bool:
    """True when two floats agree within ``rel * max(|a|, |b|) + abs_`` (NaN equals NaN)."""
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    if math.isinf(a) or math.isinf(b):
        return a == b
    return abs(a - b) <= rel * max(abs(a), abs(b)) + abs_


def _short(value, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 5] + " ...]"


def _kind(value) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "float"
    if isinstance(value, str):
        return "str"
    if value is None:
        return "null"
    if isinstance(value, list):
        return "array"
    if isinstance(value, dict):
        return "object"
    return type(value).__name__


def compare_json(current, golden, *, rel: float = DEFAULT_REL, abs_: float = DEFAULT_ABS,
                 where: str = "$") -> list[str]:
    """Differences between two parsed JSON documents, one line each (``where`` is a JSON path)."""
    kc, kg = _kind(current), _kind(golden)
    if kc != kg:  # an int that became a float is a change of type, not of rounding
        return [f"{where}: {kg} in the golden copy, {kc} now"]
    if kg == "object":
        if list(current) != list(golden):
            return [f"{where}: keys {_short(list(golden))} in the golden copy, "
                    f"{_short(list(current))} now"]
        out: list[str] = []
        for key in golden:
            out += compare_json(current[key], golden[key], rel=rel, abs_=abs_, where=f"{where}.{key}")
        return out
    if kg == "array":
        if len(current) != len(golden):
            return [f"{where}: {len(golden)} items in the golden copy, {len(current)} now"]
        out = []
        for i, (c, g) in enumerate(zip(current, golden)):
            out += compare_json(c, g, rel=rel, abs_=abs_, where=f"{where}[{i}]")
        return out
    if kg == "float":
        if not close(current, golden, rel, abs_):
            return [f"{where}: {golden!r} in the golden copy, {current!r} now (tolerance rel {rel:g})"]
        return []
    if current != golden:
        return [f"{where}: {_short(golden)} in the golden copy, {_short(current)} now"]
    return []


def compare_csv(current: bytes, golden: bytes, *, rel: float = DEFAULT_REL,
                abs_: float = DEFAULT_ABS, name: str = "csv") -> list[str]:
    """Differences between two CSV files' contents (header, row order, dtypes, values)."""
    cur = pd.read_csv(io.BytesIO(current), keep_default_na=False, na_values=["", "NaN", "nan"])
    gold = pd.read_csv(io.BytesIO(golden), keep_default_na=False, na_values=["", "NaN", "nan"])
    if list(cur.columns) != list(gold.columns):
        return [f"{name}: columns {_short(list(gold.columns))} in the golden copy, "
                f"{_short(list(cur.columns))} now"]
    if len(cur) != len(gold):
        return [f"{name}: {len(gold)} rows in the golden copy, {len(cur)} now"]
    out: list[str] = []
    for column in gold.columns:
        g, c = gold[column], cur[column]
        if str(g.dtype) != str(c.dtype):
            out.append(f"{name}[{column}]: dtype {g.dtype} in the golden copy, {c.dtype} now")
            continue
        if pd.api.types.is_float_dtype(g.dtype):
            for row, (cv, gv) in enumerate(zip(c.to_numpy(), g.to_numpy())):
                if not close(float(cv), float(gv), rel, abs_):
                    out.append(f"{name}[{column}] row {row}: {gv!r} in the golden copy, {cv!r} now "
                               f"(tolerance rel {rel:g})")
                    break
        else:
            unequal = (c.astype(str) != g.astype(str)).to_numpy().nonzero()[0]
            if len(unequal):
                row = int(unequal[0])
                out.append(f"{name}[{column}] row {row}: {g.iloc[row]!r} in the golden copy, "
                           f"{c.iloc[row]!r} now")
    return out


def _files(folder: Path) -> dict[str, Path]:
    return {p.relative_to(folder).as_posix(): p for p in sorted(folder.rglob("*")) if p.is_file()}


def compare_trees(current_dir: Path, golden_dir: Path, *, rel: float = DEFAULT_REL,
                  abs_: float = DEFAULT_ABS) -> list[str]:
    """Differences between a generated folder and its golden copy, one readable line each."""
    cur, gold = _files(Path(current_dir)), _files(Path(golden_dir))
    out = [f"{n}: only in the golden copy" for n in sorted(set(gold) - set(cur))]
    out += [f"{n}: not in the golden copy" for n in sorted(set(cur) - set(gold))]
    for name in sorted(set(cur) & set(gold)):
        c, g = cur[name].read_bytes(), gold[name].read_bytes()
        if c == g:
            continue
        suffix = Path(name).suffix.lower()
        if suffix == ".json":
            out += compare_json(json.loads(c), json.loads(g), rel=rel, abs_=abs_, where=name)
        elif suffix == ".csv":
            out += compare_csv(c, g, rel=rel, abs_=abs_, name=name)
        else:
            out.append(f"{name}: bytes differ")
    return out
