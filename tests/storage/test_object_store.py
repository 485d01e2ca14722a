"""ZarrStorage on an object store: ``s3://`` through fsspec/s3fs, against a local moto server.

The server (``tests/_s3.py``) runs in a thread of the test process on
127.0.0.1; no AWS account, no network. Writers that get SIGKILLed run in
child processes. What is checked:

* create, extend, reopen and resume on ``s3://``: rows bit-exact, the
  writer's cursor and the run tags continued;
* the writer lease (``<store>.writer-lease``, conditional puts): a second
  writer is refused while the first lives, a dead writer's lease is taken over
  once it is stale, a writer whose lease was taken over stops writing;
* a read-only reader in this process while a child process appends: every
  refresh sees a committed prefix, bit-exact;
* SIGKILL of the writer in the middle of a commit (some arrays' chunks
  uploaded, the commit record not) and at a random moment: the store reopens,
  every row below the committed length is bit-exact, and a new writer resumes.

Leases expire after ``TORCHRL_ROBOTMEM_LEASE_TTL`` seconds; the kill tests set
it to 1 s so that the next writer does not wait 30 s. The random-moment kill
loop is slow on a busy machine and runs only with ``S3_KILL_TESTS=<kills>``
(``S3_KILL_TESTS=5 pytest tests/storage/test_object_store.py``).
"""
# ruff: noqa: F811  (the fixtures imported from _s3 are parameters of the tests)
from __future__ import annotations

import json
import os
import pickle
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from _s3 import new_bucket, s3_server, s3_url  # noqa: F401  (pytest fixtures)
from conftest import make_transitions, seed_from_env
from torchrl.data import TensorDictReplayBuffer

from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.storage._backend import S3Lease

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="needs SIGKILL")

TESTS = Path(__file__).resolve().parents[1]
EPISODE_LEN = 10  # make_transitions' episodes
_DONE_KEYS = (("next", "done"), ("next", "truncated"))


def _assert_rows(storage: ZarrStorage, n: int, closed: set[int] = frozenset()) -> None:
    """Rows ``[0, n)`` equal ``make_transitions(n)`` bit for bit.

    ``closed``: rows where a reopen closed an episode cut by a kill (done and
    truncated set), the only change a reopen makes.
    """
    assert len(storage) >= n
    got = storage.get(torch.arange(n))
    want = make_transitions(n)
    assert set(got.keys(True, True)) == set(want.keys(True, True))
    for key in _DONE_KEYS:
        for row in closed:
            assert bool(got.get(key)[row].all()), f"the interrupted episode is not closed at row {row}"
            want.get(key)[row] = True
    for key in want.keys(True, True):
        g, w = got.get(key), want.get(key)
        assert g.dtype == w.dtype and torch.equal(g, w), f"{key} differs"


def _cut(n: int) -> set[int]:
    """The row a reopen closes when a writer was killed after ``n`` committed rows."""
    return {n - 1} if n % EPISODE_LEN else set()


def test_create_extend_reopen_resume(s3_url, s3_server):
    so = s3_server.storage_options
    storage = ZarrStorage(s3_url, 1000, env="FetchPush-v4", chunk_rows=64, storage_options=so)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=8)
    rb.extend(make_transitions(150))
    storage.close()

    storage = ZarrStorage(s3_url, storage_options=so)
    rb = TensorDictReplayBuffer(storage=storage, batch_size=8)
    assert len(rb) == 150 and rb.writer._cursor == 150 and storage.max_size == 1000
    _assert_rows(storage, 150)
    rb.extend(make_transitions(100, 150))  # resumes after the old rows
    assert rb.sample().batch_size == torch.Size([8])
    storage.close()

    reader = ZarrStorage(s3_url, read_only=True, storage_options=so)
    _assert_rows(reader, 250)
    assert reader["run"][:150].unique().tolist() == [0] and reader["run"][150:250].unique().tolist() == [1]
    assert reader.env_names == ("FetchPush-v4",)
    # any Zarr reader sees the same store
    import zarr
    from zarr.storage import FsspecStore

    group = zarr.open_group(FsspecStore.from_url(s3_url, storage_options=so, read_only=True), mode="r")
    assert group.attrs["len"] == 250
    assert torch.equal(torch.from_numpy(group["observation"][:250]), make_transitions(250)["observation"])
    # a pickled handle (what collector workers and Ray actors receive) is a reader with the same options
    copy = pickle.loads(pickle.dumps(reader))
    assert copy.read_only and len(copy) == 250


def _lease_age(client, bucket: str, key: str) -> float:
    """Seconds since the lease object was last written, on the server's clock."""
    from email.utils import parsedate_to_datetime

    head = client.head_object(Bucket=bucket, Key=key + ".writer-lease")
    return (parsedate_to_datetime(head["ResponseMetadata"]["HTTPHeaders"]["date"]) - head["LastModified"]).total_seconds()


