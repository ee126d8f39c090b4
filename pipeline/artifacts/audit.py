"""What in a work directory heliocal refuses to follow or read (``heliocal info DIR`` lists it):
symbolic links, FIFOs, sockets and devices anywhere in the folder, and manifests that are not
valid (a run id or file list that would lead outside the folder, cut or non-JSON text).

A work directory holds only regular files and folders that heliocal wrote; anything else was
planted or made by hand. The readers and writers refuse each such entry when they meet it
(:func:`~heliocal.pipeline.artifacts.paths.confined`, :func:`~heliocal.pipeline.artifacts.paths.open_regular`);
this module finds all of them at once, without following any link.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from ..errors import UnsafePathError
from .manifests import invalid_manifests
from .paths import is_real_dir, kind_of

__all__ = ["hostile_entries", "refuse_links"]


def _links_and_special_files(root: Path) -> list[dict]:
    out = []
    for folder, dirs, files in os.walk(root, followlinks=False):
        for name in sorted(dirs + files):
            path = Path(folder) / name
            try:
                mode = os.lstat(path).st_mode
            except OSError:
                continue
            if stat.S_ISDIR(mode) or stat.S_ISREG(mode):
                continue
            what = kind_of(mode)
            if stat.S_ISLNK(mode):
                try:
                    what += f" to {os.readlink(path)}"
                except OSError:
                    pass
            out.append({"path": str(path), "problem": f"{what}: heliocal neither follows nor reads "
                                                       "it; replace it by the file itself or "
                                                       "remove it"})
        dirs[:] = sorted(d for d in dirs if not os.path.islink(Path(folder) / d))
    return out


def hostile_entries(root: str | os.PathLike) -> list[dict]:
    """Every entry of ``root`` (walked without following links) that is not a regular file or a
    folder, and every manifest :func:`~heliocal.pipeline.artifacts.manifests.load_manifest`
    refuses, as ``{"path", "problem"}`` sorted by path."""
    root = Path(root)
    found = {e["path"]: e for e in _links_and_special_files(root)}
    for folder in [root, root / "report"]:
        if not is_real_dir(folder):
            continue
        for exc in invalid_manifests(folder):
            found.setdefault(str(exc.path), {"path": str(exc.path),
                                             "problem": f"not a valid manifest ({exc.why}); its "
                                                        f"stage replaces it: rerun `heliocal "
                                                        f"{exc.stage}`"})
    return [found[k] for k in sorted(found)]


def refuse_links(root: str | os.PathLike) -> None:
    """Raise :class:`~heliocal.pipeline.errors.UnsafePathError` naming the first link, FIFO,
    socket or device in ``root`` (walked without following links): for a writer whose folder
    holds only files it writes itself (``simulate``'s output folder), which would otherwise write
    or remove through a planted link."""
    found = _links_and_special_files(Path(root))
    if found:
        first = found[0]
        raise UnsafePathError(f"{first['path']} is {first['problem']}, then rerun the command")
