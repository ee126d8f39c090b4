"""Model files of ``fit-hybrid`` and ``sweep``: ``hybrid/<mode>/<HID>.pt`` and ``<HID>.json``.

The ``.pt`` file holds the networks' tensors (a state dict saved with :func:`torch.save`); the
``.json`` file holds the model's configuration and records the SHA-256 of the ``.pt`` file's bytes
(``weights_sha256``). Both are outputs of the stage's transaction
(:mod:`heliocal.pipeline.artifacts.transaction`), so they are committed together; :func:`read_model` reads
both through the stage's manifest and checks that the weights are the ones the configuration was
written with. Loading never runs code from a file: :func:`torch.load` with ``weights_only=True``
accepts tensors and plain containers only. :func:`read_model_config` makes the same checks but
for the tensors, without torch, for readers of the configuration alone (the report's GP
correction map, stored there: :mod:`heliocal.pipeline.models.gp_map`).
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import pickle
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

from ..errors import SchemaError, StageInputError
from .schemas import COARSE_PARAMS, HELIOSTATS, MEASUREMENTS, SPLIT
from .paths import artifact_path
from .store import artifact_present, check_fresh, committed_fingerprint
from .manifests import CommittedWorkdir

__all__ = ["model_files", "model_stage", "write_model", "rewrite_model_config", "CheckedModel",
           "read_model_config", "read_model", "fine_model_inputs", "check_fine_model_inputs"]


def model_files(mode: str, heliostat_id: str) -> tuple[str, str]:
    """(config, weights) paths of a model relative to the work directory; an id that is not a plain
    file name is refused (:func:`heliocal.pipeline.artifacts.store.safe_name`)."""
    from .paths import safe_name

    hid = safe_name(heliostat_id, f"hybrid/{mode}")
    return f"hybrid/{mode}/{hid}.json", f"hybrid/{mode}/{hid}.pt"


def write_model(txn, mode: str, heliostat_id: str, state: Mapping, config: dict) -> None:
    """Stage one model (weights and configuration) in transaction ``txn``."""
    import torch

    buffer = io.BytesIO()
    torch.save(dict(state), buffer)
    weights = buffer.getvalue()
    cfg_rel, pt_rel = model_files(mode, heliostat_id)
    config = {**config, "weights_sha256": hashlib.sha256(weights).hexdigest()}
    txn.write_bytes(pt_rel, weights)
    txn.write_bytes(cfg_rel, json.dumps(config, indent=1, sort_keys=True).encode())


def rewrite_model_config(txn, model: "CheckedModel", mode: str, heliostat_id: str,
                         config: dict) -> None:
    """Stage a committed model (``model``, read by :func:`read_model_config` from the run
    ``txn`` follows) again in ``txn`` with the configuration ``config`` and its weights as they
    are: the weights file is carried over unchanged when the previous run committed it, so its
    tensors are neither loaded nor saved again; the configuration records the same
    ``weights_sha256``."""
    cfg_rel, pt_rel = model_files(mode, heliostat_id)
    txn.carry_over([pt_rel])
    if pt_rel not in txn.files:          # not the previous run's file: stage its bytes
        txn.write_bytes(pt_rel, model.weights)
    config = {**config, "weights_sha256": hashlib.sha256(model.weights).hexdigest()}
    txn.write_bytes(cfg_rel, json.dumps(config, indent=1, sort_keys=True).encode())


def _short(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return (text[:160] + "...") if len(text) > 160 else text or type(exc).__name__


def _check_gp_shapes(state: Mapping, path: Path, hint: str) -> None:
    """A GP correction's tensors: training inputs (n, D) and their residuals (n, 2)."""
    x, y = state.get("gp.x_train"), state.get("gp.y_train_mrad")
    ok = (x is not None and y is not None and getattr(x, "dim", lambda: 0)() == 2
          and getattr(y, "dim", lambda: 0)() == 2 and y.shape[1] == 2 and x.shape[0] == y.shape[0])
    if not ok:
        raise SchemaError(f"{path} does not hold a heliocal GP correction (training inputs (n, D) "
                          f"and residuals (n, 2)); rerun {hint}")