def test_writer_lease(s3_url, s3_server, monkeypatch):
    so = s3_server.storage_options
    client = s3_server.client()
    bucket, key = s3_url[len("s3://"):].split("/", 1)
    writer = ZarrStorage(s3_url, 100, storage_options=so)
    lease = json.loads(client.get_object(Bucket=bucket, Key=key + ".writer-lease")["Body"].read())
    assert lease["pid"] == os.getpid()
    # a second writer (another process or another host) is refused while the lease is renewed
    with pytest.raises(RuntimeError, match="holds the writer lease.*read_only=True"):
        S3Lease(s3_url, so)
    # readers need no lease
    assert len(ZarrStorage(s3_url, read_only=True, storage_options=so)) == 0
    writer.close()
    with pytest.raises(client.exceptions.ClientError):  # close() deletes it
        client.head_object(Bucket=bucket, Key=key + ".writer-lease")

    # a dead writer's lease (not renewed for ttl seconds) is taken over; of two racers one wins
    dead = S3Lease(s3_url, so, ttl=1.0)
    dead._stop.set()  # the holder dies: no more renewals, no release
    dead._thread.join()  # (a renewal in flight lands before this returns)
    # until the server's clock says the lease is older than its ttl (Last-Modified has a
    # one-second resolution): an event on the server, not a time on this machine
    deadline = time.monotonic() + 60
    while (age := _lease_age(client, bucket, key)) <= dead.ttl:
        assert time.monotonic() < deadline, f"the lease never aged past its ttl (age {age} s)"
        time.sleep(0.1)
    taker = S3Lease(s3_url, so)  # renewed every 10 s (ttl 30 s): live for the next check
    assert json.loads(client.get_object(Bucket=bucket, Key=key + ".writer-lease")["Body"].read())["owner"] == (
        taker._body["owner"]), "the stale lease was not taken over"
    with pytest.raises(RuntimeError, match="holds the writer lease"):
        S3Lease(s3_url, so)
    taker.release()

    # a writer whose lease was taken over refuses further writes
    monkeypatch.setenv("TORCHRL_ROBOTMEM_LEASE_TTL", "0.6")
    storage = ZarrStorage(s3_url, 100, storage_options=so)
    rb = TensorDictReplayBuffer(storage=storage)
    rb.extend(make_transitions(10))
    storage.flush()
    client.put_object(Bucket=bucket, Key=key + ".writer-lease", Body=b'{"host": "elsewhere", "ttl": 30}')
    deadline = time.monotonic() + 10
    while storage._handle.lock.lost is None and time.monotonic() < deadline:
        time.sleep(0.05)
    with pytest.raises(RuntimeError, match="lost the writer lock"):
        rb.extend(make_transitions(10, 10))
    assert len(ZarrStorage(s3_url, read_only=True, storage_options=so)) == 10


# -- a writer process, killed ------------------------------------------------------------

WRITER_SRC = r'''
import json, os, sys, time
sys.path.insert(0, sys.argv[1])
import torch
torch.set_num_threads(1)
from conftest import make_transitions, seed_from_env
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem import ZarrStorage
from torchrl_robotmem.storage.commit import CommitEngine

url, so, mode = sys.argv[2], json.loads(sys.argv[3]), sys.argv[4]
if mode == "midcommit":
    # the 5th commit writes the chunks of half the arrays, says so, and hangs: the kill lands
    # between chunk uploads, before the commit record
    original, calls = CommitEngine._write_chunks, [0]
    def write_chunks(self, payload, prefix=""):
        calls[0] += 1
        if calls[0] == 5 and not prefix:
            paths = sorted(next(iter(payload.values())))
            half = {c: {p: a for p, a in arrays.items() if p in paths[: len(paths) // 2]}
                    for c, arrays in payload.items()}
            original(self, half, prefix)
            print("MID", flush=True)
            time.sleep(3600)
        original(self, payload, prefix)
    CommitEngine._write_chunks = write_chunks
deadline = time.monotonic() + 30
while True:  # the lease of a killed predecessor expires after its ttl
    try:
        storage = ZarrStorage(url, 100_000, chunk_rows=256, commit_interval=0.2, storage_options=so)
        break
    except RuntimeError:
        if time.monotonic() > deadline:
            raise
        time.sleep(0.2)
rb = TensorDictReplayBuffer(storage=storage)
n = len(rb)
print("READY", n, flush=True)
while True:  # about 700 rows/s, at most 3000 rows: a store that stays small
    if n < 3000:
        rb.extend(make_transitions(37, n))
        n += 37
    time.sleep(0.05)
'''


