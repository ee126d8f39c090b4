"""Benchmark: calibrate a whole simulated field, stage by stage, with 1 and 2 workers.

Simulates a field (default 2,000 heliostats with 100 to 400 measurements each; ``heliocal
simulate``'s model, seed 0), writes it as a WGS84 calibration log plus PAINT heliostat-properties
files, then runs ``ingest``, ``split-knn``, ``fit-coarse --preset static-20``, ``fit-hybrid``
(one weight decay), ``pretrained-nn`` (``fit-hybrid --mode pretrained-nn``: the pre-trained
network's cost per heliostat, default variant), ``sweep --study 0`` (the production selection of
every heliostat with the default weight decays, band sets and ensembles; no training-size study),
``plan`` (a 7-day measurement plan from 2024-03-01, the budget the logs' pace gives; only when
asked for in ``--stages``) and ``report`` (every page and figure; the size of
``report/index.html`` and of the report folder are printed too), and on request
``fit-coarse-no-rolling`` (fit-coarse without its rolling-origin evaluation, for the next-day
error's cost), ``fit-coarse-prior`` (fit-coarse with ``--prior field``, for the field prior's
cost; ``fit-coarse`` itself runs with ``--prior none``) and ``aim`` (``aim --date 2024-03-01 --every 10min``: every heliostat's aims of a
day) as separate ``heliocal`` processes, once with ``--workers 1`` and once with
``--workers 2``, and prints per stage the wall
time, heliostats per second and the peak memory of the stage's whole process tree, sampled every
0.1 s, so the scaling ratio is measured in one run. The peak is given twice: summed RSS (each
process's resident pages; the workers' pages shared with their fork server, torch's libraries
and the preloaded modules, count once per process) and summed PSS (each shared page divided
among the processes that share it: what the tree takes from the machine's memory; a file
that processes outside the tree map too, such as another run's copy of the same library,
is shared with them as well, so run it alone). Usage::

    .venv/bin/python benchmarks/field.py [--heliostats 2000] [--out runs/field-bench]
        [--hybrid-epochs 800]
        [--stages ingest,split-knn,fit-coarse,fit-hybrid,pretrained-nn,sweep,plan,report | all]
        [--solver batched|scipy] [--workers 1,2] [--sweep-args "--no-warm-start"]
        [--update-heliostats N]

The issue's daily update is 20 heliostats with 5 new rows each, 1 % of a 2,000-heliostat field;
``--heliostats 200 --update-heliostats 20`` times that update on the smaller field, where it is
10 % of the heliostats: harsher per heliostat (an update's cost that grows with the field's
share that changed, such as training chunks that hold a changed heliostat, is larger), so a
time measured there bounds the 2,000-heliostat field's from above for those parts.

``--stages all`` (with the last of ``--workers``, default 2) times, in one run, the full method
and a daily update (:func:`run_all`): the field's log without the latest 5 rows of
``--update-heliostats`` heliostats (a seeded choice; default 1 % of the field, at least one)
goes through ``ingest``, ``split-knn``, ``fit-coarse``,
``sweep --study 0`` and ``report``; then those rows through ``ingest --append`` and every
later stage with ``--incremental``; then ``split-knn``, ``fit-coarse``, ``sweep`` and ``report``
with ``--incremental`` once more on unchanged inputs; and the same update as one command,
``heliocal update`` (phase ``update-cmd``), on a copy of the work directory the full method left,
put back at the same path (the stage-by-stage result moves to ``<wd>-stages``): a plant updates
its work directory where it is, and the report's pages, which name their work directory, are kept
where their bytes did not change. Between the full method and the update, phase ``aim`` times
``aim --date 2024-03-01 --every 10min`` on what the full method chose (the sweep's fine models
included; its table beside the work directory, ``<wd>-aims.parquet``).

The simulated field is cached in OUT/field (delete it to simulate again).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
HELIOCAL = str(Path(sys.executable).parent / "heliocal")


def _simulate_chunk(args):
    from heliocal.pipeline.models.simulator import simulate_field

    n, seed = args
    return simulate_field(n, seed=seed, measurements=(100, 400), dynamic_fraction=0.5)


def write_field(out: Path, n: int, seed: int = 0) -> dict:
    """Simulate ``n`` heliostats (in chunks over 2 processes) and write the log and properties."""
    from heliocal.pipeline.physics.geodesy import enu_to_wgs84
    from heliocal.pipeline.runtime.parallel import map_tasks
    from heliocal.pipeline.stages.simulate import json_text, tower_json

    if (out / "done.json").exists():
        return json.loads((out / "done.json").read_text())
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    chunk = 100
    tasks = [(min(chunk, n - i), seed + k) for k, i in enumerate(range(0, n, chunk))]
    t0 = time.perf_counter()
    fields = map_tasks(_simulate_chunk, tasks, workers=2)
    frames, n_written = [], 0
    for k, f in enumerate(fields):
        meas = f.measurements.copy()
        rename = {hid: f"C{k:03d}{hid}" for hid in f.heliostats}  # unique names across chunks
        meas["heliostat_id"] = meas["heliostat_id"].map(rename)
        lat, lon, alt = enu_to_wgs84(meas["focal_spot_e_m"].to_numpy(), meas["focal_spot_n_m"].to_numpy(),
                                     meas["focal_spot_u_m"].to_numpy(), f.reference)
        h = {rename[hid]: v for hid, v in f.heliostats.items()}
        centers = {name: t["center_wgs84"] for name, t in f.targets.items()}
        frames.append(pd.DataFrame({
            "heliostat_id": meas["heliostat_id"],
            "timestamp": pd.to_datetime(meas["timestamp"], utc=True).dt.strftime("%Y-%m-%dT%H:%M:%SZ"),
            "sample_id": meas["measurement_id"],
            "sun_elevation": meas["sun_elevation_deg"], "sun_azimuth": meas["sun_azimuth_deg"],
            "axis_1_motor_position": meas["axis_1_steps"].astype(int),
            "axis_2_motor_position": meas["axis_2_steps"].astype(int),
            "target_name": meas["target_name"],
            "heliostat_lat": meas["heliostat_id"].map(lambda x: h[x].row["latitude_deg"]),
            "heliostat_lon": meas["heliostat_id"].map(lambda x: h[x].row["longitude_deg"]),
            "heliostat_alt": meas["heliostat_id"].map(lambda x: h[x].row["altitude_m"]),
            "focal_spot_lat": lat, "focal_spot_lon": lon, "focal_spot_alt": alt,
            "target_center_lat": meas["target_name"].map(lambda t: centers[t][0]),
            "target_center_lon": meas["target_name"].map(lambda t: centers[t][1]),
            "target_center_alt": meas["target_name"].map(lambda t: centers[t][2]),
            "temperature": meas["temperature_c"]}))
        for hid, v in h.items():
            d = out / "paint" / hid
            d.mkdir(parents=True, exist_ok=True)
            (d / f"{hid}-heliostat-properties.json").write_text(json_text(v.paint_properties))
            n_written += 1
        if k == 0:
            (out / "tower-measurements.json").write_text(json_text(tower_json(f)))
    log = pd.concat(frames, ignore_index=True)
    log.to_csv(out / "calibration_log.csv", index=False)
    info = {"heliostats": n_written, "measurements": int(len(log)),
            "simulate_s": round(time.perf_counter() - t0, 1)}
    (out / "done.json").write_text(json.dumps(info))
    return info


@dataclass
class Memory:
    """A process tree's memory [bytes]: summed RSS and summed PSS (module docstring)."""

    rss: int = 0
    pss: int = 0

    def peak(self, other: "Memory") -> "Memory":
        """Each figure's larger value (the two peaks need not fall on the same sample)."""
        return Memory(max(self.rss, other.rss), max(self.pss, other.pss))

    def gib(self) -> str:
        return f"{self.rss / 2**30:5.2f} GiB (PSS {self.pss / 2**30:5.2f})"


