"""``heliocal info PATH``: the provenance of an artifact, or the artifacts of a work directory.

For a Parquet artifact it prints what pipeline/artifacts.py recorded in the file's metadata
(schema version, stage, heliocal version and git revision, command, resolved options, seed and
the fingerprint of every input the run read), its rows and columns, the run that committed it
(from ``<stage>.manifest.json``, see pipeline/transaction.py) and whether each input is still the
one it was made from (*freshness*). For a work directory it lists every artifact with its stage,
run, rows and freshness; every committed run with its files (each verified against the manifest's
SHA-256); a commit that was interrupted after its commit point; and the leftovers of runs that
stopped before their commit (no stage reads them).

``--json`` prints the same as one JSON document. A file that is not a heliocal artifact gives one
line ``Error: ...`` and exit code 1.

The gathering functions (:func:`describe_artifact`, :func:`describe_workdir`) return plain
dictionaries; only :func:`info_cmd` and the ``_print_*`` helpers format them.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich import box
from rich.table import Table
from rich.text import Text

from heliocal.cli.app import JsonFlag, command, emit, stdout
from heliocal.pipeline.artifacts.audit import hostile_entries
from heliocal.pipeline.artifacts.paths import file_sha256, kind_of
from heliocal.pipeline.errors import HeliocalError, InputError, SchemaError
from heliocal.pipeline.artifacts.workdir_lock import lock_holder
from heliocal.pipeline.artifacts.manifests import all_manifests, verify_files
from heliocal.pipeline.artifacts.leftovers import (leftovers, stale_staging_folders,
                                                   staging_in_use)
from heliocal.pipeline.artifacts.transaction import pending_commits

if TYPE_CHECKING:
    import pyarrow.parquet as pq

__all__ = ["info_cmd", "describe_artifact", "describe_workdir"]

_SOURCE_PREFIX = "source:"  # ingest records each source as "source:<path as given>"


# ------------------------------------------------------------------------------------------------
# gathering (plain data)
# ------------------------------------------------------------------------------------------------
def _schemas_by_name() -> dict:
    from heliocal.pipeline.artifacts.schemas import all_schemas

    return {s.name: s for s in all_schemas()}


class _HashCache:
    """SHA-256 of source files, each computed once per ``info`` call (sources can be large)."""

    def __init__(self) -> None:
        self._cache: dict[Path, str] = {}

    def __call__(self, path: Path) -> str | None:
        """The SHA-256 of a source, ``None`` when it cannot be hashed (a FIFO or device named as
        a source in a tampered provenance is never read)."""
        key = path.resolve()
        if key not in self._cache:
            try:
                self._cache[key] = file_sha256(key)
            except (HeliocalError, OSError):
                self._cache[key] = None
        return self._cache[key]


class _Manifests:
    """The committed runs of one folder, loaded and verified once per ``info`` call."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.runs = all_manifests(folder)
        self._problems: dict[str, dict] = {}

    def owner(self, rel: str):
        """(manifest, entry) of the run that lists ``rel``, or ``None``."""
        for m in self.runs:
            if rel in m.files:
                return m, m.files[rel]
        return None

    def problems(self, m) -> dict:
        if m.stage not in self._problems:
            self._problems[m.stage] = verify_files(m)
        return self._problems[m.stage]

    def fingerprint(self, schema) -> str | None:
        for m in self.runs:
            if m.stage == schema.producer and schema.filename in m.files:
                return m.files[schema.filename].get("fingerprint")
        return None


def _schema_version() -> int:
    """The artifact schema version this heliocal reads (imported here: it needs pyarrow)."""
    from heliocal.pipeline.artifacts.store import SCHEMA_VERSION

    return SCHEMA_VERSION


