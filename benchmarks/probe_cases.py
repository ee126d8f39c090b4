"""The findings of issue 32 as cases of benchmarks/probe_workdir.py (run that script)."""

from __future__ import annotations

import csv
import json
import os
import shutil
import subprocess
from pathlib import Path

from probe_workdir import (HELIOCAL, ROOT, Probe, add_manifest_file, aim_args, calibration_dir,
                           case, flagged, info_json, intact, manifest, one_line_error, paint_copy,
                           sha, usage_or_error, victim, write_manifest)



def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): (sha(p) if p.is_file() else "dir")
            for p in sorted(folder.rglob("*"))}


# 1. deletes outside the work directory -----------------------------------------------------------
@case("F1a", "split-knn after a manifest `files` entry ../outside/victim.txt",
      "the file outside stays; the stage refuses or replaces the manifest, one clear line")
def f1a(p: Probe):
    wd = p.workdir()
    v = wd.parent / "outside" / "victim.txt"
    v.parent.mkdir()
    v.write_text("precious\n")
    add_manifest_file(wd, "split-knn", "../outside/victim.txt")
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    return intact(v) and r.clean, f"victim {'intact' if intact(v) else 'DELETED'}; exit {r.code}: {r.line}"


@case("F1b", "split-knn after a manifest `files` entry that is an absolute path",
      "the file stays; one clear line or a repaired manifest")
def f1b(p: Probe):
    wd = p.workdir()
    v = victim(p)
    add_manifest_file(wd, "split-knn", str(v))
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    return intact(v) and r.clean, f"victim {'intact' if intact(v) else 'DELETED'}; exit {r.code}: {r.line}"


def _traversal_run_id(p: Probe) -> tuple[Path, Path]:
    wd = p.workdir()
    target = wd.parent / "victim_dir"
    target.mkdir()
    (target / "keep.txt").write_text("precious\n")
    data = manifest(wd, "split-knn")
    data["run_id"] = "x/../../victim_dir"
    write_manifest(wd, "split-knn", data)
    (wd / ".txn-split-knn-x").mkdir()
    return wd, target


@case("F1c", "any stage after a manifest run_id x/../../victim_dir and a folder .txn-split-knn-x",
      "victim_dir and its files stay")
def f1c(p: Probe):
    wd, target = _traversal_run_id(p)
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--workers", "1", "--quiet")
    ok = intact(target / "keep.txt")
    return ok and r.clean, f"victim_dir {'intact' if ok else 'REMOVED'}; exit {r.code}: {r.line}"


@case("F1d", "info DIR with the manifest of F1c", "the manifest is flagged as hostile, not 'ok'")
def f1d(p: Probe):
    wd, target = _traversal_run_id(p)
    r, doc = info_json(p, wd)
    ok = flagged(doc, "split-knn.manifest.json") and intact(target / "keep.txt")
    runs = [x["stage"] for x in (doc or {}).get("runs", [])]
    return ok, f"exit {r.code}; flagged: {flagged(doc, 'split-knn.manifest.json')}; runs listed as ok: {runs}"


# 2. symlinks inside the work directory -----------------------------------------------------------
@case("F2a", "split-knn with DIR/.heliocal.lock a symlink to a file outside",
      "the outside file is not truncated or written")
def f2a(p: Probe):
    wd = p.workdir()
    v = victim(p)
    (wd / ".heliocal.lock").symlink_to(v)
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    return intact(v) and r.clean, f"outside file {'intact' if intact(v) else repr(v.read_text()[:40]) if v.exists() else 'GONE'}; exit {r.code}: {r.line}"


@case("F2b", "fit-hybrid with DIR/hybrid a symlink to a folder outside",
      "nothing outside changes; one line naming the link")
def f2b(p: Probe):
    wd = p.workdir()
    outside = p.fresh("outside") / "hybrid"
    shutil.move(wd / "hybrid", outside)
    (wd / "hybrid").symlink_to(outside)
    before = _snapshot(outside)
    r = p.run("fit-hybrid", "--workdir", wd, "--heliostat", "BE36", "--max-epochs", "5",
              "--ensemble", "1", "--workers", "1", "--seed", "7", "--quiet")
    same = _snapshot(outside) == before
    return same and one_line_error(r) and "hybrid" in r.line, \
        f"outside folder {'unchanged' if same else 'WRITTEN'}; exit {r.code}: {r.line}"