def _pss_bytes(pid: int) -> int:
    """A process's proportional set size (``Pss`` of /proc/PID/smaps_rollup); 0 if unreadable."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as fh:
            for line in fh:
                if line.startswith("Pss:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def _tree_memory(root_pid: int) -> Memory:
    """Summed RSS and PSS of a process and all its descendants (from /proc)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                parts = fh.read().rsplit(")", 1)[1].split()
            ppid = int(parts[1])
            rss[int(entry)] = int(parts[21]) * os.sysconf("SC_PAGE_SIZE")
            children.setdefault(ppid, []).append(int(entry))
        except (OSError, IndexError, ValueError):
            continue
    total, stack = Memory(), [root_pid]
    while stack:
        pid = stack.pop()
        if pid in rss:
            total = Memory(total.rss + rss[pid], total.pss + _pss_bytes(pid))
        stack.extend(children.get(pid, []))
    return total


def run_stage(args: list[str]) -> tuple[float, Memory]:
    """Run one heliocal command; return (wall seconds, the tree's peak :class:`Memory`)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen([HELIOCAL, *args, "--quiet"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    peak = Memory()
    stop = threading.Event()

    def sample():
        nonlocal peak
        while not stop.is_set():
            peak = peak.peak(_tree_memory(proc.pid))
            time.sleep(0.1)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    _, err = proc.communicate()
    stop.set()
    thread.join()
    if proc.returncode != 0:
        raise SystemExit(f"heliocal {' '.join(args)} failed: {err.strip()[-500:]}")
    return time.perf_counter() - t0, peak


#: Heliostats of a daily update (share of the field) and new rows of each.
UPDATE_SHARE, UPDATE_ROWS = 0.01, 5


def update_size(n_heliostats: int, requested: int | None = None) -> int:
    """Heliostats of the daily update: ``requested``, or :data:`UPDATE_SHARE` of the field's
    ``n_heliostats`` (at least one)."""
    n = max(1, round(UPDATE_SHARE * n_heliostats)) if requested is None else int(requested)
    if not 1 <= n <= n_heliostats:
        raise SystemExit(f"Error: --update-heliostats must be in [1, {n_heliostats}] (the "
                         f"field's heliostats). Got {n} instead.")
    return n


def split_update(field_dir: Path, n_update: int | None = None,
                 seed: int = 0) -> tuple[Path, Path, int]:
    """The field's log without the latest :data:`UPDATE_ROWS` rows of a seeded choice of
    :func:`update_size` heliostats (``base-<n>.csv``), and those rows (``update-<n>.csv``);
    cached beside the log."""
    log = pd.read_csv(field_dir / "calibration_log.csv")
    ids = np.sort(log["heliostat_id"].unique())
    n = update_size(len(ids), n_update)
    base, update = field_dir / f"base-{n}.csv", field_dir / f"update-{n}.csv"
    if not (base.exists() and update.exists()):
        chosen = set(np.random.default_rng(seed).choice(ids, n, replace=False))
        late = (log[log["heliostat_id"].isin(chosen)].sort_values("timestamp", kind="mergesort")
                .groupby("heliostat_id").tail(UPDATE_ROWS).index)
        log.drop(index=late).to_csv(base, index=False)
        log.loc[late].to_csv(update, index=False)
    return base, update, n


def phase_commands(args, field_dir: Path, wd: Path, base: Path, update: Path,
                   workers: int) -> dict[str, list[list[str]]]:
    """The heliocal commands of :func:`run_all`'s phases (``full``, ``update``, ``rerun``) on
    the work directory ``wd``, and ``update-cmd`` (``heliocal update``) on ``wd`` again, which
    :func:`run_all` has put back as the full phase left it: ``base`` and ``update`` are
    :func:`split_update`'s logs; ``args`` gives ``solver``, ``sweep_args`` and ``later``."""
    props = ["--properties", str(field_dir / "paint"), "--workdir", str(wd)]
    w = ["--workers", str(workers)]
    coarse = ["fit-coarse", "--workdir", str(wd), "--preset", "static-20", *w,
              "--solver", args.solver]
    later = [c for c in (["sweep", "--workdir", str(wd), "--study", "0", *w, *args.sweep_args.split()],
                         ["report", "--workdir", str(wd), *w]) if c[0] in args.later.split(",")]
    day = ["aim", "--workdir", str(wd), "--date", "2024-03-01", "--every", "10min",
           "--out", str(wd.parent / f"{wd.name}-aims.parquet"), "--json"]
    phases = {
        "full": [["ingest", str(base), *props], ["split-knn", "--workdir", str(wd)], coarse,
                 *later],
        "aim": [day],                 # a day of the field's aims with what the full method chose
        "update": [["ingest", str(update), *props, "--append"],
                   ["split-knn", "--workdir", str(wd), "--incremental"], [*coarse, "--incremental"],
                   *[[*c, "--incremental"] for c in later]],
        "rerun": [["split-knn", "--workdir", str(wd), "--incremental"],
                  [*coarse, "--incremental"], *[[*c, "--incremental"] for c in later]],
        "update-cmd": [["update", str(update), "--workdir", str(wd), *w]],
    }
    return phases


