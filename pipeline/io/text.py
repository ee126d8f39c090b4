"""Text files as ``ingest`` meets them: encodings (UTF-8 with or without BOM, Latin-1), CSV
delimiters, JSON objects, and short quotes of bad values for error messages.
"""

from __future__ import annotations

import contextlib
import json
import logging
from pathlib import Path

from ..errors import InputError

__all__ = [
    "decode_text",
    "TEXT_HEAD_BYTES",
    "open_csv_text",
    "guess_delimiter",
    "shorten",
    "load_json",
]

log = logging.getLogger("heliocal.ingest")


def guess_delimiter(header: str) -> str:
    return max(";\t|", key=header.count)


def shorten(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:160]


def load_json(path: Path, what: str):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: {what} is not UTF-8 text; restore the original file") from exc
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: {what} is not valid JSON (line {exc.lineno}: {exc.msg}); "
                         "restore the original file") from exc


def decode_text(path: Path, raw: bytes) -> str:
    """Decode a CSV's bytes as UTF-8 (with or without BOM) or raise a one-line InputError."""
    if not raw.strip():
        raise InputError(f"{path}: the file is empty; give a calibration log with a header row "
                         "and one row per measurement")
    if b"\0" in raw[:65536]:
        raise InputError(f"{path}: binary data, not a CSV text file; give a CSV (comma-separated, "
                         "UTF-8) or Parquet calibration log")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = raw[:exc.start].count(b"\n") + 1
        raise InputError(f"{path}: not UTF-8 text (line {line}, byte {exc.start}); re-save the log "
                         "as UTF-8 CSV") from exc


TEXT_HEAD_BYTES = 65536


@contextlib.contextmanager
def open_csv_text(path: Path):
    """The CSV as UTF-8 text, read as a stream; the checks of :func:`decode_text` without
    holding the file: its first 64 KiB are checked for binary data and blankness up front, and a
    decoding error anywhere is reported by :func:`decode_text` (which then reads the file)."""
    with open(path, "rb") as fh:
        head = fh.read(TEXT_HEAD_BYTES + 1)
    if (not head.strip() and len(head) <= TEXT_HEAD_BYTES) or b"\0" in head[:TEXT_HEAD_BYTES]:
        decode_text(path, head)
    try:
        with open(path, encoding="utf-8-sig", newline="") as text:
            yield text
    except UnicodeDecodeError:
        decode_text(path, path.read_bytes())  # raises the InputError naming line and byte
        raise  # pragma: no cover - Python's decoder and decode_text agree
