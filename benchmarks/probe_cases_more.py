"""The extension of the issue-32 probe: further hostile work directories and command lines, as
cases of benchmarks/probe_workdir.py (run that script)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import time

from probe_workdir import (HELIOCAL, RUN_ID, Probe, add_manifest_file, aim_args, calibration_dir,
                           case, flagged, info_json, intact, manifest, one_line_error, paint_copy,
                           sha, usage_or_error, victim, write_manifest)


def _aim_json(r) -> dict | None:
    try:
        return json.loads(r.out)
    except ValueError:
        return None


# --- file types and links inside the work directory ------------------------------------------------
@case("E1", "fit-coarse with DIR/split.parquet a symlink to an identical copy outside",
      "refused with one line naming the link; the copy outside is untouched")
def e1(p: Probe):
    wd = p.workdir()
    copy = p.fresh("outside") / "split.parquet"
    shutil.move(wd / "split.parquet", copy)
    (wd / "split.parquet").symlink_to(copy)
    digest = sha(copy)
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--workers", "1", "--quiet")
    ok = one_line_error(r) and "link" in r.line and sha(copy) == digest
    return ok, f"exit {r.code}: {r.line}"


@case("E2", "fit-coarse and info DIR with DIR/split.parquet a FIFO",
      "no hang: fit-coarse refuses in one line, info flags the FIFO")
def e2(p: Probe):
    wd = p.workdir()
    (wd / "split.parquet").unlink()
    os.mkfifo(wd / "split.parquet")
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--workers", "1", "--quiet",
              timeout=60)
    ri, doc = info_json(p, wd)
    ok = one_line_error(r) and ri.code == 0 and flagged(doc, "split.parquet")
    return ok, f"fit-coarse exit {r.code} ({r.line}); info exit {ri.code}, flagged {flagged(doc, 'split.parquet')}"


@case("E3", "split-knn with DIR/split-knn.manifest.json a FIFO",
      "no hang; the stage replaces its manifest and says so")
def e3(p: Probe):
    wd = p.workdir()
    (wd / "split-knn.manifest.json").unlink()
    os.mkfifo(wd / "split-knn.manifest.json")
    r = p.run("split-knn", "--workdir", wd, "--quiet", timeout=60)
    ok = r.code == 0 and (wd / "split-knn.manifest.json").is_file() and "manifest" in r.err
    return ok, f"exit {r.code} after {r.seconds:.1f} s: {r.line}"


@case("E4", "fit-coarse with DIR/split-knn.manifest.json a symlink to a manifest outside",
      "refused (the link is not followed); the outside file is untouched")
def e4(p: Probe):
    wd = p.workdir()
    outside = p.fresh("outside") / "m.json"
    shutil.move(wd / "split-knn.manifest.json", outside)
    (wd / "split-knn.manifest.json").symlink_to(outside)
    digest = sha(outside)
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--workers", "1", "--quiet")
    ok = one_line_error(r) and "link" in r.line and sha(outside) == digest
    return ok, f"exit {r.code}: {r.line}"


@case("E5", "split-knn with DIR/split-knn.manifest.json a folder holding a file",
      "one line naming the folder; the folder and its file stay")
def e5(p: Probe):
    wd = p.workdir()
    (wd / "split-knn.manifest.json").unlink()
    (wd / "split-knn.manifest.json").mkdir()
    (wd / "split-knn.manifest.json" / "mine.txt").write_text("precious\n")
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    ok = one_line_error(r) and "split-knn.manifest.json" in r.line and intact(
        wd / "split-knn.manifest.json" / "mine.txt")
    return ok, f"exit {r.code}: {r.line}"


@case("E6", "fit-hybrid with DIR/hybrid/hybrid a symlink to a folder outside",
      "refused before the commit; nothing outside changes")
def e6(p: Probe):
    wd = p.workdir()
    outside = p.fresh("outside") / "models"
    shutil.move(wd / "hybrid" / "hybrid", outside)
    (wd / "hybrid" / "hybrid").symlink_to(outside)
    before = sorted((q.name, sha(q)) for q in outside.iterdir())
    r = p.run("fit-hybrid", "--workdir", wd, "--heliostat", "BE36", "--max-epochs", "5",
              "--ensemble", "1", "--workers", "1", "--seed", "5", "--quiet")
    after = sorted((q.name, sha(q)) for q in outside.iterdir())
    return before == after and one_line_error(r), f"outside {'unchanged' if before == after else 'WRITTEN'}; exit {r.code}: {r.line}"


@case("E7", "aim --model hybrid with hybrid/hybrid/BE36.pt a symlink to an identical file outside",
      "refused with one line naming the link")
def e7(p: Probe):
    wd = p.workdir()
    outside = p.fresh("outside") / "BE36.pt"
    shutil.move(wd / "hybrid" / "hybrid" / "BE36.pt", outside)
    (wd / "hybrid" / "hybrid" / "BE36.pt").symlink_to(outside)
    r = p.run(*aim_args(wd, "--model", "hybrid"))
    return one_line_error(r) and "link" in r.line, f"exit {r.code}: {r.line}"


@case("E8", "split-knn with a leftover DIR/.txn-fit-coarse-<id> that is a symlink to a folder outside",
      "the folder outside and its files stay; the link is removed or flagged")
def e8(p: Probe):
    wd = p.workdir()
    outside = p.fresh("outside")
    (outside / "keep.txt").write_text("precious\n")
    (wd / f".txn-fit-coarse-{RUN_ID}").symlink_to(outside)
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    return intact(outside / "keep.txt") and r.code == 0, f"outside {'intact' if intact(outside / 'keep.txt') else 'EMPTIED'}; exit {r.code}: {r.line}"


@case("E9", "split-knn with DIR/.ingest-spill-x a symlink to a folder outside",
      "the folder outside and its files stay")
def e9(p: Probe):
    wd = p.workdir()
    outside = p.fresh("outside")
    (outside / "keep.txt").write_text("precious\n")
    (wd / ".ingest-spill-x").symlink_to(outside)
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    return intact(outside / "keep.txt") and r.code == 0, f"outside {'intact' if intact(outside / 'keep.txt') else 'EMPTIED'}; exit {r.code}: {r.line}"


@case("E10", "split-knn and info DIR with DIR/.heliocal.lock a FIFO",
      "no hang: one clear line from the stage, info answers")
def e10(p: Probe):
    wd = p.workdir()
    os.mkfifo(wd / ".heliocal.lock")
    r = p.run("split-knn", "--workdir", wd, "--quiet", timeout=60)
    ri, doc = info_json(p, wd)
    ok = (r.code == 0 or one_line_error(r)) and r.code is not None and ri.code == 0
    return ok, f"split-knn exit {r.code} ({r.line}); info exit {ri.code}"


@case("E11", "split-knn with DIR/.heliocal.lock a folder", "one line naming it")
def e11(p: Probe):
    wd = p.workdir()
    (wd / ".heliocal.lock").mkdir()
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    return one_line_error(r) and ".heliocal.lock" in r.line, f"exit {r.code}: {r.line}"


# --- manifests ------------------------------------------------------------------------------------
@case("E12", "split-knn after a manifest `removed` entry ../outside/victim.txt",
      "the file outside stays")
def e12(p: Probe):
    wd = p.workdir()
    v = wd.parent / "outside" / "victim.txt"
    v.parent.mkdir()
    v.write_text("precious\n")
    add_manifest_file(wd, "split-knn", "../outside/victim.txt", key="removed")
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    return intact(v) and r.clean, f"victim {'intact' if intact(v) else 'DELETED'}; exit {r.code}: {r.line}"


@case("E13", "fit-hybrid after a manifest `files` entry hybrid/../../outside/victim.txt",
      "the file outside stays")
def e13(p: Probe):
    wd = p.workdir()
    v = wd.parent / "outside" / "victim.txt"
    v.parent.mkdir()
    v.write_text("precious\n")
    add_manifest_file(wd, "fit-hybrid", "hybrid/../../outside/victim.txt")
    r = p.run("fit-hybrid", "--workdir", wd, "--heliostat", "BE36", "--max-epochs", "5",
              "--ensemble", "1", "--workers", "1", "--quiet")
    return intact(v) and r.clean, f"victim {'intact' if intact(v) else 'DELETED'}; exit {r.code}: {r.line}"


@case("E14", "split-knn after a manifest run_id that is an absolute folder, which exists",
      "that folder and its files stay")
def e14(p: Probe):
    wd = p.workdir()
    target = p.fresh("outside")
    (target / "keep.txt").write_text("precious\n")
    data = manifest(wd, "split-knn")
    data["run_id"] = str(target)
    write_manifest(wd, "split-knn", data)
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    ok = intact(target / "keep.txt")
    return ok and r.clean, f"folder {'intact' if ok else 'REMOVED'}; exit {r.code}: {r.line}"


@case("E15", "fit-coarse after split-knn.manifest.json claims stage `ingest`",
      "refused as not a valid manifest, one line")
def e15(p: Probe):
    wd = p.workdir()
    data = manifest(wd, "split-knn")
    data["stage"] = "ingest"
    write_manifest(wd, "split-knn", data)
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--workers", "1", "--quiet")
    return one_line_error(r) and "manifest" in r.line, f"exit {r.code}: {r.line}"


@case("E16", "split-knn after its manifest's `removed` lists ingest.manifest.json",
      "ingest.manifest.json stays")
def e16(p: Probe):
    wd = p.workdir()
    add_manifest_file(wd, "split-knn", "ingest.manifest.json", key="removed")
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    ok = (wd / "ingest.manifest.json").is_file()
    return ok and r.clean, f"ingest.manifest.json {'kept' if ok else 'DELETED'}; exit {r.code}: {r.line}"


@case("E17", "split-knn after its manifest's file entry became a list",
      "the stage replaces the invalid manifest; exit 0")
def e17(p: Probe):
    wd = p.workdir()
    data = manifest(wd, "split-knn")
    data["files"]["split.parquet"] = ["not", "an", "entry"]
    write_manifest(wd, "split-knn", data)
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    return r.code == 0 and r.clean, f"exit {r.code}: {r.line}"


@case("E18", "split-knn after its manifest became Latin-1 bytes",
      "the stage replaces the invalid manifest; exit 0")
def e18(p: Probe):
    wd = p.workdir()
    (wd / "split-knn.manifest.json").write_bytes(b"\xff\xfe{\xe9}")
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    return r.code == 0 and r.clean, f"exit {r.code}: {r.line}"


@case("E19", "fit-coarse and info after split-knn.manifest.json became 100,000 nested `[`",
      "one clear line from fit-coarse (no internal RecursionError); info flags the manifest")
def e19(p: Probe):
    wd = p.workdir()
    (wd / "split-knn.manifest.json").write_text("[" * 100_000)
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--workers", "1", "--quiet")
    ri, doc = info_json(p, wd)
    ok = one_line_error(r) and ri.code == 0 and flagged(doc, "split-knn.manifest.json")
    return ok, f"fit-coarse exit {r.code} ({r.line}); info exit {ri.code}"


@case("E20", "info DIR after the provenance of split.parquet names its input source:/dev/zero "
             "(file rewritten and recommitted)",
      "info answers within 20 s (it does not hash an endless device)")
def e20(p: Probe):
    import pyarrow.parquet as pq

    wd = p.workdir()
    path = wd / "split.parquet"
    table = pq.read_table(path)
    meta = dict(table.schema.metadata)
    prov = json.loads(meta[b"heliocal"])
    prov["inputs"]["source:/dev/zero"] = "0" * 64
    meta[b"heliocal"] = json.dumps(prov).encode()
    pq.write_table(table.replace_schema_metadata(meta), path)
    data = manifest(wd, "split-knn")
    data["files"]["split.parquet"].update(sha256=sha(path), size=path.stat().st_size)
    write_manifest(wd, "split-knn", data)
    r = p.run("info", wd, timeout=20)
    return r.code == 0, f"exit {r.code} after {r.seconds:.1f} s: {r.line}"


# --- leftovers and concurrency --------------------------------------------------------------------
@case("E21", "fit-coarse after a killed run left .txn-split-knn-<id>/, .ingest-spill-x/ and "
             ".split.parquet.tmp-x",
      "all three removed; one stderr line says what was removed")
def e21(p: Probe):
    wd = p.workdir()
    (wd / f".txn-split-knn-{RUN_ID}").mkdir()
    (wd / f".txn-split-knn-{RUN_ID}" / "split.parquet").write_bytes(b"half")
    (wd / ".ingest-spill-x").mkdir()
    (wd / ".split.parquet.tmp-x").write_bytes(b"half")
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--workers", "1", "--quiet")
    left = [q.name for q in wd.iterdir() if q.name.startswith((".txn", ".ingest", ".split"))]
    # log records start with their level; the terminal width may wrap one record over lines
    records = [" ".join(x.split()) for x in re.split(r"\n(?=[A-Z]+ )", r.err) if "removed" in x]
    said = len(records) == 1 and all(n in records[0] for n in (
        f".txn-split-knn-{RUN_ID}", ".ingest-spill-x", ".split.parquet.tmp-x"))
    return r.code == 0 and not left and said, f"exit {r.code}; left: {left}; said: {records}"


@case("E22", "two split-knn at once on one work directory",
      "one runs, the other stops at once with one line naming the running stage")
def e22(p: Probe):
    wd = p.workdir()
    cmd = [HELIOCAL, "split-knn", "--workdir", str(wd), "--quiet"]
    first = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    time.sleep(0.3)
    second = p.run("split-knn", "--workdir", wd, "--quiet")
    err = first.communicate(timeout=120)[1]
    codes = sorted([first.returncode, second.code])
    busy = "being written by" in second.err or "being written by" in err
    return codes[0] == 0 and busy or codes == [0, 0], f"exit codes {codes}; busy message: {busy}"


@case("E23", "aim --model auto, 5 times while fit-coarse rewrites the work directory",
      "every aim answers (exit 0) with the previous or the new fit")
def e23(p: Probe):
    wd = p.workdir()
    fit = subprocess.Popen([HELIOCAL, "fit-coarse", "--workdir", str(wd), "--preset", "static-6",
                            "--workers", "1", "--quiet"], stdout=subprocess.DEVNULL,
                           stderr=subprocess.PIPE, text=True)
    codes = []
    for _ in range(5):
        r = p.run(*aim_args(wd, "--model", "coarse"))
        codes.append(r.code if r.code == 0 else f"{r.code}: {r.line}")
    fit.communicate(timeout=300)
    return all(c == 0 for c in codes) and fit.returncode == 0, f"aim exits {codes}; fit-coarse {fit.returncode}"


# --- odd times, targets and options for aim --------------------------------------------------------
def _same_steps(a: dict | None, b: dict | None) -> bool:
    return a is not None and b is not None and all(
        abs(a[k] - b[k]) < 1e-9 for k in ("axis_1_steps", "axis_2_steps"))


@case("E24", "aim --time 2023-06-21T14:00:00+02:00 against 2023-06-21T12:00:00Z",
      "the same steps (an offset is converted to UTC)")
def e24(p: Probe):
    a = _aim_json(p.run(*aim_args(p.base, time_utc="2023-06-21T12:00:00Z")))
    b = _aim_json(p.run(*aim_args(p.base, time_utc="2023-06-21T14:00:00+02:00")))
    return _same_steps(a, b), f"steps {a and a['axis_1_steps']:.3f} vs {b and b['axis_1_steps']:.3f}" if a and b else "no answer"


@case("E25", "aim --time 2023-06-21T12:00:00 (no zone)", "read as UTC: the steps of ...Z")
def e25(p: Probe):
    a = _aim_json(p.run(*aim_args(p.base, time_utc="2023-06-21T12:00:00Z")))
    b = _aim_json(p.run(*aim_args(p.base, time_utc="2023-06-21T12:00:00")))
    return _same_steps(a, b), "same steps" if _same_steps(a, b) else f"{a and a.get('axis_1_steps')} vs {b and b.get('axis_1_steps')}"


@case("E26", "aim --time NaT", "a usage error naming --time (not a time)")
def e26(p: Probe):
    r = p.run(*aim_args(p.base, time_utc="NaT"))
    return usage_or_error(r) and "--time" in r.err, f"exit {r.code}: {r.line}"


@case("E27", "aim --time ''", "a usage error naming --time")
def e27(p: Probe):
    r = p.run(*aim_args(p.base, time_utc=""))
    return usage_or_error(r) and "--time" in r.err, f"exit {r.code}: {r.line}"


@case("E28", "aim --time 99999-01-01T00:00:00Z", "a usage error naming --time (out of range)")
def e28(p: Probe):
    r = p.run(*aim_args(p.base, time_utc="99999-01-01T00:00:00Z"))
    return usage_or_error(r) and "--time" in r.err, f"exit {r.code}: {r.line}"


@case("E29", "aim --time 2023-06-21T00:00:00Z (midnight at Jülich)",
      "one line: the sun is below the horizon")
def e29(p: Probe):
    r = p.run(*aim_args(p.base, time_utc="2023-06-21T00:00:00Z"))
    return one_line_error(r) and "horizon" in r.line, f"exit {r.code}: {r.line}"


@case("E30", "aim --time 1800-06-21T12:00:00Z (long before the data)",
      "steps with a warning on stderr and in the JSON")
def e30(p: Probe):
    r = p.run(*aim_args(p.base, time_utc="1800-06-21T12:00:00Z"))
    doc = _aim_json(r)
    ok = (r.code == 0 and doc is not None and bool(doc.get("warnings"))
          and "warning" in r.err.lower())
    return ok, f"exit {r.code}; JSON warnings: {(doc or {}).get('warnings')}"


@case("E31", "aim --target inf,0,0", "one line: not finite")
def e31(p: Probe):
    r = p.run(*aim_args(p.base, target="inf,0,0"))
    return usage_or_error(r) and "finite" in r.err, f"exit {r.code}: {r.line}"


@case("E32", "aim --target E,N,U at the heliostat's own position (its reference point, not the "
             "mirror centre)",
      "finite steps and aim error, or one clear line; never NaN in the answer")
def e32(p: Probe):
    import pyarrow.parquet as pq

    h = pq.read_table(p.base / "heliostats.parquet").to_pandas().set_index("heliostat_id").loc["BE36"]
    point = ",".join(repr(float(h[f"heliostat_{a}_m"])) for a in "enu")
    r = p.run(*aim_args(p.base, target=point))
    if r.code != 0:
        return one_line_error(r), f"exit {r.code}: {r.line}"
    doc = _aim_json(r)
    finite = doc is not None and "NaN" not in r.out and "Infinity" not in r.out
    return finite, f"exit 0: steps {doc and round(doc['axis_1_steps'], 1)}, {doc and round(doc['axis_2_steps'], 1)}; aim error {doc and doc['aim_error_mrad']:.2g} mrad"


@case("E33", "aim --sun-azimuth nan --sun-elevation 30", "one line: not finite")
def e33(p: Probe):
    r = p.run(*aim_args(p.base, "--sun-azimuth", "nan", "--sun-elevation", "30", time_utc=None))
    return usage_or_error(r) and "finite" in r.err, f"exit {r.code}: {r.line}"


@case("E34", "aim --sun-azimuth 0 --sun-elevation 95", "one line: elevation outside [-90, 90]")
def e34(p: Probe):
    r = p.run(*aim_args(p.base, "--sun-azimuth", "0", "--sun-elevation", "95", time_utc=None))
    return usage_or_error(r) and "elevation" in r.err, f"exit {r.code}: {r.line}"


@case("E35", "aim --env temperature", "a clear error: NAME=VALUE expected")
def e35(p: Probe):
    r = p.run(*aim_args(p.base, "--env", "temperature"))
    return usage_or_error(r) and "NAME=VALUE" in r.err, f"exit {r.code}: {r.line}"


@case("E36", "aim --heliostat ../../etc/passwd", "one line: no such heliostat; nothing read outside")
def e36(p: Probe):
    r = p.run(*aim_args(p.base, heliostat="../../etc/passwd"))
    return one_line_error(r), f"exit {r.code}: {r.line}"


@case("E37", "aim --workdir FILE (a regular file)", "one clear line")
def e37(p: Probe):
    f = p.fresh("file") / "notadir"
    f.write_text("x")
    r = p.run(*aim_args(f))
    return usage_or_error(r), f"exit {r.code}: {r.line}"


# --- info on odd paths ----------------------------------------------------------------------------
@case("E38", "info FIFO", "no hang; one line: not a regular file")
def e38(p: Probe):
    fifo = p.fresh("fifo") / "a.parquet"
    os.mkfifo(fifo)
    r = p.run("info", fifo, timeout=20)
    return one_line_error(r), f"exit {r.code} after {r.seconds:.1f} s: {r.line}"


@case("E39", "info /dev/zero", "no hang; one line")
def e39(p: Probe):
    r = p.run("info", "/dev/zero", timeout=20)
    return one_line_error(r), f"exit {r.code} after {r.seconds:.1f} s: {r.line}"


@case("E40", "info DIR with DIR/hybrid a symlink and DIR/extra.parquet a symlink to /etc/hostname",
      "exit 0; both links flagged as hostile")
def e40(p: Probe):
    wd = p.workdir()
    outside = p.fresh("outside") / "hybrid"
    shutil.move(wd / "hybrid", outside)
    (wd / "hybrid").symlink_to(outside)
    (wd / "extra.parquet").symlink_to("/etc/hostname")
    r, doc = info_json(p, wd)
    ok = r.code == 0 and flagged(doc, "extra.parquet") and flagged(doc, "hybrid")
    return ok, f"exit {r.code}; flagged hybrid {flagged(doc, 'hybrid')}, extra.parquet {flagged(doc, 'extra.parquet')}"


# --- input sources --------------------------------------------------------------------------------
@case("E41", "ingest FIFO.csv (a named pipe as the log)", "no hang; one line: not a regular file")
def e41(p: Probe):
    fifo = p.fresh("fifo") / "log.csv"
    os.mkfifo(fifo)
    r = p.run("ingest", fifo, "--workdir", p.fresh("wd") / "wd", "--quiet", timeout=30)
    return one_line_error(r), f"exit {r.code} after {r.seconds:.1f} s: {r.line}"


@case("E42", "ingest PAINT/ whose BE36/BE36-heliostat-properties.json is a symlink outside",
      "one line naming the link (properties are not read from outside)")
def e42(p: Probe):
    paint = paint_copy(p)
    prop = paint / "BE36" / "BE36-heliostat-properties.json"
    outside = p.fresh("outside") / prop.name
    shutil.move(prop, outside)
    prop.symlink_to(outside)
    r = p.run("ingest", paint, "--workdir", p.fresh("wd") / "wd", "--quiet")
    return one_line_error(r) and "link" in r.line, f"exit {r.code}: {r.line}"


@case("E43", "ingest PAINT/ whose heliostat folder BX99 is a symlink to a folder outside",
      "BX99's files refused with a reason (rejected rows or one line); nothing outside read into raw")
def e43(p: Probe):
    paint = paint_copy(p)
    outside = p.fresh("outside") / "BX99"
    shutil.copytree(paint / "BH35", outside)
    (outside / "BH35-heliostat-properties.json").rename(outside / "BX99-heliostat-properties.json")
    (paint / "BX99").symlink_to(outside)
    wd = p.fresh("wd") / "wd"
    r = p.run("ingest", paint, "--workdir", wd, "--quiet")
    if r.code != 0:
        return one_line_error(r) and "link" in r.line, f"exit {r.code}: {r.line}"
    import pyarrow.parquet as pq

    m = pq.read_table(wd / "measurements.parquet").to_pandas()
    kept = int((m["heliostat_id"] == "BX99").sum())
    return kept == 0, f"exit 0; BX99 rows kept: {kept}"


@case("E44", "ingest PAINT/ with a calibration file symlinked to another file inside PAINT/",
      "accepted like a copy (a link inside the source folder is fine)")
def e44(p: Probe):
    paint = paint_copy(p)
    cal = calibration_dir(paint)
    first = sorted(cal.iterdir())[0]
    (cal / "99997-calibration-properties.json").symlink_to(first)
    wd = p.fresh("wd") / "wd"
    r = p.run("ingest", paint, "--workdir", wd, "--quiet")
    if r.code != 0:
        return False, f"exit {r.code}: {r.line}"
    import pyarrow.parquet as pq

    ids = set(pq.read_table(wd / "measurements.parquet").to_pandas()["measurement_id"])
    return "99997" in ids, f"measurement 99997 {'kept' if '99997' in ids else 'not kept'}"


@case("E45", "ingest PAINT/ --workdir PAINT (the source folder itself)",
      "one line: the work directory is inside the source folder")
def e45(p: Probe):
    paint = paint_copy(p)
    r = p.run("ingest", paint, "--workdir", paint, "--quiet")
    return one_line_error(r) and "inside the source folder" in r.line, f"exit {r.code}: {r.line}"


@case("E46", "ingest DIR/paint --workdir DIR (the source folder inside the work directory)",
      "ingested (the stage writes nothing into the source folder)")
def e46(p: Probe):
    paint = paint_copy(p)
    wd = paint.parent
    r = p.run("ingest", paint, "--workdir", wd, "--quiet")
    return r.code == 0, f"exit {r.code}: {r.line}"


@case("E47", "ingest a log with ids LPT9, Aux, CONSOLE and COM10",
      "LPT9 and Aux rejected as invalid_heliostat_id; CONSOLE and COM10 kept")
def e47(p: Probe):
    from probe_cases import _log_with_ids, _rejected

    log = _log_with_ids(p, ["LPT9", "Aux", "CONSOLE", "COM10"])
    wd = p.fresh("wd") / "wd"
    r = p.run("ingest", log, "--workdir", wd, "--quiet")
    if r.code != 0:
        return False, f"exit {r.code}: {r.line}"
    bad = sorted(set(_rejected(wd).query("reason == 'invalid_heliostat_id'")["heliostat_id"]))
    return bad == ["Aux", "LPT9"], f"rejected: {bad}"


# --- Dask addresses --------------------------------------------------------------------------------
@case("E48", "fit-coarse --dask-address tcp://127.0.0.1:99999 (no such port)",
      "one line naming --dask-address, within 15 s")
def e48(p: Probe):
    wd = p.workdir()
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--dask-address",
              "tcp://127.0.0.1:99999", "--quiet")
    return one_line_error(r) and r.seconds < 15 and "dask" in r.line.lower(), f"exit {r.code} after {r.seconds:.1f} s: {r.line}"


@case("E49", "fit-coarse --dask-address tcp://no-such-host.invalid:8786",
      "one line: could not reach, within 15 s")
def e49(p: Probe):
    wd = p.workdir()
    r = p.run("fit-coarse", "--workdir", wd, "--preset", "static-6", "--dask-address",
              "tcp://no-such-host.invalid:8786", "--quiet")
    return one_line_error(r) and r.seconds < 15 and "could not" in r.line, f"exit {r.code} after {r.seconds:.1f} s: {r.line}"


# --- replaced links are not followed ---------------------------------------------------------------
@case("E50", "split-knn with DIR/split.parquet a symlink to a file outside (recommitted)",
      "the new split replaces the link itself; the outside file is untouched")
def e50(p: Probe):
    wd = p.workdir()
    v = victim(p)
    (wd / "split.parquet").unlink()
    (wd / "split.parquet").symlink_to(v)
    r = p.run("split-knn", "--workdir", wd, "--quiet")
    ok = intact(v) and r.code == 0 and not (wd / "split.parquet").is_symlink()
    return ok, f"outside {'intact' if intact(v) else 'WRITTEN'}; exit {r.code}: {r.line}"


@case("E51", "report with DIR/report/figures a symlink to a folder outside holding old.png",
      "nothing outside is written or removed; one line naming the link")
def e51(p: Probe):
    wd = p.workdir()
    outside = p.fresh("outside")
    (outside / "old.png").write_bytes(b"png")
    (wd / "report").mkdir()
    (wd / "report" / "figures").symlink_to(outside)
    r = p.run("report", "--workdir", wd, "--workers", "1", "--quiet", timeout=300)
    names = sorted(q.name for q in outside.iterdir())
    return names == ["old.png"] and one_line_error(r), f"outside holds {names}; exit {r.code}: {r.line}"


@case("E52", "split-knn as an unprivileged user on a work directory it cannot write",
      "one line: permission denied, what to do")
def e52(p: Probe):
    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        return True, "not root or no setpriv: skipped (needs another user)"
    wd = p.workdir()
    for q in [wd.parent.parent, *wd.parents][:3]:
        os.chmod(q, 0o755)
    os.chmod(wd, 0o555)
    proc = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups",
                           HELIOCAL, "split-knn", "--workdir", str(wd), "--quiet"],
                          capture_output=True, text=True, timeout=120)
    os.chmod(wd, 0o755)
    err = proc.stderr.strip().splitlines()
    line = err[-1] if err else ""
    ok = proc.returncode == 1 and "permission" in line.lower() and "internal" not in line
    return ok, f"exit {proc.returncode}: {line[:140]}"