@case("F2c", "report with DIR/report a symlink to a folder outside",
      "nothing is written outside; one line naming the link")
def f2c(p: Probe):
    wd = p.workdir()
    outside = p.fresh("outside")
    (wd / "report").symlink_to(outside)
    r = p.run("report", "--workdir", wd, "--workers", "1", "--quiet", timeout=300)
    files = list(outside.iterdir())
    return not files and one_line_error(r), f"{len(files)} file(s) written outside; exit {r.code}: {r.line}"


# 3. input folders -------------------------------------------------------------------------------
def _rejected(wd: Path):
    import pyarrow.parquet as pq

    return pq.read_table(wd / "rejected.parquet").to_pandas()


@case("F3a", "ingest PAINT/ with calibration/99999-calibration-properties.json -> a file outside",
      "refused with a reason; no outside byte in rejected.parquet")
def f3a(p: Probe):
    paint = paint_copy(p)
    v = victim(p, "secret-outside-bytes\n")
    (calibration_dir(paint) / "99999-calibration-properties.json").symlink_to(v)
    wd = p.fresh("wd") / "wd"
    r = p.run("ingest", paint, "--workdir", wd, "--quiet")
    if r.code != 0:
        return one_line_error(r) and "link" in r.line, f"exit {r.code}: {r.line}"
    rej = _rejected(wd)
    leaked = rej["raw"].astype(str).str.contains("secret-outside").any()
    row = rej[rej["measurement_id"] == "99999"]
    why = (row["reason"].iloc[0] + ": " + row["detail"].iloc[0]) if len(row) else "not rejected"
    return (not leaked and len(row) == 1), f"outside bytes {'COPIED into raw' if leaked else 'not copied'}; {why}"


@case("F3b", "ingest PAINT/ with a FIFO named 99998-calibration-properties.json",
      "no hang; the FIFO is refused with a reason")
def f3b(p: Probe):
    paint = paint_copy(p)
    os.mkfifo(calibration_dir(paint) / "99998-calibration-properties.json")
    wd = p.fresh("wd") / "wd"
    r = p.run("ingest", paint, "--workdir", wd, "--quiet", timeout=60)
    if r.code != 0:
        return one_line_error(r), f"exit {r.code} after {r.seconds:.0f} s: {r.line}"
    row = _rejected(wd).query("measurement_id == '99998'")
    why = (row["reason"].iloc[0] + ": " + row["detail"].iloc[0]) if len(row) else "not rejected"
    return len(row) == 1, f"exit 0 after {r.seconds:.1f} s; {why}"


@case("F3c", "ingest PAINT/ --workdir PAINT/run (the work directory inside the input folder)",
      "one line saying the work directory is inside the source folder")
def f3c(p: Probe):
    paint = paint_copy(p)
    r = p.run("ingest", paint, "--workdir", paint / "run", "--quiet")
    return one_line_error(r) and "inside the source folder" in r.line, f"exit {r.code}: {r.line}"


