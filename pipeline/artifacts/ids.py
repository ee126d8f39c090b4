"""What a heliostat id may be: the rule every artifact's ``heliostat_id`` follows (ids become file
names, so they must be safe and portable as such), why an id breaks it, and a valid id close to
a bad one. :mod:`.schemas` re-exports these names.
"""

from __future__ import annotations

import re

__all__ = ["HELIOSTAT_ID_RE", "HELIOSTAT_ID_RULE", "WINDOWS_RESERVED_NAMES",
           "heliostat_id_problem", "suggest_heliostat_id"]

#: What a heliostat id may be. Ids become file names (``hybrid/<mode>/<id>.pt``, report figures),
#: so ingest keeps only ids that are safe and portable as such: 1 to 64 ASCII letters, digits,
#: ``_``, ``-`` and ``.``, the first a letter, digit or ``_`` (not ``.``: hidden files, ``..``;
#: not ``-``: read as an option on a command line).
HELIOSTAT_ID_RE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")
HELIOSTAT_ID_RULE = ("1-64 ASCII letters, digits, '_', '-' or '.', starting with a letter, digit "
                     "or '_'")


#: Device names Windows reserves in every folder, in any case and also with an extension
#: (``NUL.txt``): a file of that name cannot be made there, so they are not portable ids.
WINDOWS_RESERVED_NAMES = frozenset(["CON", "PRN", "AUX", "NUL", *(f"COM{i}" for i in range(1, 10)),
                                    *(f"LPT{i}" for i in range(1, 10))])


def _reserved_stem(hid: str) -> str | None:
    """The Windows device name ``hid`` is (its part before the first '.'), if any."""
    stem = hid.split(".", 1)[0]
    return stem if stem.upper() in WINDOWS_RESERVED_NAMES else None


def heliostat_id_problem(hid) -> str | None:
    """Why ``hid`` is not a valid heliostat id (see :data:`HELIOSTAT_ID_RE` and
    :data:`WINDOWS_RESERVED_NAMES`), or ``None``."""
    if not isinstance(hid, str):
        return f"it is a {type(hid).__name__}, not text"
    if HELIOSTAT_ID_RE.fullmatch(hid):
        stem = _reserved_stem(hid)
        if stem is None:
            return None
        return (f"{stem!r} is a device name Windows reserves (CON, PRN, AUX, NUL, COM1-9, "
                "LPT1-9), so no file can have that name there")
    if len(hid) > 64:
        return f"it has {len(hid)} characters, more than 64"
    if hid[:1] in (".", "-"):
        return f"it starts with {hid[0]!r}"
    bad = sorted({c for c in hid if not (c.isascii() and (c.isalnum() or c in "_.-"))})
    return "it contains " + ", ".join(repr(c) for c in bad[:5]) + (" ..." if len(bad) > 5 else "")


def suggest_heliostat_id(hid: str) -> str:
    """A valid id close to ``hid``: other characters become ``_``, leading ``.``/``-``/``_`` runs
    are dropped, cut to 64 characters (``"../../x/pwned"`` -> ``"x_pwned"``)."""
    text = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(hid))
    text = re.sub(r"^[._-]+", "", text)[:64]
    stem = _reserved_stem(text)
    if stem is not None:  # CON -> CON_, NUL.txt -> NUL_.txt
        text = (stem + "_" + text[len(stem):])[:64]
    return text or "H1"
