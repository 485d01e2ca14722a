"""What the open-time integrity checks cost: ``ZarrStorage(path, read_only=True)`` with and without the chunk listing.

Builds a store of FetchPush-shaped transitions (200k rows by default), then
times a read-only open (median of ``--repeat``) three ways: as shipped (commit
record checks, array metadata checks, one listing of every array's chunk
keys), without the chunk listing, and the listing alone. Also times
``verify`` (every chunk decoded). Run from the repository root::

    python benchmarks/bench_open_integrity.py --rows 200000 --repeat 5
    python benchmarks/bench_open_integrity.py --rows 200000 --chunk-rows 1024   # many small chunks
"""
from __future__ import annotations

import argparse
import functools
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from conftest import make_transitions  # noqa: E402

from torchrl_robotmem import ZarrStorage  # noqa: E402
from torchrl_robotmem.storage import integrity  # noqa: E402


def _median(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=200_000)
    parser.add_argument("--chunk-rows", type=int, default=None)
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    path = Path(tempfile.mkdtemp()) / "bench.zarr"
    with ZarrStorage(path, args.rows, chunk_rows=args.chunk_rows) as s:
        for start in range(0, args.rows, 20_000):
            n = min(20_000, args.rows - start)
            s.set(slice(start, start + n), make_transitions(n, start))
        chunk_rows, narrays = s.chunk_rows, len(s._mirror.schema)
    files = sum(1 for p in path.rglob("*") if p.is_file())

    def open_close():
        ZarrStorage(path, read_only=True).close()

    full = _median(open_close, args.repeat)
    original = integrity.check_open
    integrity.check_open = functools.partial(original, list_chunks=False)
    try:
        no_listing = _median(open_close, args.repeat)
    finally:
        integrity.check_open = original
    s = ZarrStorage(path, read_only=True)
    attrs = s._handle.group.attrs.asdict()
    arrays = {p: s._handle.group[p] for p in attrs["schema"]}
    listing = _median(lambda: integrity.missing_chunks(arrays, attrs, store=s._handle.store, local_dir=s._handle.local_dir),
                      args.repeat)
    after_read = _median(lambda: integrity.missing_after_read(s._handle.group, attrs, store=s._handle.store, local_dir=s._handle.local_dir),
                         args.repeat)
    s.close()
    verify = _median(lambda: integrity.verify(path), max(1, args.repeat // 2))
    print(f"{args.rows} rows, {narrays} arrays, chunk_rows {chunk_rows}, {files} files")
    print(f"read-only open, median of {args.repeat}: {full * 1e3:.0f} ms with the chunk listing, "
          f"{no_listing * 1e3:.0f} ms without; the listing alone {listing * 1e3:.1f} ms; "
          f"the listing again after the read (included in every open) {after_read * 1e3:.1f} ms")
    print(f"verify (every chunk decoded): {verify * 1e3:.0f} ms")


if __name__ == "__main__":
    main()