def _start_writer(url: str, server, mode: str) -> subprocess.Popen:
    env = {**os.environ, "TORCHRL_ROBOTMEM_LEASE_TTL": "1", "TORCHRL_ROBOTMEM_SIGNALS": "0"}
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER_SRC, str(TESTS), url, json.dumps(server.storage_options), mode],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )
    line = proc.stdout.readline()
    if not line.startswith("READY"):
        proc.kill()
        raise AssertionError(f"writer did not start: {line!r} {proc.stderr.read()[-3000:]}")
    return proc


def _reopen_writer(url: str, so: dict, deadline_s: float = 20.0) -> ZarrStorage:
    deadline = time.monotonic() + deadline_s
    while True:
        try:
            return ZarrStorage(url, storage_options=so)
        except RuntimeError as err:  # the killed writer's lease has not expired yet
            if "writer lease" not in str(err) or time.monotonic() > deadline:
                raise
            time.sleep(0.2)


@pytest.mark.full
def test_reader_while_writer_appends_then_sigkill_mid_commit(s3_url, s3_server, monkeypatch):
    so = s3_server.storage_options
    monkeypatch.setenv("TORCHRL_ROBOTMEM_LEASE_TTL", "1")
    # (the store is created here, so the child's chunking is this one)
    ZarrStorage(s3_url, 100_000, chunk_rows=256, storage_options=so).close()
    proc = _start_writer(s3_url, s3_server, "midcommit")
    try:
        reader = ZarrStorage(s3_url, read_only=True, storage_options=so)
        seen, checked = [len(reader)], 0
        deadline = time.monotonic() + 120
        # while the child appends and commits (it hangs in its 5th commit): refresh until rows
        # were seen, at least three times
        while not checked or len(seen) <= 3:
            assert time.monotonic() < deadline and proc.poll() is None, (
                f"the reader saw no committed rows (lens {seen[-10:]})", proc.stderr.read()[-3000:] if proc.poll() else "")
            n = reader.refresh()
            assert n >= seen[-1]
            if n:  # (the loop goes on until some were: asserted below)
                _assert_rows(reader, n)  # every refresh: a committed prefix, bit-exact
            checked += n
            seen.append(n)
        assert checked > 0, "no row was checked"
        line = proc.stdout.readline()  # waits for the hung 5th commit
        assert line.strip() == "MID", (line, proc.stderr.read()[-3000:] if proc.poll() is not None else "")
        committed = reader.refresh()
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert committed > 0

    storage = _reopen_writer(s3_url, so)
    n = len(storage)
    assert n == committed  # half a commit's chunks uploaded, no commit record: nothing new visible
    _assert_rows(storage, n, _cut(n))
    rb = TensorDictReplayBuffer(storage=storage)
    rb.extend(make_transitions(50, n))
    storage.close()
    again = ZarrStorage(s3_url, read_only=True, storage_options=so)
    assert len(again) == n + 50
    tail = again.get(torch.arange(n, n + 50))
    assert torch.equal(tail["observation"], make_transitions(50, n)["observation"])
    assert again["run"][n:].unique().numel() == 1 and int(again["run"][n]) > int(again["run"][0])


@pytest.mark.skipif(not os.environ.get("S3_KILL_TESTS"), reason="slow (a minute on a busy 2-core box): set S3_KILL_TESTS=1")
def test_sigkill_at_random_moments(s3_url, s3_server, monkeypatch):
    """Kills at random moments of a sustained append (timed commits every 0.2 s).

    ``S3_KILL_TESTS=<n>`` runs it with ``n`` kills, each after the writer committed rows;
    ``CRASH_SEED`` (else ``ROBOTMEM_TEST_SEED``, default 0) replays a schedule.
    """
    so = s3_server.storage_options
    monkeypatch.setenv("TORCHRL_ROBOTMEM_LEASE_TTL", "1")
    seed = seed_from_env("CRASH_SEED")
    print(f"CRASH_SEED={seed}")
    rng = random.Random(seed)
    ZarrStorage(s3_url, 100_000, chunk_rows=256, storage_options=so).close()
    reader = ZarrStorage(s3_url, read_only=True, storage_options=so)
    before, closed = 0, set()
    for _ in range(max(1, int(os.environ.get("S3_KILL_TESTS", "2")))):
        proc = _start_writer(s3_url, s3_server, "append")
        deadline = time.monotonic() + 120
        while reader.refresh() <= before:  # the writer committed rows: the kill lands after progress
            assert time.monotonic() < deadline and proc.poll() is None, f"the writer committed nothing (CRASH_SEED={seed})"
            time.sleep(0.05)
        time.sleep(rng.uniform(0.0, 1.5))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        storage = _reopen_writer(s3_url, so)
        n = len(storage)
        assert n > before, f"len went from {before} to {n} (CRASH_SEED={seed})"
        closed |= _cut(n)
        _assert_rows(storage, n, closed)
        storage.close()  # (a reopen closes the cut episode: the next child continues from there)
        before = n


