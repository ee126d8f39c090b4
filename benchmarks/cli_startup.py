"""Benchmark: how fast the ``heliocal`` command answers when it has no work to do.

Times, each in a fresh process (the console script of the active environment), the median wall
time of ``heliocal --help``, ``heliocal fit-hybrid --help`` and a usage error (an unknown option:
exit 2), and which heavy libraries the CLI imports before any command runs. Usage::

    flock /tmp/heliocal-heavy.lock .venv/bin/python benchmarks/cli_startup.py [--repeats 5]

The target of issue 19: every median under 0.3 s, and none of torch, sklearn, matplotlib, pandas,
scipy, dask imported by ``import heliocal.cli.main``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

HEAVY = ("torch", "sklearn", "matplotlib", "pandas", "scipy", "dask", "pyarrow", "pvlib")
CASES = {
    "heliocal --help": ["--help"],
    "heliocal fit-hybrid --help": ["fit-hybrid", "--help"],
    "usage error (unknown option)": ["split-knn", "--no-such-option"],
}


def _console_script() -> str:
    script = Path(sys.executable).with_name("heliocal")
    if not script.exists():
        sys.exit(f"Error: {script} not found; run `make install` first")
    return str(script)


def _median_seconds(argv: list[str], repeats: int) -> tuple[float, int]:
    times, code = [], 0
    for _ in range(repeats):
        start = time.perf_counter()
        code = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
        times.append(time.perf_counter() - start)
    return statistics.median(times), code


def _heavy_imports() -> list[str]:
    probe = ("import sys, json; import heliocal.cli.main; "
             f"print(json.dumps(sorted(m for m in {list(HEAVY)!r} if m in sys.modules)))")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    script = _console_script()
    print(f"heliocal CLI start-up, median of {args.repeats} fresh processes")
    for label, argv in CASES.items():
        median, code = _median_seconds([script, *argv], args.repeats)
        print(f"  {label:<32} {median:6.3f} s  (exit {code})")
    print(f"  heavy libraries imported by heliocal.cli.main: {', '.join(_heavy_imports()) or 'none'}")


if __name__ == "__main__":
    main()
