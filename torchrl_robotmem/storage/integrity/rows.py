"""``robotmem verify --rows``: a local store's sealed row file compared, row for row, with its committed chunks.

An open serves a sealed row file (:mod:`..rowfile`) without reading a chunk: the seal binds the file to the
commit record and to the file's identity (inode, size, modification time), which catches a stale file, a
file written or replaced since its seal, and a seal copied from elsewhere. What it cannot catch is a file
*and* seal both rewritten by someone who can write the store (as they could rewrite a chunk and its
checksum). This check reads every committed chunk and the file, and says where they differ.

Example:
    >>> import tempfile, torch
    >>> from tensordict import TensorDict
    >>> from torchrl_robotmem import ZarrStorage
    >>> from torchrl_robotmem.storage.integrity.rows import row_file_problems
    >>> path = tempfile.mkdtemp() + "/m.zarr"
    >>> with ZarrStorage(path, 100, goal_conditioned=False) as st:
    ...     st.set(torch.arange(10), TensorDict({"obs": torch.randn(10, 3)}, [10]))
    >>> row_file_problems(path)
    []
"""
from __future__ import annotations

import os
from typing import Any

import numpy as np

from .. import _backend
from ..errors import Problem
from ..format import dims
from ..layout import PackedLayout
from ..rowfile import ROWS_DIR, ROWS_FILE, RowFile, rows_layout

__all__ = ["row_file_problems"]


def row_file_problems(path: Any) -> list[Problem]:
    """Where a local store's row file differs from its committed chunks (``[]``: it matches, or there is none).

    A row file without a seal that matches the record is not served (the next open fills it again): that is
    reported as a warning, not damage. Rows that differ are errors naming the column and the rows;
    ``robotmem repair`` deletes the file (the next open fills it from the chunks).

    Args:
        path: the local store's directory.
    """
    store, local_dir = _backend.open_store(path, read_only=True, storage_options=None)
    if local_dir is None:
        return []
    if not os.path.lexists(os.path.join(local_dir, ROWS_DIR, ROWS_FILE)):
        return []
    group = _backend.open_group(store, read_only=True)
    attrs = group.attrs.asdict()
    if not attrs.get("schema"):
        return []
    max_dim0, n0, inner = dims(attrs)
    layout = PackedLayout(attrs["schema"])
    rows = RowFile(local_dir, read_only=True)
    try:
        if not rows.open(attrs, layout=rows_layout(layout, (max_dim0, *inner))):
            return [Problem("rows", "no seal binds the row file to the commit record (a writer is active, or it "
                            "did not close cleanly): it is not served; the next open fills it from the chunks",
                            key=f"{ROWS_DIR}/{ROWS_FILE}", severity="warning")]
        views = layout.views(rows.map((max_dim0, *inner), layout.row_bytes))
        chunk_rows = int(attrs["chunk_rows"])
        problems = []
        for p in attrs["schema"]:
            column, arr = views.get(_backend.path_to_key(p)), group[p]
            for lo in range(0, n0, chunk_rows):
                hi = min(lo + chunk_rows, n0)
                stored = np.asarray(arr[lo:hi])
                served = column[lo:hi].numpy()
                if stored.tobytes() != np.ascontiguousarray(served).tobytes():
                    problems.append(Problem("rows", "the row file differs from the committed chunk: `robotmem "
                                            "repair` deletes the row file (the next open fills it from the chunks)",
                                            array=p, chunk=lo // chunk_rows, key=f"{ROWS_DIR}/{ROWS_FILE}",
                                            rows=(lo, hi)))
        return problems
    finally:
        rows.release()
