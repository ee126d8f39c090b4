"""Every shell command in README.md, sample_data/README.md and docs/*.md runs as documented.

The commands of every ```sh block are taken from the files in that order (README first, since
the docs' examples read the work directory its `make sample` makes), one line per command
(backslash continuations joined), and run with bash in a sandbox: a temporary directory holding
copies of ``sample_data/`` and ``tests/baseline/`` (commands may write there, e.g. the baseline
regeneration in docs/report.md) and links to the Makefile, the code and ``.venv``, with
``.venv/bin`` first on PATH. Each must exit with 0. The commands that genuinely cannot run here
are listed in NOT_RUN with the reason; a test keeps that list short and current.

The commands form *chains*, one per work directory (:func:`chain_of`): `make sample` and every
later command on ``runs/sample``, the simulated field on ``runs/simulated``, ... Each chain runs
in order in a sandbox of its own, as a test class of its own (a unit of work of ``pytest -n 2
--dist loadscope``), so that chains run side by side, each in order.

The README's typical run is the list of commands `make sample` runs: those lines are not run a
second time after `make sample` (the chain's first command), and a test checks that they are
exactly what the Makefile runs (``make -n``), option for option.

A second, quick test checks the command lines that are not run (NOT_RUN, usage synopses in
plain ``` blocks, commands quoted inline in the text): every ``--option`` they name exists on
that heliocal subcommand.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", ROOT / "sample_data" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]

#: Commands of ```sh blocks that are not run, with the reason.
NOT_RUN = {
    "make test": "runs this test suite itself",
    "dask scheduler --port 8786": "starts a Dask scheduler that serves until stopped (head node of "
                                  "a cluster)",
    "dask worker tcp://HEAD:8786 --nworkers 16 --nthreads 1":
        "needs the scheduler on the machine HEAD of a cluster",
    "heliocal fit-coarse --workdir runs/field --preset static-20 --dask-address tcp://HEAD:8786":
        "needs that cluster and a field's work directory",
    "heliocal fit-hybrid --workdir runs/field --weight-decay 1e-3 --dask-address tcp://HEAD:8786":
        "needs that cluster and a field's work directory",
}


def _blocks(path: Path, language: str | None) -> list[tuple[int, str]]:
    """(line number, text) of the lines of fenced blocks of ``language`` (None: no language)."""
    out, fence = [], None
    for no, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
        m = re.match(r"^(`{3,})\s*(\S*)", line)
        if m and fence is None:
            fence = (m.group(1), m.group(2) or None)
            continue
        if m and fence is not None and line.strip() == fence[0]:
            fence = None
            continue
        if fence is not None and fence[1] == language:
            out.append((no, line))
    return out


def shell_commands(path: Path) -> list[tuple[str, int, str]]:
    """(file, line, command) of every command in ``path``'s ```sh blocks."""
    return [c[:3] for c in _shell_commands_with_blocks(path)]


def _shell_commands_with_blocks(path: Path) -> list[tuple[str, int, str, int]]:
    """(file, line, command, line of its block's first command) of ``path``'s ```sh blocks."""
    commands, pending, start, block, previous = [], "", 0, 0, -1
    for no, line in _blocks(path, "sh"):
        text = line.rstrip()
        if no != previous + 1:
            block = no  # a new fenced block (a block's lines are consecutive)
        previous = no
        if not pending and (not text.strip() or text.lstrip().startswith("#")):
            continue
        if not pending:
            start = no
        if text.endswith("\\"):
            pending += text[:-1] + " "
            continue
        commands.append((str(path.relative_to(ROOT)), start, (pending + text).strip(), block))
        pending = ""
    return commands


def _work_directory(command: str) -> str | None:
    """The work directory or output folder a command names: ``--workdir``/``--out`` or a path
    under ``runs/``; ``make sample`` works in the Makefile's WORKDIR, runs/sample."""
    if re.match(r"make\s+sample\b", command):
        return "runs/sample"
    m = re.search(r"--(?:workdir|out)[= ](\S+)", command) or re.search(r"\b(runs/[^\s/]+)", command)
    return m.group(1) if m else None