def _check_shapes(state: Mapping, cfg: dict, path: Path, hint: str) -> None:
    """The tensors form a chain of layers, and match the configuration's layer sizes (a GP
    correction: :func:`_check_gp_shapes`)."""
    if cfg.get("mode") == "gp":
        return _check_gp_shapes(state, path, hint)
    n = len([k for k in state if k.endswith(".weight")])
    try:
        shapes = [(tuple(state[f"layers.{k}.weight"].shape), tuple(state[f"layers.{k}.bias"].shape))
                  for k in range(n)]
    except (KeyError, AttributeError) as exc:
        raise SchemaError(f"{path} does not hold heliocal network weights (missing {exc}); rerun "
                          f"{hint}") from None
    ok = n > 0 and all(len(w) == 3 and b == (w[0], w[1]) for w, b in shapes)
    ok = ok and all(shapes[k][0][1] == shapes[k + 1][0][2] for k in range(n - 1))
    sizes = cfg.get("sizes")
    if ok and sizes is not None:
        ok = list(sizes) == [shapes[0][0][2]] + [w[1] for w, _ in shapes]
    if not ok:
        raise SchemaError(f"{path} holds weights of other layer sizes than its configuration "
                          f"{path.with_suffix('.json').name} describes; rerun {hint}")


def model_stage(workdir, mode: str) -> tuple[str, str]:
    """(stage, command in backticks) that writes the models of ``mode``: ``selected`` is the
    sweep's (``hybrid/selected/``), every other mode ``fit-hybrid --mode <mode>``'s."""
    if mode == "selected":
        return "sweep", f"`heliocal sweep --workdir {workdir}`"
    return "fit-hybrid", f"`heliocal fit-hybrid --workdir {workdir} --mode {mode}`"


@dataclass(frozen=True)
class CheckedModel:
    """A committed model's files, read through the stage's manifest and checked as far as that
    needs no torch (:func:`read_model_config`).

    Attributes
    ----------
    config : the parsed configuration; config_path, weights_path : the files on disk.
    weights : the weights file's bytes (the SHA-256 its configuration records).
    """

    config: dict
    config_path: Path
    weights_path: Path
    weights: bytes


def read_model_config(workdir, stage: str, mode: str, heliostat_id: str, *,
                      hint: str) -> CheckedModel | None:
    """A committed model's configuration and weights' bytes, or ``None`` if ``stage`` committed
    none: every check of :func:`read_model` but the weights' content (their tensors and shapes),
    without importing torch.

    Raises
    ------
    StageInputError, SchemaError : as :func:`read_model`.
    """
    wd = CommittedWorkdir.of(workdir)
    cfg_rel, pt_rel = model_files(mode, heliostat_id)
    m = wd.manifest(stage)
    listed = m is not None and cfg_rel in m.files and pt_rel in m.files
    if not listed:
        for rel in (cfg_rel, pt_rel):
            # present but not committed (and not just being removed by the last commit): refused
            if os.path.lexists(wd.root / rel) and not (m is not None and m.removes(rel)):
                wd.read(stage, rel, hint=hint)
        return None
    cfg_file = wd.read(stage, cfg_rel, hint=hint)
    pt_file = wd.read(stage, pt_rel, hint=hint)
    try:
        cfg = json.loads(cfg_file.data.decode("utf-8"))
        if not isinstance(cfg, dict):
            raise ValueError("not a JSON object")
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise SchemaError(f"{cfg_file.path} is not a valid model configuration ({_short(exc)}); "
                          f"rerun {hint}") from None
    _check_owner(cfg, cfg_file.path, heliostat_id, mode, hint)
    if cfg.get("weights_sha256") != hashlib.sha256(pt_file.data).hexdigest():
        raise SchemaError(f"{pt_file.path} is not the weights file its configuration "
                          f"{cfg_file.path.name} was written with (weights_sha256 differs); rerun "
                          f"{hint}")
    if not pt_file.data:
        raise SchemaError(f"{pt_file.path} is empty, not a torch model file; rerun {hint}")
    return CheckedModel(cfg, cfg_file.path, pt_file.path, pt_file.data)


