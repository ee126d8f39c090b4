"""The fine model's network: its configuration, the feature encoder (motor steps and time to
features) and the small MLP (initialisation, forward pass, flat <-> per-layer state).
"""

from __future__ import annotations
import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence
import numpy as np
import pandas as pd
import torch
from ..errors import InputError
from ..physics.parameters import PARAMETER_NAMES, HeliostatSpec
from .coarse import parameter_kind
from ..vocabulary import FineMode

__all__ = [
    "MODES",
    "OUTPUT_SCALE",
    "FeatureEncoder",
    "init_mlp",
    "mlp_forward",
    "output_scales",
    "mlp_columns",
    "flatten_layers",
    "layer_views",
    "layers_to_state",
    "state_to_layers",
    "Layers",
]


#: Modes of ``fit-hybrid``.
MODES = FineMode.values()


#: Output scale per parameter kind: one unit of network output is this deviation. Angles [rad],
#: translations [m], actuator lengths [m]; increments relative to the nominal increment.
OUTPUT_SCALE = {"angle": 1e-3, "translation": 1e-2, "length": 3e-4, "increment": 1e-3}


def output_scales(free: torch.Tensor, nominal: torch.Tensor, factor: float = 1.0) -> torch.Tensor:
    """Deviation per unit of network output for each free parameter, shape (P,).

    Parameters
    ----------
    free : bool (28,) free parameters (their order is the network's output order).
    nominal : (28,) nominal parameters (increments scale relative to them).
    factor : multiplier of :data:`OUTPUT_SCALE`.
    """
    scales = []
    for i in torch.nonzero(free).flatten().tolist():
        kind = parameter_kind(PARAMETER_NAMES[i])
        s = OUTPUT_SCALE[kind]
        if kind == "increment":
            s *= abs(float(nominal[i])) or 1.0
        scales.append(s * factor)
    return torch.tensor(scales, dtype=torch.float64)


# ------------------------------------------------------------------------------------------------
# inputs
# ------------------------------------------------------------------------------------------------
def _epoch_seconds(timestamps) -> np.ndarray:
    ts = pd.to_datetime(pd.Series(timestamps), utc=True)
    out = (ts - pd.Timestamp("1970-01-01", tz="UTC")).dt.total_seconds().to_numpy(np.float64)
    return out


def _month_position(timestamps) -> np.ndarray:
    """Month as a continuous position in the year, in [0, 12)."""
    ts = pd.to_datetime(pd.Series(timestamps), utc=True)
    days = np.where(ts.dt.is_leap_year, 366.0, 365.0)
    frac = (ts.dt.day_of_year.to_numpy(np.float64) - 1.0
            + (ts.dt.hour * 3600 + ts.dt.minute * 60 + ts.dt.second).to_numpy(np.float64) / 86400.0)
    return 12.0 * frac / days