def _read_metadata(path: Path) -> tuple[pq.FileMetaData, dict]:
    """The Parquet footer and the heliocal provenance of ``path`` (one-line errors otherwise)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from heliocal.pipeline.artifacts.store import PROVENANCE_KEY, parse_provenance

    if not path.exists():
        raise InputError(f"{path}: no such file or folder; check the path")
    mode = path.stat().st_mode
    if not stat.S_ISREG(mode):  # a FIFO or device is never opened (it could block or not end)
        raise InputError(f"{path} is {kind_of(mode)}, not a heliocal artifact; give a Parquet "
                         "artifact or a work directory")
    try:
        meta = pq.ParquetFile(path).metadata
    except (pa.ArrowInvalid, OSError) as exc:
        raise SchemaError(f"{path} is not a readable Parquet file ({' '.join(str(exc).split())}); "
                          "give a heliocal artifact or a work directory") from exc
    kv = meta.metadata or {}
    if PROVENANCE_KEY not in kv:
        raise SchemaError(f"{path} is a Parquet file but not a heliocal artifact (it has no "
                          "heliocal provenance metadata)")
    return meta, parse_provenance(kv[PROVENANCE_KEY], path)


def _inputs_freshness(prov: dict, folder: Path, schemas: dict, sha: _HashCache,
                      manifests: _Manifests) -> dict:
    """Per recorded input: its path now, the recorded and the current fingerprint (an upstream
    artifact: its content fingerprint as its stage committed it; a source: its SHA-256), and a
    status."""
    out = {}
    for label, recorded in sorted((prov.get("inputs") or {}).items()):
        path, current = None, None
        if label.startswith(_SOURCE_PREFIX):
            path = Path(label[len(_SOURCE_PREFIX):])
            current = sha(path) if path.exists() else None
        elif label in schemas:  # an upstream artifact in the same work directory
            path = folder / schemas[label].filename
            current = manifests.fingerprint(schemas[label])
        else:
            value = (prov.get("options") or {}).get(label)  # e.g. ingest's tower/properties
            if isinstance(value, str) and value:
                path = Path(value)
                current = sha(path) if path.exists() else None
        if recorded is None or current is None:
            status = "unknown"
        else:
            status = "fresh" if current == recorded else "stale"
        out[label] = {"path": None if path is None else str(path), "recorded": recorded,
                      "current": current, "status": status}
    return out


def _commit(path: Path, manifests: _Manifests) -> dict:
    """Which run committed ``path`` and whether the file is still what it wrote."""
    try:
        rel = path.absolute().relative_to(manifests.folder.absolute()).as_posix()
    except ValueError:
        rel = path.name
    found = manifests.owner(rel)
    if found is None:
        return {"status": "uncommitted", "stage": None, "run_id": None, "manifest": None}
    m, _ = found
    problem = manifests.problems(m).get(rel)
    return {"status": "modified" if problem else "committed", "stage": m.stage,
            "run_id": m.run_id, "manifest": str(m.path)}


def _status(prov: dict, inputs: dict, commit: dict) -> str:
    if prov.get("schema_version") != _schema_version():
        return "incompatible"
    if commit["status"] != "committed":
        return commit["status"]
    states = {i["status"] for i in inputs.values()}
    for status in ("stale", "unknown"):
        if status in states:
            return status
    return "fresh"


def _hint(status: str, prov: dict, folder: Path) -> str | None:
    if status in ("stale", "incompatible", "modified", "uncommitted"):
        return f"rerun `heliocal {prov.get('stage', '?')} --workdir {folder}`"
    return None


def describe_artifact(path: str | Path, *, _sha: _HashCache | None = None,
                      _schemas: dict | None = None, _manifests: _Manifests | None = None) -> dict:
    """Provenance, shape, commit and freshness of one heliocal Parquet artifact.

    Raises
    ------
    InputError : ``path`` does not exist.
    SchemaError : it is not a Parquet file, or not a heliocal artifact.
    """
    path = Path(path)
    meta, prov = _read_metadata(path)
    schemas = _schemas if _schemas is not None else _schemas_by_name()
    manifests = _manifests if _manifests is not None else _Manifests(path.parent)
    inputs = _inputs_freshness(prov, path.parent, schemas, _sha or _HashCache(), manifests)
    commit = _commit(path, manifests)
    status = _status(prov, inputs, commit)
    arrow = meta.schema.to_arrow_schema()
    return {
        "path": str(path),
        "artifact": prov.get("artifact"),
        "stage": prov.get("stage"),
        "rows": int(meta.num_rows),
        "row_groups": int(meta.num_row_groups),
        "size_bytes": path.stat().st_size,
        "columns": [{"name": f.name, "type": str(f.type)} for f in arrow],
        "status": status,
        "hint": _hint(status, prov, path.parent),
        "reads_schema_version": _schema_version(),
        "commit": commit,
        "inputs": inputs,
        "provenance": prov,
    }


def describe_workdir(workdir: str | Path) -> dict:
    """Every artifact of ``workdir`` (stage, run, rows, freshness), every committed run (files
    verified), interrupted commits, foreign files and leftovers."""
    workdir = Path(workdir)
    sha, schemas = _HashCache(), _schemas_by_name()
    manifests = _Manifests(workdir)
    artifacts, foreign = [], []
    for path in sorted(workdir.glob("*.parquet")):
        if path.name.startswith(".") or os.path.islink(path) or not path.is_file():
            continue  # a link, FIFO or device: listed under "hostile", never opened
        try:
            d = describe_artifact(path, _sha=sha, _schemas=schemas, _manifests=manifests)
        except SchemaError as exc:
            listed = _commit(path, manifests)
            if listed["status"] != "modified":
                foreign.append({"path": str(path), "reason": str(exc)})
                continue
            # committed, but its bytes changed so that they no longer read as an artifact
            d = {"path": str(path), "artifact": None, "stage": listed["stage"], "rows": None,
                 "status": "modified", "inputs": {}, "commit": listed, "provenance": {},
                 "hint": f"rerun `heliocal {listed['stage']} --workdir {workdir}`"}
        artifacts.append({k: d[k] for k in ("path", "artifact", "stage", "rows", "status", "hint",
                                             "inputs")}
                         | {"schema_version": d["provenance"].get("schema_version"),
                            "run_id": d["commit"]["run_id"]})
    runs = []
    for m in manifests.runs:
        problems = manifests.problems(m)
        runs.append({"stage": m.stage, "run_id": m.run_id, "manifest": str(m.path),
                     "created_utc": m.data.get("created_utc"), "command": m.data.get("command"),
                     "files": len(m.files), "pending": m.pending(),
                     "problems": [{"path": str(workdir / r), "problem": p}
                                  for r, p in problems.items()]})
    pending = [{"stage": m.stage, "run_id": m.run_id, "staging": str(m.staging),
                "staged_files": sum(1 for r in m.files if (m.staging / r).is_file())}
               for m in pending_commits(workdir)]
    stopped = [{"path": str(p), "in_progress": staging_in_use(p)}
               for p in stale_staging_folders(workdir)]
    hostile = hostile_entries(workdir)
    models, models_error = _aim_models(workdir)
    return {
        "workdir": str(workdir),
        "artifacts": artifacts,
        "runs": runs,
        "fresh": all(a["status"] == "fresh" for a in artifacts)
        and not any(r["problems"] for r in runs) and not hostile,
        "not_artifacts": foreign,
        "pending_commits": pending,
        "uncommitted_runs": stopped,
        "leftovers": [str(p) for p in leftovers(workdir) if not os.path.islink(p)],
        "hostile": hostile,
        "aim_models": models,
        "aim_models_error": models_error,
        "writer": lock_holder(workdir),  # the stage writing it right now, if any (not blocked)
    }


def _aim_models(workdir: Path) -> tuple[list, str | None]:
    """The models ``aim --model auto`` uses, or why that cannot be told (a modified or missing
    input: the artifacts' table above shows which), so that ``info`` still shows the rest."""
    from heliocal.pipeline.stages.aim_choice import aim_models

    try:
        return [{k: v for k, v in m.items() if k != "model_dir"}
                for m in aim_models(workdir).values()], None
    except HeliocalError as exc:
        return [], str(exc)


# ------------------------------------------------------------------------------------------------
# formatting
# ------------------------------------------------------------------------------------------------
_STYLE = {"fresh": "green", "stale": "bold red", "unknown": "yellow", "incompatible": "bold red",
          "modified": "bold red", "uncommitted": "bold red"}


def _short(sha: str | None) -> str:
    return "-" if sha is None else sha[:12]


def _inputs_table(inputs: dict) -> Table:
    table = Table(box=box.SIMPLE_HEAD, pad_edge=False, show_edge=False)
    for col in ("input", "path", "recorded", "current", "status"):
        table.add_column(col, overflow="fold")
    for label, i in inputs.items():
        table.add_row(Text(label), Text(i["path"] or "-"), Text(_short(i["recorded"])),
                      Text(_short(i["current"])),
                      Text(i["status"], style=_STYLE.get(i["status"], "")))
    return table


def _run_text(commit: dict) -> str:
    if commit["status"] == "uncommitted":
        return "not committed (no manifest of its stage lists it)"
    text = f"{commit['run_id']} ({Path(commit['manifest']).name})"
    if commit["status"] == "modified":
        text += ": the file differs from what this run wrote"
    return text


def _print_artifact(d: dict) -> None:
    prov = d["provenance"]
    head = Table(box=None, show_header=False, pad_edge=False)
    head.add_column(style="bold", no_wrap=True)
    head.add_column(overflow="fold")
    version = str(prov.get("schema_version"))
    if prov.get("schema_version") != _schema_version():
        version += f" (this heliocal reads {_schema_version()})"
    rows = [
        ("file", d["path"]),
        ("artifact", str(prov.get("artifact"))),
        ("stage", f"heliocal {prov.get('stage')}"),
        ("rows", f"{d['rows']} in {d['row_groups']} row group(s), {len(d['columns'])} columns, "
                 f"{d['size_bytes']} bytes"),
        ("schema version", version),
        ("heliocal", f"{prov.get('heliocal_version')} (git {prov.get('git_revision')})"),
        ("command", str(prov.get("command"))),
        ("seed", "-" if prov.get("seed") is None else str(prov.get("seed"))),
        ("run", _run_text(d["commit"])),
    ]
    for key, value in rows:
        head.add_row(Text(key), Text(value))
    status = Text(d["status"], style=_STYLE.get(d["status"], ""))
    if d["hint"]:
        status.append(f": {d['hint']}")
    head.add_row(Text("status"), status)
    stdout.print(head)
    options = prov.get("options") or {}
    stdout.print(Text("options", style="bold"))
    if not options:
        stdout.print(Text("  (none)"))
    for key, value in sorted(options.items()):
        stdout.print(Text(f"  {key} = {json.dumps(value)}"))
    stdout.print(Text("inputs (content fingerprint of an artifact, SHA-256 of a source)",
                      style="bold"))
    if d["inputs"]:
        stdout.print(_inputs_table(d["inputs"]))
    else:
        stdout.print(Text("  (none recorded)"))
    stdout.print(Text("columns", style="bold"))
    stdout.print(Text("  " + ", ".join(f"{c['name']} ({c['type']})" for c in d["columns"])))


def _print_workdir(d: dict) -> None:
    if not d["artifacts"] and not d["not_artifacts"] and not d["runs"]:
        stdout.print(Text(f"{d['workdir']}: no heliocal artifacts (run `heliocal ingest SOURCE "
                          f"--workdir {d['workdir']}` first)"))
    else:
        table = Table(title=Text(f"artifacts in {d['workdir']}"), box=box.SIMPLE_HEAD,
                      pad_edge=False)
        for col in ("file", "stage", "rows", "status", "changed inputs"):
            table.add_column(col, justify="right" if col == "rows" else "left",
                             no_wrap=col != "changed inputs", overflow="fold")
        for a in d["artifacts"]:
            changed = ", ".join(k for k, i in a["inputs"].items() if i["status"] != "fresh")
            status = Text(a["status"], style=_STYLE.get(a["status"], ""))
            table.add_row(Text(Path(a["path"]).name), Text(str(a["stage"])),
                          Text(str(a["rows"])), status, Text(changed or "-"))
        stdout.print(table)
        for a in d["artifacts"]:
            if a["hint"]:
                why = a["status"]
                if why == "incompatible":
                    why += (f" (schema version {a['schema_version']}, this heliocal reads "
                            f"{_schema_version()})")
                stdout.print(Text(f"{Path(a['path']).name}: {why}; {a['hint']}"))
    if d["runs"]:
        runs = Table(title=Text("committed runs"), box=box.SIMPLE_HEAD, pad_edge=False)
        for col in ("stage", "run (UTC time and id)", "files", "check"):
            runs.add_column(col, justify="right" if col == "files" else "left",
                            no_wrap=col != "check", overflow="fold")
        for r in d["runs"]:
            check = "ok" if not r["problems"] else f"{len(r['problems'])} file(s) differ"
            if r["pending"]:
                check += ", commit not applied yet"
            runs.add_row(Text(r["stage"]), Text(r["run_id"]), Text(str(r["files"])), Text(check))
        stdout.print(runs)
        for r in d["runs"]:
            for p in r["problems"]:
                stdout.print(Text(f"{p['path']}: {p['problem']} since `heliocal {r['stage']}` "
                                  f"committed it (run {r['run_id']}); rerun `heliocal {r['stage']} "
                                  f"--workdir {d['workdir']}`"))
    for p in d["pending_commits"]:
        stdout.print(Text(f"the `heliocal {p['stage']}` run {p['run_id']} was interrupted after "
                          f"its commit: {p['staged_files']} file(s) are still in {p['staging']} "
                          "(readers use them; the next stage run moves them into place)"))
    for f in d["not_artifacts"]:
        stdout.print(Text(f"not an artifact: {f['reason']}"))
    for u in d["uncommitted_runs"]:
        if u["in_progress"]:
            stdout.print(Text(f"a run in progress is writing {u['path']}"))
        else:
            stdout.print(Text(f"leftover of a run that stopped before its commit (no stage reads "
                              f"it; the next run removes it; safe to delete): {u['path']}"))
    for p in d["leftovers"]:
        stdout.print(Text(f"leftover of an interrupted write (no stage reads it; safe to delete): "
                          f"{p}"))
    for h in d.get("hostile", []):
        stdout.print(Text(f"hostile: {h['path']}: {h['problem']}", style="bold red"))
    w = d.get("writer")
    if w is not None:
        stdout.print(Text(f"being written now by `heliocal {w.get('stage', '?')}` (pid "
                          f"{w.get('pid', '?')} on {w.get('host', '?')}, started "
                          f"{w.get('started', '?')}): artifacts may change while you look"))
    if d.get("aim_models"):
        stdout.print(_aim_table(d["aim_models"]))
    elif d.get("aim_models_error"):
        stdout.print(Text(f"the models `aim --model auto` uses cannot be told: "
                          f"{d['aim_models_error']}"))


def _mrad(x) -> str:
    return "-" if x is None or x != x else f"{x:.3f}"


def _aim_table(models: list) -> Table:
    table = Table(title=Text("models `aim --model auto` uses (mean error_mrad)"),
                  caption=Text("forward: the same model fitted on the time split's training "
                               "rows, on its test rows (the latest); next day: fit-coarse's "
                               "rolling-origin evaluation (rolling_origin.parquet)"),
                  box=box.SIMPLE_HEAD, pad_edge=False)
    numbers = ("validation", "test", "forward", "next day", "weight decay")
    for col in ("heliostat", "model", "weight decay", "chosen by", "validation", "test",
                "forward", "next day"):
        table.add_column(col, justify="right" if col in numbers else "left", no_wrap=True)
    for m in models:
        name = (f"coarse {m['preset']}" if m["model"] == "coarse"
                else f"nominal ({m['preset']} worse)" if m["model"] == "nominal"
                else f"{m['variant']} on {m['preset']}")
        if m["preset"].endswith("+field-prior"):   # no training rows: no fit of its own
            name = f"field prior {m['preset'].split('+')[0]} (no fit of its own)"
        wd = "-" if m["weight_decay"] is None else f"{m['weight_decay']:g}"
        table.add_row(Text(m["heliostat_id"]), Text(name), Text(wd), Text(m["source"]),
                      Text(_mrad(m["val_error_mrad"])), Text(_mrad(m["test_error_mrad"])),
                      Text(_mrad(m.get("forward_error_mrad"))),
                      Text(_mrad(m.get("next_day_error_mrad"))))
    return table


# ------------------------------------------------------------------------------------------------
# the command
# ------------------------------------------------------------------------------------------------
@command("info")
def info_cmd(
    path: Annotated[Path, typer.Argument(
        help="A heliocal Parquet artifact, or a work directory to list its artifacts.")],
    json_: JsonFlag = False,
) -> None:
    """Show an artifact's provenance (version, command, options, seed, input hashes) and freshness."""
    if path.is_dir():
        emit(describe_workdir(path), json_, _print_workdir)
    else:
        emit(describe_artifact(path), json_, _print_artifact)