def _log_with_ids(p: Probe, ids: list[str]) -> Path:
    src = ROOT / "sample_data" / "synthetic" / "calibration_log.csv"
    with open(src, newline="") as fh:
        rows = list(csv.reader(fh))
    out = p.fresh("log") / "log.csv"
    shutil.copy(src.parent / "tower-measurements.json", out.parent)  # the plant's reference
    with open(out, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(rows[0])
        for k, row in enumerate(rows[1:61]):
            w.writerow([ids[k % len(ids)], *row[1:]])
    return out


@case("F3d", "ingest a log whose heliostat ids are CON, NUL.txt, com1 and BE36",
      "CON, NUL.txt, com1 rejected as invalid_heliostat_id with a suggested name; BE36 kept")
def f3d(p: Probe):
    log = _log_with_ids(p, ["CON", "NUL.txt", "com1", "BE36"])
    wd = p.fresh("wd") / "wd"
    r = p.run("ingest", log, "--workdir", wd, "--quiet")
    if r.code != 0:
        return False, f"exit {r.code}: {r.line}"
    rej = _rejected(wd)
    bad = rej[rej["reason"] == "invalid_heliostat_id"]
    ids = sorted(set(bad["heliostat_id"]))
    ok = ids == ["CON", "NUL.txt", "com1"]
    hint = bad["detail"].iloc[0] if len(bad) else ""
    return ok, f"rejected as invalid_heliostat_id: {ids}; {hint[:90]}"


# 4. wedged states --------------------------------------------------------------------------------
@case("F4a", "split-knn after split-knn.manifest.json became `[]`",
      "the stage replaces its invalid manifest and says so; exit 0")
def f4a(p: Probe):
    wd = p.workdir()
    (wd / "split-knn.manifest.json").write_text("[]")
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    again = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--workers", "1", "--quiet")
    said = "manifest" in r.err
    return r.code == 0 and said and again.code == 0, \
        f"split-knn exit {r.code} ({r.line}); then fit-coarse exit {again.code}"


@case("F4b", "split-knn after split-knn.manifest.json was cut in the middle",
      "the stage replaces its invalid manifest and says so; exit 0")
def f4b(p: Probe):
    wd = p.workdir()
    path = wd / "split-knn.manifest.json"
    path.write_bytes(path.read_bytes()[:300])
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    return r.code == 0 and "manifest" in r.err, f"exit {r.code}: {r.line}"


@case("F4c", "fit-hybrid, then aim and fit-hybrid again, with DIR/hybrid a mount of another "
             "file system (tmpfs; private mount namespace)",
      "no internal error, nothing wedged: the commit completes (copy + rename) or is refused "
      "before it")
def f4c(p: Probe):
    if shutil.which("unshare") is None:
        return False, "unshare not available: not run"
    wd = p.workdir()
    shm = Path(tempfile_in_shm())
    shutil.copytree(wd / "hybrid", shm / "hybrid")
    heliocal = HELIOCAL
    fit = (f"{heliocal} fit-hybrid --workdir {wd} --heliostat BE36 --max-epochs 5 --ensemble 1 "
           "--workers 1 --seed 3 --quiet > /dev/null")
    aim = " ".join(map(str, [heliocal, *aim_args(wd, "--model", "hybrid")])) + " > /dev/null"
    script = (f"mount --bind {shm / 'hybrid'} {wd / 'hybrid'} || exit 99; "
              f"{fit}; echo first=$? >&2; {aim}; echo aim=$? >&2; {fit}; echo second=$? >&2")
    proc = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True,
                          timeout=600)
    shutil.rmtree(shm, ignore_errors=True)
    if proc.returncode == 99:
        return False, "bind mount not permitted here: not run"
    err = proc.stderr
    codes = {k: v for k, v in (x.split("=") for x in err.split() if x.startswith(("first=", "aim=", "second=")))}
    internal = "internal error" in err or "Traceback" in err
    ok = not internal and codes.get("second") == "0" and codes.get("aim") == "0"
    lines = [x for x in err.splitlines() if x.startswith("Error")]
    return ok, f"exit codes {codes}; {lines[0][:120] if lines else 'no error line'}"


def tempfile_in_shm() -> str:
    import tempfile

    return tempfile.mkdtemp(prefix="heliocal-probe-", dir="/dev/shm")


@case("F4d", "info DIR, then split-knn, after a killed ingest left .ingest-spill-abc/",
      "info lists it; the next stage removes it and says so on stderr")
def f4d(p: Probe):
    wd = p.workdir()
    spill = wd / ".ingest-spill-abc123"
    spill.mkdir()
    (spill / "rejected-000000.parquet").write_bytes(b"x" * 1000)
    r, doc = info_json(p, wd)
    listed = ".ingest-spill-abc123" in r.out
    r2 = p.run("split-knn", "--workdir", wd, "--quiet")
    gone = not spill.exists()
    said = ".ingest-spill-abc123" in r2.err
    return listed and gone and said and r2.code == 0, \
        f"info lists it: {listed}; split-knn exit {r2.code}, removed: {gone}, said so: {said}"