def chain_of(commands: list[tuple[str, int, str, int]]) -> list[str]:
    """The chain of each command: the work directory the first command of its ```sh block names
    (a block is run in order: input_formats.md's ingest reads what the simulate before it
    wrote), else its file's name."""
    first: dict[tuple[str, int], str] = {}
    out = []
    for source, _, command, block in commands:
        key = (source, block)
        if key not in first:
            first[key] = _work_directory(_strip_comment(command)) or source
        out.append(first[key])
    return out


def _strip_comment(command: str) -> str:
    return re.sub(r"\s+#.*$", "", command).strip()


def make_sample_commands() -> list[str]:
    """The heliocal commands `make sample` runs, as a user types them: the Makefile's recipes as
    ``make -n -B`` prints them (nothing runs), without the venv's path and ``--quiet``."""
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS")}
    proc = subprocess.run(["make", "-n", "-B", "sample"], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return [re.sub(r"\s+--quiet\b", "", line.removeprefix(".venv/bin/"))
            for line in proc.stdout.splitlines() if line.startswith(".venv/bin/heliocal ")]


_WITH_BLOCKS = [c for p in DOCS for c in _shell_commands_with_blocks(p)]
COMMANDS = [c[:3] for c in _WITH_BLOCKS]
CHAINS = chain_of(_WITH_BLOCKS)


def test_commands_are_found_and_the_not_run_list_is_short_and_current():
    texts = [_strip_comment(c) for _, _, c in COMMANDS]
    assert len(texts) >= 20, texts
    assert len(NOT_RUN) <= 6
    assert all(key in texts for key in NOT_RUN), [k for k in NOT_RUN if k not in texts]
    assert all(reason for reason in NOT_RUN.values())


def test_chains_keep_each_work_directory_in_one_order():
    """make sample and the commands on runs/sample (the README's typical run among them) are one
    chain that starts with make sample, and a block is never split (input_formats.md ingests what
    its simulate wrote)."""
    runs = [(command, chain) for (_, _, command), chain in zip(COMMANDS, CHAINS)]
    assert {c for command, c in runs if command == "make sample"} == {"runs/sample"}
    assert {c for command, c in runs if "runs/sample" in command} == {"runs/sample"}
    assert [command for command, c in runs if c == "runs/sample"][0] == "make sample"
    simulated = [c for command, c in runs if "runs/simulated" in command]
    assert len(simulated) >= 2 and set(simulated) == {"runs/simulated"}


#: The README's typical run: the commands `make sample` runs (checked below), not run again.
MADE_BY_MAKE_SAMPLE = make_sample_commands()


def test_readme_typical_run_is_what_make_sample_runs():
    """The README's typical run lists, in order, exactly the stage commands of `make sample`
    (ingest, split-knn, fit-coarse, sweep, report; from the Makefile's recipes), so running
    `make sample` runs each of its lines as documented."""
    readme = [_strip_comment(c) for s, _, c in COMMANDS if s == "README.md"]
    assert [c.split()[1] for c in MADE_BY_MAKE_SAMPLE] == [
        "ingest", "split-knn", "fit-coarse", "sweep", "report"]
    start = readme.index(MADE_BY_MAKE_SAMPLE[0])
    assert readme[start:start + len(MADE_BY_MAKE_SAMPLE)] == MADE_BY_MAKE_SAMPLE
    assert readme.index("make sample") < start


@pytest.fixture(scope="module")
def sandboxes(tmp_path_factory):
    """A sandbox per chain (made when the chain's first command runs)."""
    boxes: dict[str, dict] = {}

    def get(chain: str) -> dict:
        if chain not in boxes:
            boxes[chain] = _sandbox(tmp_path_factory)
        return boxes[chain]

    return get


def _sandbox(tmp_path_factory) -> dict:
    """The temporary directory the commands run in, and their environment."""
    box = tmp_path_factory.mktemp("docs")
    shutil.copytree(ROOT / "sample_data", box / "sample_data")
    shutil.copytree(ROOT / "tests" / "baseline", box / "tests" / "baseline")
    for name in (".venv", "Makefile", "pipeline", "cli", "pyproject.toml", "requirements.lock"):
        (box / name).symlink_to(ROOT / name)
    env = dict(os.environ, PATH=f"{ROOT / '.venv' / 'bin'}{os.pathsep}{os.environ.get('PATH', '')}")
    env.pop("MAKEFLAGS", None)
    env.pop("MAKELEVEL", None)
    # `make sample` must not reinstall the venv: it has to be up to date with the lock
    fresh = subprocess.run(["make", "-q", ".venv/.installed"], cwd=box, env=env,
                           capture_output=True, text=True)
    assert fresh.returncode == 0, ("the venv is older than requirements.lock or pyproject.toml: "
                                   "run `make install` first")
    return {"dir": box, "env": env, "seconds": {}}


def _chain_class(chain: str) -> type:
    """A test class running the commands of ``chain`` in order (a class is its own unit of work
    for ``pytest -n 2 --dist loadscope``, so two chains can run on two workers)."""

    @pytest.mark.slow
    @pytest.mark.parametrize("source,line,command", [
        pytest.param(s, n, c, id=f"{s}:{n}") for (s, n, c), ch in zip(COMMANDS, CHAINS)
        if ch == chain])
    def test_documented_command_runs(self, sandboxes, source, line, command):
        if _strip_comment(command) in NOT_RUN:
            pytest.skip(f"not run: {NOT_RUN[_strip_comment(command)]}")
        if chain == "runs/sample" and _strip_comment(command) in MADE_BY_MAKE_SAMPLE:
            pytest.skip("run by `make sample`, this chain's first command "
                        "(test_readme_typical_run_is_what_make_sample_runs)")
        sandbox = sandboxes(chain)
        t0 = time.monotonic()
        proc = subprocess.run(["bash", "-c", command], cwd=sandbox["dir"], env=sandbox["env"],
                              capture_output=True, text=True, timeout=900)
        sandbox["seconds"][f"{source}:{line}"] = time.monotonic() - t0
        assert proc.returncode == 0, (
            f"{source}:{line}: `{command}` exited with {proc.returncode}\n"
            f"stdout: {proc.stdout[-2000:]}\nstderr: {proc.stderr[-3000:]}")

    name = "TestChain_" + re.sub(r"\W", "_", chain)
    return type(name, (), {"__doc__": f"The documented commands on {chain}, in order.",
                           "test_documented_command_runs": test_documented_command_runs})


for _chain in dict.fromkeys(CHAINS):
    _cls = _chain_class(_chain)
    globals()[_cls.__name__] = _cls


# ------------------------------------------------------------------------------------------------
# options of the command lines that are not run
# ------------------------------------------------------------------------------------------------
def _heliocal_lines() -> list[tuple[str, str]]:
    """(where, command line) of heliocal commands that are not run: NOT_RUN entries, usage
    synopses in plain ``` blocks (continuation lines joined) and inline `heliocal ...` quotes."""
    out = [(f"NOT_RUN {k}", k) for k in NOT_RUN if k.startswith("heliocal ")]
    for path in DOCS:
        rel = str(path.relative_to(ROOT))
        current = None
        for no, line in _blocks(path, None):
            if line.startswith("heliocal "):
                current = [f"{rel}:{no}", line]
                out.append(current)
            elif current is not None and line.startswith(" ") and line.strip().startswith("["):
                current[1] += " " + line.strip()
            else:
                current = None
        text = path.read_text(encoding="utf-8")
        for m in re.finditer(r"`(heliocal [^`]+)`", text):
            out.append((f"{rel}:{text.count(chr(10), 0, m.start()) + 1}", m.group(1)))
    return [(w, c) for w, c in out]


def test_every_quoted_option_exists():
    import typer.main

    from heliocal.cli.main import app

    group = typer.main.get_command(app)
    checked = 0
    lines = [(where, part.strip()) for where, line in _heliocal_lines()
             for part in re.split(r"&&|;|\|\|", line)]   # each command of a chain on its own
    for where, line in lines:
        words = line.replace("\\|", "|").split()
        if len(words) < 2 or words[1] not in group.commands:
            continue
        command = group.commands[words[1]]
        known = {o for p in command.params for o in (*p.opts, *p.secondary_opts)}
        used = set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", line))
        missing = sorted(used - known)
        assert not missing, f"{where}: `{line}` names {missing}, not options of heliocal {words[1]}"
        checked += 1
    assert checked >= 30