def read_model(workdir, stage: str, mode: str, heliostat_id: str, *,
               hint: str) -> tuple[dict, dict] | None:
    """(configuration, state dict) of a committed model, or ``None`` if ``stage`` committed none.

    ``workdir`` is the work directory or its :class:`CommittedWorkdir`.

    Raises
    ------
    StageInputError : a model file exists but no complete run of ``stage`` wrote it.
    SchemaError : a file was changed after the run, is empty or corrupt, holds something other
        than tensors, the weights are not the ones the configuration records, or the
        configuration is another heliostat's or mode's (files swapped). Every message names the
        file and the command that writes it again (``hint``).
    """
    import torch

    found = read_model_config(workdir, stage, mode, heliostat_id, hint=hint)
    if found is None:
        return None
    path = found.weights_path
    try:
        state = torch.load(io.BytesIO(found.weights), weights_only=True)
    except pickle.UnpicklingError as exc:
        raise SchemaError(
            f"{path} was refused: it holds objects other than tensors (heliocal loads "
            f"model files with weights_only=True and never runs code from them: "
            f"{_short(exc).split('.')[0]}); delete it and rerun {hint}") from None
    except (RuntimeError, EOFError, ValueError, OSError, zipfile.BadZipFile, KeyError,
            AttributeError, TypeError) as exc:
        raise SchemaError(f"{path} is not a readable torch model file (truncated or "
                          f"corrupt: {_short(exc)}); rerun {hint}") from None
    if not isinstance(state, dict):
        raise SchemaError(f"{path} does not hold a state dict of tensors; rerun {hint}")
    _check_shapes(state, found.config, path, hint)
    return found.config, state


#: Modes whose configuration names another folder than its own (the sweep's selected model is a
#: hybrid or a pretrained-nn model; its ``mode`` says which).
_ANY_MODE = {"selected"}


def _check_owner(cfg: dict, path: Path, heliostat_id: str, mode: str, hint: str) -> None:
    """The configuration is this heliostat's, of this folder's mode: a pair of model files copied
    over another heliostat's (the manifest updated to match) is refused, not aimed with."""
    owner = cfg.get("heliostat_id")
    if owner != heliostat_id:
        raise SchemaError(f"{path} is the model of heliostat {owner!r}, not {heliostat_id!r} (its "
                          "files were replaced by another heliostat's, and the manifest with "
                          f"them); rerun {hint}, which writes {heliostat_id}'s model again")
    if mode not in _ANY_MODE and cfg.get("mode") != mode:
        raise SchemaError(f"{path} is a {cfg.get('mode')!r} model, not {mode!r} (its files were "
                          f"replaced by another mode's); rerun {hint}")


def fine_model_inputs(workdir: Path) -> dict:
    """label -> committed content fingerprint of every input a fine model is made from (the labels
    its run recorded: the artifacts it read)."""
    out = {}
    for label, schema in (("measurements", MEASUREMENTS), ("heliostats", HELIOSTATS),
                          ("coarse_params", COARSE_PARAMS), ("split", SPLIT)):
        fp = committed_fingerprint(workdir, schema)
        if fp is not None:
            out[label] = fp
    return out


def check_fine_model_inputs(workdir: Path) -> None:
    """Raise :class:`StageInputError` unless fit-coarse's parameters exist and are fresh with
    respect to the measurements, heliostats and (if present) the split."""
    if not artifact_present(workdir, COARSE_PARAMS):
        raise StageInputError(f"{artifact_path(workdir, COARSE_PARAMS)} is missing: run "
                              f"`heliocal fit-coarse --workdir {workdir}` first")
    upstream = {"measurements": MEASUREMENTS, "heliostats": HELIOSTATS}
    if artifact_present(workdir, SPLIT):
        upstream["split"] = SPLIT
    check_fresh(workdir, COARSE_PARAMS, upstream)