@case("F4e", "info DIR after one byte of coarse_params.parquet changed",
      "exit 0: the table with coarse_params.parquet marked modified")
def f4e(p: Probe):
    wd = p.workdir()
    path = wd / "coarse_params.parquet"
    data = bytearray(path.read_bytes())
    data[100] ^= 0xFF
    path.write_bytes(bytes(data))
    r, doc = info_json(p, wd)
    if doc is None:
        return False, f"exit {r.code}: {r.line}"
    status = {Path(a["path"]).name: a["status"] for a in doc["artifacts"]}
    st = status.get("coarse_params.parquet") or next(
        (f["reason"][:60] for f in doc.get("not_artifacts", []) if "coarse_params" in f["path"]), None)
    return r.code == 0 and st == "modified", f"exit {r.code}; coarse_params.parquet: {st}"


# 5. a model file pair swapped with another heliostat's --------------------------------------------
@case("F5", "aim --model hybrid after BE36's model files were replaced by BF41's (manifest updated)",
      "refused: the configuration names BF41; one line saying what to do")
def f5(p: Probe):
    wd = p.workdir()
    folder = wd / "hybrid" / "hybrid"
    data = manifest(wd, "fit-hybrid")
    for ext in ("json", "pt"):
        shutil.copy(folder / f"BF41.{ext}", folder / f"BE36.{ext}")
        rel = f"hybrid/hybrid/BE36.{ext}"
        raw = (folder / f"BE36.{ext}").read_bytes()
        data["files"][rel].update(sha256=sha(folder / f"BE36.{ext}"), size=len(raw))
    write_manifest(wd, "fit-hybrid", data)
    r = p.run(*aim_args(wd, "--model", "hybrid"))
    return one_line_error(r) and "BF41" in r.line, f"exit {r.code}: {r.line if r.code else r.out[:80]}"


# 6. internal errors and wrong messages ------------------------------------------------------------
@case("F6a", "aim --time noon", "a usage error naming --time; no internal error")
def f6a(p: Probe):
    r = p.run(*aim_args(p.base, time_utc="noon"))
    return usage_or_error(r) and "--time" in r.err, f"exit {r.code}: {r.line}"


@case("F6b", "aim --time 2023-02-30T12:00:00Z", "a usage error naming --time")
def f6b(p: Probe):
    r = p.run(*aim_args(p.base, time_utc="2023-02-30T12:00:00Z"))
    return usage_or_error(r) and "--time" in r.err, f"exit {r.code}: {r.line}"


@case("F6c", "fit-coarse --dask-address 'not a url'", "one line naming --dask-address")
def f6c(p: Probe):
    wd = p.workdir()
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--dask-address", "not a url",
              "--quiet")
    return one_line_error(r) and "dask" in r.line.lower(), f"exit {r.code} after {r.seconds:.1f} s: {r.line}"


@case("F6d", "fit-coarse --dask-address tcp://127.0.0.1:1 (nothing listens)",
      "fails within 15 s; says no scheduler could be reached at that address")
def f6d(p: Probe):
    wd = p.workdir()
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--dask-address",
              "tcp://127.0.0.1:1", "--quiet")
    ok = one_line_error(r) and r.seconds < 15 and "could not" in r.line and "parameter" not in r.line
    return ok, f"exit {r.code} after {r.seconds:.1f} s: {r.line}"


@case("F6e", "aim --target nan,nan,nan", "one line saying the target is not finite")
def f6e(p: Probe):
    r = p.run(*aim_args(p.base, target="nan,nan,nan"))
    return usage_or_error(r) and "finite" in r.err, f"exit {r.code}: {r.line}"


