"""External sort on disk: tables appended in any order come back merged in key order.

``ingest`` uses it to regroup a large calibration log by heliostat (every heliostat's rows must
be seen together, for duplicate detection and position medians) and to put rejected rows back in
source order, while holding only a bounded number of rows in memory: each appended table is
sorted and written as one Parquet *run*; :meth:`SortedSpill.merged` reads all runs in parallel,
a slice of each at a time, and yields tables that hold every row of a contiguous range of keys.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterator

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

__all__ = ["SortedSpill"]

#: Smallest slice read from one run at a time (keeps many-run merges from crawling).
_MIN_READ_ROWS = 1024


class SortedSpill:
    """Runs of rows sorted by ``(key, tie)`` in ``folder``; :meth:`merged` yields them in order.

    Parameters
    ----------
    folder : a folder (or ``os.PathLike`` made on first use) for the run files; the caller
        removes it.
    name : file name prefix of the runs.
    key : column the merge groups by; a yielded table never splits one key value.
    tie : optional column ordering the rows of one key (for example the source row).
    """

    def __init__(self, folder: "os.PathLike[str]", name: str, key: str, tie: str | None = None):
        self.folder = folder  # converted to a path only when the first run is written
        self.name = name
        self.key = key
        self.tie = tie
        self.runs: list[Path] = []
        self.rows = 0

    def _sort_keys(self):
        keys = [(self.key, "ascending")]
        if self.tie is not None:
            keys.append((self.tie, "ascending"))
        return keys

    def add(self, table: pa.Table) -> None:
        """Sort ``table`` and write it as one run (an empty table is skipped)."""
        if table.num_rows == 0:
            return
        path = Path(self.folder) / f"{self.name}-{len(self.runs):06d}.parquet"
        pq.write_table(table.sort_by(self._sort_keys()), path,
                       row_group_size=max(_MIN_READ_ROWS, min(table.num_rows, 1 << 16)))
        self.runs.append(path)
        self.rows += table.num_rows

    def merged(self, chunk_rows: int) -> Iterator[pa.Table]:
        """Yield tables sorted by ``(key, tie)``, each holding all rows of a range of keys.

        A yielded table has at most ``chunk_rows`` rows, unless one step of the merge (all rows
        below the cutoff key, at most half a chunk with slices of ``chunk_rows / (2 runs)`` rows,
        at least 1024, plus the rest of one key) has more; the key ranges of successive tables
        increase. Memory: one slice per run plus the table being assembled.
        """
        if not self.runs:
            return
        read_rows = max(_MIN_READ_ROWS, chunk_rows // (2 * len(self.runs)))
        readers = [pq.ParquetFile(p).iter_batches(batch_size=read_rows) for p in self.runs]
        buffers: list[pa.Table | None] = [None] * len(readers)
        done = [False] * len(readers)

        def pull(i: int) -> None:
            batch = next(readers[i], None)
            if batch is None:
                done[i] = True
                return
            more = pa.Table.from_batches([batch])
            buffers[i] = more if buffers[i] is None else pa.concat_tables([buffers[i], more])

        out: list[pa.Table] = []
        out_rows = 0
        while True:
            for i in range(len(readers)):
                if not done[i] and (buffers[i] is None or buffers[i].num_rows == 0):
                    pull(i)
            live = [i for i in range(len(readers)) if buffers[i] is not None and buffers[i].num_rows]
            if not live:
                break
            # every row below the smallest last key of a run that may still grow is complete
            growing = [i for i in live if not done[i]]
            cutoff = min(buffers[i][self.key][-1].as_py() for i in growing) if growing else None
            emitted = 0
            parts = []
            for i in live:
                buf = buffers[i]
                n = (buf.num_rows if cutoff is None
                     else pc.sum(pc.less(buf[self.key], cutoff)).as_py() or 0)
                if n:
                    parts.append(buf.slice(0, n))
                    buffers[i] = buf.slice(n)
                    emitted += n
            if not emitted:  # the runs ending at the cutoff key hold only that key: read on
                for i in growing:
                    if buffers[i][self.key][-1].as_py() == cutoff:
                        pull(i)
                continue
            if out and out_rows + emitted > chunk_rows:  # would outgrow a chunk: hand it out
                yield pa.concat_tables(out).sort_by(self._sort_keys())
                out, out_rows = [], 0
            out += parts
            out_rows += emitted
        if out:
            yield pa.concat_tables(out).sort_by(self._sort_keys())
