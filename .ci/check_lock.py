"""Check that the running environment holds exactly the versions of a lock file.

    python .ci/check_lock.py requirements.lock            # exit 1 on any difference
    python .ci/check_lock.py requirements.lock --report   # print the installed versions, exit 0

Compares the ``name==version`` pins of the lock (as written by ``uv pip compile``) with the
distributions installed in this interpreter's environment, skipping heliocal itself (installed
from the checkout) and pip (the venv's own bootstrap, not a dependency). Names are compared in
their normalised form (PEP 503). Used by ``make install`` after installing from the lock, and by
``make test-latest`` to list what drifted.
"""

from __future__ import annotations

import argparse
import re
import sys
from importlib import metadata

SKIP = {"heliocal", "pip"}
PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)(?:\[[^\]]*\])?==([^\s;\\]+)")


def normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def locked(path: str) -> dict[str, str]:
    pins = {}
    with open(path, encoding="utf-8") as handle:
        for line in handle:
            match = PIN.match(line.strip())
            if match:
                pins[normalise(match.group(1))] = match.group(2)
    return pins


def installed() -> dict[str, str]:
    return {normalise(d.metadata["Name"]): d.version for d in metadata.distributions()
            if d.metadata["Name"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("lock")
    parser.add_argument("--report", action="store_true",
                        help="print every installed version and how it differs; always exit 0")
    args = parser.parse_args(argv)
    want = {k: v for k, v in locked(args.lock).items() if k not in SKIP}
    have = {k: v for k, v in installed().items() if k not in SKIP}
    if not want:
        print(f"check_lock: no pins found in {args.lock}", file=sys.stderr)
        return 2
    problems = [f"{n}: locked {want[n]}, installed {have[n]}" for n in sorted(want)
                if n in have and have[n] != want[n]]
    problems += [f"{n}: locked {want[n]}, not installed" for n in sorted(set(want) - set(have))]
    problems += [f"{n}: installed {have[n]}, not in the lock" for n in sorted(set(have) - set(want))]
    if args.report:
        for name in sorted(have):
            print(f"{name}=={have[name]}")
        for line in problems:
            print(f"  differs from the lock: {line}", file=sys.stderr)
        return 0
    if problems:
        for line in problems:
            print(f"check_lock: {line}", file=sys.stderr)
        print(f"check_lock: the environment differs from {args.lock} in {len(problems)} package(s); "
              f"remove it and run 'make install'", file=sys.stderr)
        return 1
    print(f"check_lock: {len(want)} packages match {args.lock} exactly", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