@case("F6f", "aim --env bogus=1", "one line naming bogus and the env inputs there are")
def f6f(p: Probe):
    r = p.run(*aim_args(p.base, "--env", "bogus=1"))
    return one_line_error(r) and "bogus" in r.line, f"exit {r.code}: {r.line if r.code else 'ignored'}"


@case("F6g", "aim --time 2300-06-21T12:00:00Z",
      "a warning on stderr and a field in the JSON: the time is far past the heliostat's data")
def f6g(p: Probe):
    r = p.run(*aim_args(p.base, time_utc="2300-06-21T12:00:00Z"))
    try:
        doc = json.loads(r.out)
    except ValueError:
        return False, f"exit {r.code}: {r.line}"
    warned = "warning" in r.err.lower()
    field = doc.get("warnings")
    return r.code == 0 and warned and bool(field), \
        f"exit {r.code}; stderr warning: {warned}; JSON warnings: {field and field[0][:80]}"


# 7. field metrics ---------------------------------------------------------------------------------
@case("F7", "report on a field with heliostat DEG1 whose 150 rows are one repeated measurement",
      "DEG1 is counted apart and left out of the field's mean and median")
def f7(p: Probe):
    paint = paint_copy(p)
    src = paint / "BE36"
    dst = paint / "DEG1"
    (dst / "calibration").mkdir(parents=True)
    props = json.loads((src / "BE36-heliostat-properties.json").read_text())
    (dst / "DEG1-heliostat-properties.json").write_text(json.dumps(props))
    one = sorted((src / "calibration").iterdir())[0]
    stamps = json.loads((paint / "timestamps.json").read_text())
    t = stamps[f"BE36_{one.name.split('-')[0]}"]
    for k in range(150):
        shutil.copy(one, dst / "calibration" / f"{900000 + k}-calibration-properties.json")
        stamps[f"DEG1_{900000 + k}"] = t
    (paint / "timestamps.json").write_text(json.dumps(stamps))
    wd = p.fresh("wd") / "wd"
    for args in (["ingest", paint], ["split-knn"], ["fit-coarse", "--preset", "static-6", "--workers", "1"],
                 ["report", "--workers", "1"]):
        r = p.run(*args, "--workdir", wd, "--quiet", timeout=600)
        if r.code != 0:
            return False, f"{args[0]} exit {r.code}: {r.line}"
    metrics = json.loads((wd / "report" / "metrics.json").read_text())
    fld = metrics["field"]
    pooled = fld["forward_in_time"]["coarse"]["knn_test"]
    others = sum(metrics["heliostats"][h]["forward_in_time"]["coarse"]["knn_test"]["n"]
                 for h in metrics["heliostats"] if h != "DEG1")
    apart = fld.get("degenerate_heliostats")
    return apart == ["DEG1"] and pooled["n"] == others, \
        f"field degenerate_heliostats: {apart}; pooled kNN test rows {pooled['n']} (others' {others})"


# 8. writes outside the work directory in normal use -----------------------------------------------
@case("F8", "split-knn from a git checkout whose index is stale (a tracked file touched)",
      "the checkout's .git/index is not rewritten (no index.lock taken)")
def f8(p: Probe):
    import heliocal.pipeline

    code = Path(heliocal.pipeline.__file__).resolve().parents[1]  # the checkout heliocal runs from
    try:
        index = Path(subprocess.run(["git", "rev-parse", "--path-format=absolute", "--git-path",
                                     "index"], cwd=code, capture_output=True, text=True,
                                    check=True).stdout.strip())
    except (OSError, subprocess.CalledProcessError):
        return True, "not a git checkout: nothing to write"
    readme = code / "README.md"
    st = readme.stat()
    try:
        os.utime(readme, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
        before = index.stat()
        wd = p.workdir()
        r = p.run("split-knn", "--workdir", wd, "--quiet")
        after = index.stat()
    finally:
        os.utime(readme, ns=(st.st_atime_ns, st.st_mtime_ns))
    same = (before.st_ino, before.st_mtime_ns) == (after.st_ino, after.st_mtime_ns)
    return same and r.code == 0, f"index {'untouched' if same else 'REWRITTEN (git took index.lock)'}; exit {r.code}"

