"""Where `make install` finds the locked CPU build of torch (Makefile TORCH_WHEELS / TORCH_INDEX,
.ci/torch_index.py): the local folder when it holds the wheel, else PyTorch's CPU index, and a
clear error naming the fix when neither can give it. Nothing here installs anything: `make -n`
prints the recipe, and the one real `make install` stops at the check, before the venv."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYTORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="needs GNU make")


def _torch_pin() -> str:
    """The locked torch version, read from requirements.lock here (independently of make)."""
    text = (ROOT / "requirements.lock").read_text(encoding="utf-8")
    return re.search(r"^torch==(\S+)", text, re.M).group(1)


def _wheel_name() -> str:
    tag = f"cp{sys.version_info.major}{sys.version_info.minor}"
    return f"torch-{_torch_pin()}-{tag}-{tag}-manylinux_2_28_x86_64.whl"


def _make(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["make", "--no-print-directory", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


def _pip_line(recipe: str) -> str:
    return next(line for line in recipe.splitlines() if "pip install --quiet --require-hashes" in line)


def test_a_folder_with_the_wheel_is_used_and_no_index_is_asked(tmp_path):
    """TORCH_WHEELS holds a file named like the locked wheel: pip gets --find-links to it, no
    index and no reachability check; the lock's own --find-links line is left out."""
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    (wheels / _wheel_name()).write_bytes(b"")
    out = _make("-n", "install", f"VENV={tmp_path / 'venv'}", f"TORCH_WHEELS={wheels}")
    assert out.returncode == 0, out.stderr
    pip = _pip_line(out.stdout)
    assert f"--find-links {wheels} " in pip and "--extra-index-url" not in pip
    assert "torch_index.py" not in out.stdout
    assert f"grep -v '^--find-links' requirements.lock > {tmp_path / 'venv'}/requirements.lock" \
        in out.stdout
    assert pip.endswith(f"-r {tmp_path / 'venv'}/requirements.lock")


@pytest.mark.parametrize("folder", ["empty", "missing"])
def test_without_the_wheel_pytorchs_cpu_index_is_used_after_a_check(tmp_path, folder):
    """An empty or missing TORCH_WHEELS: pip gets PyTorch's CPU index as an extra index (the
    lock's hash still decides which file is accepted), after .ci/torch_index.py has checked the
    index serves the wheel."""
    wheels = tmp_path / "wheels"
    if folder == "empty":
        wheels.mkdir()
    out = _make("-n", "install", f"VENV={tmp_path / 'venv'}", f"TORCH_WHEELS={wheels}")
    assert out.returncode == 0, out.stderr
    pip = _pip_line(out.stdout)
    assert f"--extra-index-url {PYTORCH_CPU_INDEX} " in pip and "--find-links" not in pip
    lines = out.stdout.splitlines()
    check = lines.index(f"python3 .ci/torch_index.py {PYTORCH_CPU_INDEX} {_torch_pin()} {wheels}")
    assert check < next(i for i, line in enumerate(lines) if line.startswith("rm -rf"))


def test_an_unreachable_index_stops_make_install_with_the_fix_before_the_venv(tmp_path):
    """No wheel in TORCH_WHEELS and an index that cannot be reached (a folder that does not
    exist, as file: URL): `make install` fails with one Error line naming both fixes, and the
    venv was not even started."""
    venv = tmp_path / "venv"
    out = _make("install", f"VENV={venv}", f"TORCH_WHEELS={tmp_path / 'none'}",
                f"TORCH_INDEX=file://{tmp_path / 'no-index'}")
    assert out.returncode != 0
    errors = [line for line in out.stderr.splitlines() if line.startswith("Error:")]
    assert len(errors) == 1
    assert errors[0].startswith(
        f"Error: make install needs the CPU wheel of torch {_torch_pin()} that requirements.lock "
        f"pins by SHA-256; TORCH_WHEELS={tmp_path / 'none'} holds no copy and "
        f"file://{tmp_path / 'no-index'}/torch/ cannot be reached (")
    assert errors[0].endswith(
        f"Download {_wheel_name()} from {PYTORCH_CPU_INDEX}/torch/ into a folder and run "
        "`make install TORCH_WHEELS=<that folder>`, or set TORCH_INDEX to a mirror of PyTorch's "
        "CPU index.")
    assert not venv.exists()


def test_the_index_check_wants_this_pythons_wheel_of_the_locked_version(tmp_path):
    """A local mirror of the index (a folder per project with an index.html, as pip reads it)
    that lists the locked wheel passes; one listing only another version does not."""
    index = tmp_path / "index"
    (index / "torch").mkdir(parents=True)
    page = index / "torch" / "index.html"
    script = [sys.executable, str(ROOT / ".ci" / "torch_index.py"), f"file://{index}",
              _torch_pin(), str(tmp_path / "wheels")]
    page.write_text(f'<a href="../../{_wheel_name().replace("+", "%2B")}#sha256=00">x</a>')
    assert subprocess.run(script, capture_output=True, text=True).returncode == 0
    page.write_text('<a href="torch-2.12.0%2Bcpu-cp311-cp311-manylinux_2_28_x86_64.whl">x</a>')
    out = subprocess.run(script, capture_output=True, text=True)
    assert out.returncode == 1
    assert f"{index}/torch/ lists no {_wheel_name().rsplit('-', 1)[0]}-*.whl" in out.stderr
