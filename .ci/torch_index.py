"""Check, before ``make install`` builds the venv, that PyTorch's wheel index serves the locked
CPU build of torch for this Python, and say what to do when it cannot be reached.

    python .ci/torch_index.py INDEX VERSION WHEELS

``make install`` runs it only when the folder ``TORCH_WHEELS`` holds no copy of the wheel (then
pip is to fetch it from ``INDEX``, PyTorch's CPU index by default); pip checks the wheel against
the SHA-256 of requirements.lock either way. Exit 0 when ``INDEX/torch/`` lists
``torch-VERSION-cpXY-cpXY-...``, else 1 with one ``Error: ...`` line on stderr naming both ways
to fix it.
"""

from __future__ import annotations

import sys
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

TIMEOUT_S = 30


def wheel_prefix(version: str) -> str:
    """The start of the wheel's file name for this interpreter, e.g. torch-2.13.0+cpu-cp311-cp311."""
    tag = f"cp{sys.version_info.major}{sys.version_info.minor}"
    return f"torch-{version}-{tag}-{tag}"


def _read(url: str) -> str:
    """The index page of ``url``; a local mirror (file:) is a folder with an index.html, as pip
    reads it."""
    parsed = urllib.parse.urlparse(url)
    if parsed.scheme == "file":
        folder = Path(urllib.request.url2pathname(parsed.path))
        return (folder / "index.html").read_text(encoding="utf-8", errors="replace")
    with urllib.request.urlopen(url, timeout=TIMEOUT_S) as response:
        return response.read().decode("utf-8", "replace")


def problem(index: str, version: str) -> str | None:
    """Why ``index`` does not serve the wheel (None if it does)."""
    url = index.rstrip("/") + "/torch/"
    try:
        page = urllib.parse.unquote(_read(url))
    except (urllib.error.URLError, OSError, ValueError) as exc:
        return f"{url} cannot be reached ({getattr(exc, 'reason', exc)})"
    if wheel_prefix(version) not in page:
        return f"{url} lists no {wheel_prefix(version)}-*.whl (is this Python 3.11?)"
    return None


def main(argv: list[str]) -> int:
    index, version, wheels = argv
    why = problem(index, version)
    if why is None:
        return 0
    name = f"{wheel_prefix(version)}-manylinux_2_28_x86_64.whl"
    print(f"Error: make install needs the CPU wheel of torch {version} that requirements.lock "
          f"pins by SHA-256; TORCH_WHEELS={wheels} holds no copy and {why}. Download {name} "
          f"from https://download.pytorch.org/whl/cpu/torch/ into a folder and run "
          f"`make install TORCH_WHEELS=<that folder>`, or set TORCH_INDEX to a mirror of "
          f"PyTorch's CPU index.", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
