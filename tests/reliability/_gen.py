"""Deterministic rows and a killable writer process, shared by the reliability tests.

Every column of a row is a function of the row's global write number ``w``
(``make_rows``), so a reader can tell from a row alone which write produced it
and whether any of its columns came from another write (a torn row). The
``action`` column holds ``-w``.

``writer_main`` is the body of a writer process: it opens a ``ZarrStorage``,
builds a ``TensorDictReplayBuffer`` on it, checks that the buffer's writer was
restored to the stored write count, and extends deterministic batches forever,
recording its progress in shared memory. It is started with
``runpy.run_path(__file__, init_globals={"ARGS": {...}}, run_name=WRITER_RUN_NAME)``
from a forkserver that has torch, torchrl and zarr loaded already, so a writer
starts in milliseconds (``writer_context``).
"""
from __future__ import annotations

import multiprocessing as mp
import random
import time
import traceback

import torch
from tensordict import TensorDict

EPISODE_LEN = 50
WRITER_RUN_NAME = "__robotmem_reliability_writer__"

# progress slots of the shared int64 array a writer fills
STATE, W_OPEN, W_TRYING, W_DONE, W_FLUSHED, N_EXTENDS = range(6)
PROGRESS_SLOTS = 6
STAMP_SLOTS = 50_000  # (rows written, time) of the last extends, a ring


def make_rows(w, *, goal_dim: int = 3) -> TensorDict:
    """Rows for write numbers ``w`` (int64 ``[n]``); every column is a function of ``w``."""
    w = torch.as_tensor(w, dtype=torch.long)
    n = len(w)
    wf = w.double()
    done = (w % EPISODE_LEN == EPISODE_LEN - 1).unsqueeze(-1)
    goal = torch.stack([torch.sin(wf * 0.37), torch.cos(wf * 0.11), wf * 1e-4]
                       + [torch.sin(wf * (0.5 + j)) for j in range(goal_dim - 3)], -1).float()
    return TensorDict(
        {
            "observation": (w.unsqueeze(-1) * 5 + torch.arange(5)).float(),
            "action": torch.stack([-w, w % 7], -1),
            "value": wf / 8,
            "flag": (w % 3 == 0).unsqueeze(-1),
            "step_count": (w % EPISODE_LEN).unsqueeze(-1),
            "nested": {"deep": {"x": (w.unsqueeze(-1) * 3 + torch.arange(3)).int()}},
            "next": {
                "observation": (w.unsqueeze(-1) * 5 + torch.arange(5) + 1).float(),
                "achieved_goal": goal,
                "reward": torch.where(w % 10 == 0, 0.0, -1.0).float().unsqueeze(-1),
                "is_success": (w % 10 == 0).float(),
                "done": done,
                "truncated": done.clone(),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
            },
        },
        [n],
    )


# keys a writable reopen may change (it closes the episode a killed writer left open)
EPISODE_END_KEYS = (("next", "done"), ("next", "truncated"))


def torn_or_wrong(td: TensorDict, expected_w: torch.Tensor | None = None) -> dict:
    """``{key: row positions}`` where ``td`` disagrees with ``make_rows`` of its own write numbers.

    The write number of each row is read from its ``action`` column; with
    ``expected_w`` the rows must also hold exactly those write numbers. Episode
    end flags are left out (a reopen may set them).
    """
    w = -td["action"][:, 0]
    bad = {}
    if expected_w is not None:
        wrong = (w != expected_w).nonzero().squeeze(-1)
        if len(wrong):
            bad["write number"] = wrong[:10].tolist()
    ref = make_rows(w)
    for key in ref.keys(True, True):
        if key in EPISODE_END_KEYS:
            continue
        a, b = td.get(key), ref.get(key)
        if a.dtype != b.dtype or a.shape != b.shape:
            bad[key] = f"dtype/shape {a.dtype}{tuple(a.shape)} != {b.dtype}{tuple(b.shape)}"
            continue
        mism = (a != b).reshape(len(w), -1).any(-1).nonzero().squeeze(-1)
        if len(mism):
            bad[key] = mism[:10].tolist()
    return bad


_CTX = None


def writer_context():
    """A forkserver with torch / torchrl / zarr preloaded: a writer starts in ms, not seconds."""
    global _CTX
    if _CTX is None:
        _CTX = mp.get_context("forkserver")
        _CTX.set_forkserver_preload(["torch", "tensordict", "torchrl.data", "zarr", "torchrl_robotmem"])
    return _CTX


def writer_main(path, max_size, chunk_rows, commit_interval, seed, prog, stamps, err_file,
                max_batch=40, pause=0.02, flush_prob=0.1):
    """Extends deterministic batches forever; records progress in ``prog`` and ``stamps``.

    ``prog`` slots: ``STATE`` (1 opened, 2 first extend returned), ``W_OPEN``
    (write count found at open), ``W_TRYING`` (write count the extend in flight
    leads to), ``W_DONE`` (write count after the last extend that returned),
    ``W_FLUSHED`` (after the last ``flush()`` that returned), ``N_EXTENDS``.
    ``stamps[2 * (i % STAMP_SLOTS)]`` is the write count after extend ``i``,
    the next slot the ``time.monotonic()`` at which it returned.
    """
    import torch
    from torchrl.data import TensorDictReplayBuffer

    from torchrl_robotmem import ZarrStorage

    torch.set_num_threads(1)
    try:
        st = ZarrStorage(path, max_size, chunk_rows=chunk_rows, commit_interval=commit_interval,
                         env="FetchPush-v4")
        rb = TensorDictReplayBuffer(storage=st, batch_size=16)
        w = int(rb.writer.state_dict()["_write_count"])
        stored = st.state_dict()["zarr"]
        assert w == stored["write_count"] and int(rb.writer.state_dict()["_cursor"]) == stored["cursor"], (
            f"the buffer's writer was not restored: {rb.writer.state_dict()} vs {stored}"
        )
        prog[W_OPEN] = prog[W_TRYING] = prog[W_DONE] = prog[W_FLUSHED] = w
        prog[STATE] = 1
        rng = random.Random(seed)
        i = 0
        while True:
            b = rng.randint(1, max_batch)
            prog[W_TRYING] = w + b
            rb.extend(make_rows(torch.arange(w, w + b)))
            w += b
            prog[W_DONE] = w
            stamps[2 * (i % STAMP_SLOTS)] = w
            stamps[2 * (i % STAMP_SLOTS) + 1] = time.monotonic()
            i += 1
            prog[N_EXTENDS] = i
            prog[STATE] = 2
            u = rng.random()
            if u < flush_prob:
                st.flush()
                prog[W_FLUSHED] = w
            elif u < flush_prob + 0.1:
                rb.sample()
            time.sleep(rng.random() * pause)
    except BaseException:
        with open(err_file, "w") as f:
            f.write(traceback.format_exc())
        raise


if __name__ == WRITER_RUN_NAME:
    writer_main(**ARGS)  # noqa: F821 - ARGS is injected by runpy.run_path(init_globals=...)