@dataclass
class FeatureEncoder:
    """The fine network's input encoding (paper 000 section 3.3); all constants are stored so
    that :meth:`to_dict` / :meth:`from_dict` rebuild it exactly.

    Attributes
    ----------
    step_scale : (2,) divisor of the steps [steps] (the actuators' maximum steps).
    bands : Fourier frequency bands.
    t0_s, t1_s : first and last measurement time [s since 1970-01-01 UTC] (eq. 1).
    env : env column names (without ``env_``); env_mean, env_std : their standardisation.
    fill_time_s : time used for rows without a timestamp (the median time).
    """

    step_scale: list
    bands: tuple
    t0_s: float
    t1_s: float
    fill_time_s: float
    env: tuple = ()
    env_mean: list = field(default_factory=list)
    env_std: list = field(default_factory=list)
    decay: float = 0.0

    @property
    def n_features(self) -> int:
        return 2 + 4 * len(self.bands) + 4 + len(self.env)

    @classmethod
    def fit(cls, rows: pd.DataFrame, spec: HeliostatSpec, bands: Sequence[float],
            env: Sequence[str] = (), decay: float = 0.0) -> "FeatureEncoder":
        """Normalisation constants from all rows of one heliostat (inputs only)."""
        steps = rows[["axis_1_steps", "axis_2_steps"]].to_numpy(np.float64)
        scale = []
        for axis in (0, 1):
            hi = float(spec.max_steps[axis])
            if not math.isfinite(hi) or hi <= 0:
                hi = float(np.nanmax(np.abs(steps[:, axis]))) or 1.0
            scale.append(hi)
        t = _epoch_seconds(rows["timestamp"]) if "timestamp" in rows else np.array([np.nan])
        finite = t[np.isfinite(t)]
        if len(finite):
            t0, t1, fill = float(finite.min()), float(finite.max()), float(np.median(finite))
        else:
            t0, t1, fill = 0.0, 1.0, 0.0
        means, stds = [], []
        for name in env:
            col = f"env_{name}"
            if col not in rows.columns:
                avail = sorted(c[4:] for c in rows.columns if c.startswith("env_"))
                raise InputError(f"measurements.parquet has no column {col!r} for --env "
                                 f"{name}; available env columns: {avail or 'none'}")
            v = pd.to_numeric(rows[col], errors="coerce").to_numpy(np.float64)
            v = v[np.isfinite(v)]
            means.append(float(v.mean()) if len(v) else 0.0)
            stds.append(float(v.std()) if len(v) and v.std() > 0 else 1.0)
        return cls(scale, tuple(float(b) for b in bands), t0, t1, fill, tuple(env), means, stds,
                   float(decay))

    def context(self, timestamps, env_values: np.ndarray | None = None) -> torch.Tensor:
        """Time, season and env features (N, 4 + E) for UTC ``timestamps`` (NaT -> median time)
        and ``env_values`` (N, E) raw values (NaN -> the mean)."""
        t = _epoch_seconds(timestamps)
        missing = ~np.isfinite(t)
        if missing.any():
            t = np.where(missing, self.fill_time_s, t)
        span = self.t1_s - self.t0_s
        dt = (t - self.t0_s) / span if span > 0 else np.zeros_like(t)
        ts = pd.to_datetime(pd.Series(t), unit="s", utc=True)
        month = _month_position(ts)
        cols = [np.sin(math.pi * dt), np.cos(math.pi * dt),
                np.sin(2 * math.pi * month / 12.0), np.cos(2 * math.pi * month / 12.0)]
        if self.env:
            env_values = np.asarray(env_values, np.float64).reshape(len(t), len(self.env))
            z = (env_values - np.asarray(self.env_mean)) / np.asarray(self.env_std)
            cols += list(np.nan_to_num(z, nan=0.0).T)
        return torch.tensor(np.stack(cols, axis=-1), dtype=torch.float64)

    def context_from_frame(self, rows: pd.DataFrame) -> torch.Tensor:
        env = rows[[f"env_{e}" for e in self.env]].apply(pd.to_numeric, errors="coerce") \
            .to_numpy(np.float64) if self.env else None
        return self.context(rows["timestamp"], env)

    def step_features(self, steps: torch.Tensor) -> torch.Tensor:
        """Normalised steps and their Fourier features (..., 2 + 4 B), differentiable."""
        a = steps / torch.as_tensor(self.step_scale, dtype=torch.float64)
        feats = [a]
        for b in self.bands:
            amp = b ** -self.decay if self.decay else 1.0
            feats += [amp * torch.sin(2 * math.pi * b * a), amp * torch.cos(2 * math.pi * b * a)]
        return torch.cat(feats, dim=-1)

    def encode(self, steps: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """All inputs (..., N, n_features) from steps (..., N, 2) and context (N, 4 + E)."""
        sf = self.step_features(steps)
        return torch.cat([sf, context.expand(*sf.shape[:-1], context.shape[-1])], dim=-1)

    def to_dict(self) -> dict:
        return {"step_scale": list(map(float, self.step_scale)), "bands": list(self.bands),
                "t0_s": self.t0_s, "t1_s": self.t1_s, "fill_time_s": self.fill_time_s,
                "env": list(self.env), "env_mean": list(self.env_mean),
                "env_std": list(self.env_std), "decay": float(self.decay)}

    @classmethod
    def from_dict(cls, d: Mapping) -> "FeatureEncoder":
        return cls(list(d["step_scale"]), tuple(d["bands"]), float(d["t0_s"]), float(d["t1_s"]),
                   float(d["fill_time_s"]), tuple(d.get("env", ())), list(d.get("env_mean", ())),
                   list(d.get("env_std", ())), float(d.get("decay", 0.0)))


# ------------------------------------------------------------------------------------------------
# the batched self-normalizing MLP
# ------------------------------------------------------------------------------------------------
Layers = list  # [(W (M, out, in), b (M, out)), ...]


def init_mlp(sizes: Sequence[int], seeds: Sequence[int], *, zero_last: bool = True) -> Layers:
    """LeCun-normal weights (std 1/sqrt(fan_in)), zero biases, for ``len(seeds)`` members.

    Member ``m`` draws from its own ``torch.Generator`` seeded with ``seeds[m]`` (layer by layer),
    so a member's initial weights do not depend on the other members. With ``zero_last`` the
    output layer is all zeros (the untrained hybrid equals its base model exactly).
    """
    per_member = []
    for seed in seeds:
        g = torch.Generator().manual_seed(int(seed))
        layers = []
        for k, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
            w = torch.randn(fan_out, fan_in, generator=g, dtype=torch.float64) / math.sqrt(fan_in)
            if zero_last and k == len(sizes) - 2:
                w = torch.zeros_like(w)
            layers.append((w, torch.zeros(fan_out, dtype=torch.float64)))
        per_member.append(layers)
    return [(torch.stack([m[k][0] for m in per_member]), torch.stack([m[k][1] for m in per_member]))
            for k in range(len(sizes) - 1)]


def mlp_forward(layers: Layers, x: torch.Tensor) -> torch.Tensor:
    """Apply the member networks: x (M, N, in) or (N, in) -> (M, N, out). SELU between layers,
    linear output."""
    return mlp_columns(layers, x).transpose(1, 2)


def mlp_columns(layers: Layers, x: torch.Tensor) -> torch.Tensor:
    """:func:`mlp_forward` with the rows as columns: returns (M, out, N).

    Activations are kept as (M, width, N) so every layer is one batched ``W @ H`` whose long
    dimension (the N rows) is contiguous; the row-major (M, N, width) layout makes the batched
    matrix products of a narrow network several times slower.
    """
    w0, b0 = layers[0]
    h = torch.matmul(w0, x.transpose(-1, -2)) + b0.unsqueeze(-1)       # (M, width, N)
    for w, b in layers[1:]:
        h = torch.baddbmm(b.unsqueeze(-1), w, torch.nn.functional.selu(h))
    return h


def flatten_layers(layers: Layers) -> torch.Tensor:
    """All weights and biases of each member in one row: (M, T)."""
    m = layers[0][0].shape[0]
    return torch.cat([t.reshape(m, -1) for w, b in layers for t in (w, b)], dim=1)


def layer_views(theta: torch.Tensor, like: Layers) -> Layers:
    """Views of the flat (M, T) tensor shaped like ``like`` (inverse of :func:`flatten_layers`).

    Training keeps one flat leaf tensor so that the optimiser, the weight-decay penalty, the
    gradient clean-up and the best-state bookkeeping are one operation each, not one per layer.
    """
    views, offset = [], 0
    for w, b in like:
        (_, o, i), nb = w.shape, b.shape[1]
        views.append((theta[:, offset:offset + o * i].view(-1, o, i),
                      theta[:, offset + o * i:offset + o * i + nb]))
        offset += o * i + nb
    return views


def layers_to_state(layers: Layers, member: int | None = None) -> dict:
    state = {}
    for k, (w, b) in enumerate(layers):
        state[f"layers.{k}.weight"] = (w if member is None else w[member:member + 1]).detach().clone()
        state[f"layers.{k}.bias"] = (b if member is None else b[member:member + 1]).detach().clone()
    return state


def state_to_layers(state: Mapping) -> Layers:
    n = len([k for k in state if k.endswith(".weight")])
    return [(state[f"layers.{k}.weight"].to(torch.float64), state[f"layers.{k}.bias"].to(torch.float64))
            for k in range(n)]