def run_all(args, field_dir: Path, info: dict, workers: int) -> None:
    """The full method, a daily update and a rerun on unchanged inputs, timed in one run."""
    base, update, n_update = split_update(field_dir, args.update_heliostats)
    wd = args.out / f"run-{args.heliostats}-all-w{workers}"
    copy = Path(f"{wd}-day0")         # the day before, for the update as one command
    stages = Path(f"{wd}-stages")     # where the stage-by-stage update's result goes then
    for folder in (wd, copy, stages):
        shutil.rmtree(folder, ignore_errors=True)
    phases = phase_commands(args, field_dir, wd, base, update, workers)
    print(f"update: {n_update} heliostats x {UPDATE_ROWS} new rows; workers={workers}", flush=True)
    table = []
    for phase, commands in phases.items():
        if phase == "update-cmd":     # the day before, back at the work directory's path
            wd.rename(stages)
            copy.rename(wd)
        total = 0.0
        for cmd in commands:
            wall, peak = run_stage(cmd)
            total += wall
            table.append((phase, cmd[0], wall, peak))
            print(f"  {phase:10s} {cmd[0]:11s} {wall:8.1f} s  peak {peak.gib()}",
                  flush=True)
        print(f"  {phase:10s} total       {total:8.1f} s", flush=True)
        if phase == "full":
            shutil.copytree(wd, copy)
    first = {stage: wall for phase, stage, wall, _ in table if phase == "full"}
    print(f"\n{info['heliostats']} heliostats, {workers} workers: phase, stage, wall, peak memory"
          " (rerun: share of the stage's first run)")
    for phase, stage, wall, peak in table:
        share = f"  {100 * wall / first[stage]:5.1f} %" if phase == "rerun" else ""
        print(f"{phase:10s} {stage:11s} {wall:8.1f} s  {peak.gib()}{share}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--heliostats", type=int, default=2000)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "field-bench")
    ap.add_argument("--hybrid-epochs", type=int, default=800)
    ap.add_argument("--stages", default="ingest,split-knn,fit-coarse,fit-hybrid,sweep,report")
    ap.add_argument("--workers", default="1,2", help="worker counts (--stages all: the last)")
    ap.add_argument("--solver", default="batched", help="fit-coarse --solver (batched or scipy)")
    ap.add_argument("--sweep-args", default="", help="extra options of the sweep stage")
    ap.add_argument("--later", default="sweep,report",
                    help="--stages all: the stages after fit-coarse in the full method, the "
                         "update and the rerun ('' leaves them out)")
    ap.add_argument("--update-heliostats", type=int, default=None,
                    help="--stages all: heliostats of the daily update, each with "
                         f"{UPDATE_ROWS} new rows (default {100 * UPDATE_SHARE:g} %% of the field, at "
                         "least one)")
    args = ap.parse_args()
    field_dir = args.out / f"field-{args.heliostats}"
    info = write_field(field_dir, args.heliostats)
    print(f"field: {info['heliostats']} heliostats, {info['measurements']} measurements "
          f"(simulated in {info['simulate_s']} s, cached in {field_dir})", flush=True)
    if args.stages == "all":
        run_all(args, field_dir, info, int(args.workers.split(",")[-1]))
        return
    stages = args.stages.split(",")
    results = {}
    sizes: dict[int, tuple[int, int, int]] = {}
    for workers in [int(w) for w in args.workers.split(",")]:
        wd = args.out / f"run-{args.heliostats}-w{workers}"
        if "ingest" in stages:  # a fresh workdir; later stages alone reuse the previous one
            shutil.rmtree(wd, ignore_errors=True)
        commands = {
            "ingest": ["ingest", str(field_dir / "calibration_log.csv"), "--properties",
                       str(field_dir / "paint"), "--workdir", str(wd)],
            "split-knn": ["split-knn", "--workdir", str(wd)],
            "fit-coarse": ["fit-coarse", "--workdir", str(wd), "--preset", "static-20",
                           "--workers", str(workers), "--solver", args.solver,
                           "--prior", "none"],
            "fit-hybrid": ["fit-hybrid", "--workdir", str(wd), "--weight-decay", "1e-3",
                           "--max-epochs", str(args.hybrid_epochs), "--workers", str(workers)],
            "pretrained-nn": ["fit-hybrid", "--workdir", str(wd), "--mode", "pretrained-nn",
                              "--workers", str(workers)],
            "sweep": ["sweep", "--workdir", str(wd), "--study", "0",
                      "--workers", str(workers), *args.sweep_args.split()],
            "plan": ["plan", "--workdir", str(wd), "--start", "2024-03-01", "--days", "7",
                     "--workers", str(workers)],
            "report": ["report", "--workdir", str(wd), "--workers", str(workers)],
            # fit-coarse without its rolling-origin evaluation: beside fit-coarse, the cost of
            # the next-day error (run it after fit-coarse; it replaces the fit's artifacts)
            "fit-coarse-no-rolling": ["fit-coarse", "--workdir", str(wd), "--preset",
                                      "static-20", "--workers", str(workers), "--solver",
                                      args.solver, "--rolling-origins", "0"],
            # fit-coarse with the field prior (issue 34): beside fit-coarse (--prior none), the
            # prior's cost in the same run (it replaces the fit's artifacts)
            "fit-coarse-prior": ["fit-coarse", "--workdir", str(wd), "--preset", "static-20",
                                 "--workers", str(workers), "--solver", args.solver,
                                 "--prior", "field"],
            # a day of the whole field: an aim every 10 minutes while the sun is up (one process)
            "aim": ["aim", "--workdir", str(wd), "--date", "2024-03-01", "--every", "10min",
                    "--out", str(wd / "aims-2024-03-01.parquet"), "--json"],
        }
        for stage in stages:
            wall, peak = run_stage(commands[stage])
            results[(stage, workers)] = (wall, peak)
            print(f"  workers={workers} {stage:11s} {wall:8.1f} s  "
                  f"{info['heliostats'] / wall:8.1f} heliostats/s  peak {peak.gib()}",
                  flush=True)
            if stage == "aim":
                aims = pd.read_parquet(wd / "aims-2024-03-01.parquet")
                print(f"  workers={workers} aim: {len(aims)} aims ({(aims['status'] == 'ok').sum()}"
                      f" ok), {len(aims) / wall:.0f} aims/s", flush=True)
            if stage == "report":
                rep = wd / "report"
                files = [f for f in rep.rglob("*") if f.is_file()]
                sizes[workers] = ((rep / "index.html").stat().st_size,
                                  sum(f.stat().st_size for f in files), len(files))
                print(f"  workers={workers} report/index.html {sizes[workers][0] / 2**20:.2f} MiB;"
                      f" report/ {sizes[workers][1] / 2**20:.1f} MiB in {sizes[workers][2]} files",
                      flush=True)
    print("\nstage        " + "".join(f"  wall w={w}   " for w in args.workers.split(","))
          + " speed-up  peak memory")
    ws = [int(w) for w in args.workers.split(",")]
    for stage in stages:
        walls = [results[(stage, w)][0] for w in ws]
        peak = Memory()
        for w in ws:
            peak = peak.peak(results[(stage, w)][1])
        line = f"{stage:12s} " + "".join(f"{w:9.1f} s   " for w in walls)
        if len(walls) > 1:
            line += f"  {walls[0] / walls[-1]:5.2f}x"
        line += f"   {peak.gib()}"
        if stage == "report" and sizes:
            index, total, n = sizes[ws[-1]]
            line += f"   index.html {index / 2**20:.2f} MiB, report/ {total / 2**20:.0f} MiB, {n} files"
        print(line)


if __name__ == "__main__":
    main()
