"""Benchmark: one heliostat's static-28 coarse fit on 300 measurements, exact vs finite differences.

Both fits run in the same process, alternating, on the same synthetic heliostat (Jülich type,
known deviations of every free parameter, 0.2 mrad focal-spot noise). Prints the median wall
time of each and their ratio. Usage::

    .venv/bin/python benchmarks/coarse_fit.py [--repeats 7] [--measurements 300]

The fit starts from the nominal geometry (robust start off): the timed part is the
Levenberg-Marquardt solve (MINPACK) with its Jacobian.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from heliocal.pipeline.models.coarse import MeasurementBatch, fit_heliostat, normal_errors_mrad
from heliocal.pipeline.physics.parameters import HeliostatSpec, nominal_parameters
from heliocal.pipeline.physics.kinematics import forward_kinematics, inverse_kinematics
from heliocal.pipeline.physics.metrics import reflect

ROW = {
    "heliostat_id": "BENCH", "kinematic_type": "juelich", "actuator_type": "linear",
    "heliostat_e_m": 0.9, "heliostat_n_m": 209.6, "heliostat_u_m": 1.7,
    "concentrator_translation_n_m": 0.175,
    "axis_1_increment": 154166.6667, "axis_1_initial_stroke_length_m": 0.075676,
    "axis_1_offset_m": 0.335308, "axis_1_pivot_radius_m": 0.338095,
    "axis_1_initial_angle_rad": -1.557136, "axis_1_clockwise": False,
    "axis_1_min_steps": 0.0, "axis_1_max_steps": 69001.0,
    "axis_2_increment": 154166.6667, "axis_2_initial_stroke_length_m": 0.078387,
    "axis_2_offset_m": 0.340771, "axis_2_pivot_radius_m": 0.3191,
    "axis_2_initial_angle_rad": 0.937086, "axis_2_clockwise": True,
    "axis_2_min_steps": 0.0, "axis_2_max_steps": 75454.0,
}


def make_data(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    spec = HeliostatSpec.from_row(ROW)
    nominal = nominal_parameters(ROW)
    dev = torch.tensor([0.01] * 18 + [300.0, 5e-4, 5e-4, 5e-4, 0.005] * 2, dtype=torch.float64)
    truth = nominal + dev * torch.randn(28, generator=g, dtype=torch.float64) * 0.3
    az = (torch.rand(4 * n, generator=g, dtype=torch.float64) - 0.5) * 3.0  # +-86 deg
    el = 0.25 + 0.8 * torch.rand(4 * n, generator=g, dtype=torch.float64)
    sun = torch.stack([torch.cos(el) * torch.sin(az), -torch.cos(el) * torch.cos(az), torch.sin(el)], -1)
    aim = torch.tensor([0.0, -3.2, 36.0], dtype=torch.float64) \
        + torch.randn(4 * n, 3, generator=g, dtype=torch.float64) * torch.tensor([1.0, 0.0, 1.0])
    steps = inverse_kinematics(truth, spec, sun, aim)
    ok = torch.isfinite(steps).all(-1).nonzero().squeeze(-1)[:n]
    steps, sun, aim = steps[ok].round(), sun[ok], aim[ok]
    normal, position = forward_kinematics(truth, spec, steps)
    beam = reflect(-sun, normal)
    distance = torch.linalg.vector_norm(aim - position, dim=-1, keepdim=True)
    noise = 0.2e-3 * distance * torch.randn(len(ok), 3, generator=g, dtype=torch.float64)
    spot = position + distance * beam + noise
    import numpy as np

    m = len(ok)
    data = MeasurementBatch(np.array([str(i) for i in range(m)]), steps, sun, spot,
                            aim.clone(), torch.tensor([[0.0, 1.0, 0.0]]).double().expand(m, 3))
    return spec, nominal, data


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--measurements", type=int, default=300)
    ap.add_argument("--preset", default="static-28")
    args = ap.parse_args()
    torch.set_num_threads(1)
    spec, nominal, data = make_data(args.measurements)
    times = {"exact": [], "2-point": []}
    fits = {}
    for mode in times:  # warm-up
        fit_heliostat(spec, nominal, data, args.preset, loss="linear", robust_start="never", jacobian=mode)
    for _ in range(args.repeats):
        for mode in times:
            t0 = time.perf_counter()
            fits[mode] = fit_heliostat(spec, nominal, data, args.preset, loss="linear",
                                       robust_start="never", jacobian=mode)
            times[mode].append(time.perf_counter() - t0)
    print(f"{args.preset} fit on {args.measurements} measurements, {args.repeats} repeats "
          "(median wall time, single thread):")
    for mode, ts in times.items():
        err = normal_errors_mrad(fits[mode].params, spec, data).mean().item()
        print(f"  {mode:8s} Jacobian: {statistics.median(ts) * 1000:8.1f} ms  "
              f"({fits[mode].iterations} Jacobians, mean error {err:.4f} mrad)")
    ratio = statistics.median(times["2-point"]) / statistics.median(times["exact"])
    print(f"  speed-up exact / finite differences: {ratio:.1f}x")


if __name__ == "__main__":
    main()