APPEND_SRC = r'''
import json, sys
sys.path.insert(0, sys.argv[1])
from conftest import make_transitions
from torchrl.data import TensorDictReplayBuffer
from torchrl_robotmem import ZarrStorage
storage = ZarrStorage(sys.argv[2], storage_options=json.loads(sys.argv[3]))
rb = TensorDictReplayBuffer(storage=storage)
n = len(rb)
rb.extend(make_transitions(int(sys.argv[4]), n))
storage.close()
'''


@pytest.mark.full
def test_chunks_written_by_another_process_after_a_listing_are_read(s3_url, s3_server):
    """A listing made in this process never hides chunk files another process wrote later.

    fsspec caches one filesystem object per set of options, and in it every
    directory listing: a reader's open-time chunk listing, reused by a later
    ``refresh()`` or by a writable open in the same process, made s3fs read the
    chunks written since as missing and Zarr serve zeros (rows 256 on, here;
    seen as a flaky ``test_reader_while_writer_appends_then_sigkill_mid_commit``).
    """
    so = s3_server.storage_options
    ZarrStorage(s3_url, 10_000, chunk_rows=64, storage_options=so).close()
    first = subprocess.run([sys.executable, "-c", APPEND_SRC, str(TESTS), s3_url, json.dumps(so), "100"],
                           capture_output=True, text=True, timeout=300)
    assert first.returncode == 0, first.stderr[-3000:]
    reader = ZarrStorage(s3_url, read_only=True, storage_options=so)  # lists chunks 0-1
    _assert_rows(reader, 100)
    more = subprocess.run([sys.executable, "-c", APPEND_SRC, str(TESTS), s3_url, json.dumps(so), "300"],
                          capture_output=True, text=True, timeout=300)
    assert more.returncode == 0, more.stderr[-3000:]
    assert reader.refresh() == 400
    _assert_rows(reader, 400)
    _assert_rows(ZarrStorage(s3_url, read_only=True, storage_options=so), 400)
    writer = ZarrStorage(s3_url, storage_options=so)  # closes the episode the last writer left open
    _assert_rows(writer, 400, {399})
    writer.close()


def test_a_url_stores_row_file_is_cached_locally_and_never_served_for_another_session(s3_url, s3_server, tmp_path,
                                                                                      monkeypatch):
    """A writer's clean close seals the rows in the local cache folder of the URL: the next open serves
    them without reading a chunk. A store replaced at the same URL with other rows of the same count (same
    length, counters and names: only the writing session differs) is filled from its chunks, never served
    the cached rows of the store before."""
    from torchrl_robotmem.storage.rowfile import CACHE_ENV, ROWS_DIR, url_cache_dir

    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    so = s3_server.storage_options
    rows = make_transitions(100)
    with ZarrStorage(s3_url, 200, chunk_rows=64, storage_options=so) as st:
        st.set(slice(0, 100), rows)
    folder = url_cache_dir(s3_url, so)
    assert sorted(os.listdir(os.path.join(folder, ROWS_DIR))) == ["rows.bin", "seal.json"]
    with ZarrStorage(s3_url, read_only=True, storage_options=so) as st:
        assert st.row_file["sealed"] is True
        _assert_rows(st, 100)

    cached = os.path.join(folder, ROWS_DIR)
    os.link(os.path.join(cached, "rows.bin"), tmp_path / "first.bin")  # the first store's sealed file, kept
    first_seal = Path(cached, "seal.json").read_bytes()
    import s3fs

    fs = s3fs.S3FileSystem(**so, skip_instance_cache=True, use_listings_cache=False)
    fs.rm(s3_url.removeprefix("s3://"), recursive=True)  # the store deleted, and made again with other rows
    other = rows.clone()
    other["observation"] += 1000.0
    with ZarrStorage(s3_url, 200, chunk_rows=64, storage_options=so) as st:
        st.set(slice(0, 100), other)
    # the first store's sealed file put back: the records agree in length, schema, counters and names, and
    # differ in the writing session only
    os.replace(tmp_path / "first.bin", os.path.join(cached, "rows.bin"))
    Path(cached, "seal.json").write_bytes(first_seal)
    with ZarrStorage(s3_url, read_only=True, storage_options=so) as st:
        assert st.row_file["sealed"] is False
        assert torch.equal(st.get(torch.arange(100))["observation"], other["observation"])
