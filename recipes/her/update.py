"""The update step of the HER recipe: loss, backward, optimiser, target networks; eager, compiled or CUDA-graphed.

TorchRL's ``sota-implementations/{sac,td3}`` define an ``update(batch)``
function in the script and wrap it in ``torch.compile`` (``compile.compile``)
and ``tensordict.nn.CudaGraphModule`` (``compile.cudagraphs``). :class:`Updater`
does the same for this recipe's update, whose shape changes between calls in
two ways a captured graph cannot follow: whether the actor trains (TD3's delayed
updates; the critic-only steps of ``experiments/prior_variants``) and whether the
target networks move. Each of the
(at most four) variants is its own compiled / captured function, built on first
use.

:func:`draw_batches` draws the ``n`` batches of one collection step in one
sample of ``n * batch_size`` rows (HER relabelling, the goal sampler's query
and the prior mix run once instead of ``n`` times), shuffled and split.
"""
from __future__ import annotations

import functools
import warnings
from collections.abc import Callable

import torch
from tensordict import TensorDictBase

__all__ = ["LossTerms", "Updater", "compile_settings", "draw_batches"]


def compile_settings(cfg, device: torch.device) -> dict:
    """``compile.*`` of the config, with ``auto`` resolved for ``device``: on for CUDA, off for the CPU.

    On the CPU the update is arithmetic-bound (docs/benchmarks.md, "The update
    step"): ``torch.compile`` cost minutes of compilation there and gained
    nothing measurable, so ``auto`` leaves it off. CUDA graphs need a CUDA device;
    ``compile.cudagraphs=true`` with ``device=cpu`` is refused.

    Returns:
        ``{"compile": bool, "mode": str | None, "cudagraphs": bool, "warmup": int, "backend": str}``
    """
    node = cfg.get("compile") or {}
    cuda = device.type == "cuda"

    def flag(name: str) -> bool:
        value = node.get(name, "auto")
        if value in ("auto", None):
            return cuda
        if not isinstance(value, bool):
            raise ValueError(f"compile.{name} must be true, false or auto, got {value!r}.")
        return value

    compiled, graphs = flag("compile"), flag("cudagraphs")
    if graphs and not cuda:
        raise ValueError(f"compile.cudagraphs=true needs a CUDA device, but device={device}. "
                         "Set compile.cudagraphs=false (or auto) on the CPU.")
    mode = node.get("compile_mode") or None
    if compiled and mode is None:  # as TorchRL's sota SAC: CUDA graphs come from CudaGraphModule, not inductor
        mode = "default" if graphs or not cuda else "reduce-overhead"
    return {"compile": compiled, "mode": mode, "cudagraphs": graphs, "warmup": int(node.get("warmup", 5)),
            "backend": node.get("backend") or "inductor"}


class LossTerms:
    """What an update minimises: the algorithm's loss terms, or the critics' alone.

    :meth:`loss` returns the terms ``keys`` of the loss module for a batch;
    :meth:`total` sums those an update trains: all of them, or the critics'
    (``keys[1]``) on a step that leaves the actor alone. :class:`Updater` asks
    any object with these two methods (``experiments/prior_variants`` adds its
    prior-memory terms that way).

    Args:
        loss_module: the run's SAC / TD3 / DDPG loss.
        keys (tuple): its terms, the actor's first, then the critics' (``utils.loss_keys``).

    Example:
        >>> terms = LossTerms(loss_module, ("loss_actor", "loss_qvalue", "loss_alpha"))
        >>> loss_td = terms.loss(batch)
        >>> terms.total(loss_td).backward()
    """

    def __init__(self, loss_module, keys: tuple) -> None:
        self.loss_module, self.keys = loss_module, tuple(keys)

    def loss(self, batch: TensorDictBase, train_actor: bool = True) -> TensorDictBase:
        """The algorithm's terms (``keys``) for one batch."""
        return self.loss_module(batch).select(*self.keys)

    def total(self, loss_td: TensorDictBase, train_actor: bool = True) -> torch.Tensor:
        """What an update minimises: every term, or the critics' alone when ``train_actor`` is False."""
        return sum(loss_td[k] for k in (self.keys if train_actor else self.keys[1:2]))


class Updater:
    """One gradient step of the HER recipe, eager, compiled (``torch.compile``) or captured in CUDA graphs.

    A step computes the loss terms (``terms.loss``), minimises their sum
    (``terms.total``) with ``optimizer``, and moves the target networks
    (``target_updater.step()``) when they are due. TD3's actor and targets
    move every ``policy_delay``-th step; ``critic_only`` steps train the critics
    alone and move the targets.

    Args:
        terms: what the update minimises, with ``loss(batch, train_actor)`` and
            ``total(loss_td, train_actor)`` (:class:`LossTerms`).
        optimizer: one optimiser over every trained parameter (``group_optimizers``).
        target_updater: a ``torchrl.objectives.SoftUpdate`` / ``HardUpdate``.

    Keyword Args:
        policy_delay (int): the actor and targets move every ``policy_delay``-th step (TD3). Default: 1.
        compile (bool): wrap each variant in ``torch.compile``. Default: ``False``.
        compile_mode (str, optional): ``torch.compile``'s ``mode`` (inductor only).
        compile_backend (str): ``torch.compile``'s ``backend``. Default: ``"inductor"``.
        cudagraphs (bool): capture each variant in a ``tensordict.nn.CudaGraphModule``
            (CUDA only; the optimiser must be ``capturable``). Default: ``False``.
        warmup (int): calls of a variant before it is compiled (eager) or captured (the warm-up of
            ``CudaGraphModule``, at least 2: one eager call, then compiled ones). Default: 5.

    Example:
        >>> updater = Updater(terms, optimizer, SoftUpdate(loss_module, eps=0.995))
        >>> loss_td = updater(batch)                     # actor, critics, targets
        >>> loss_td = updater(batch, critic_only=True)   # critics and targets
        >>> updater.num_updates
        2
    """

    def __init__(self, terms, optimizer, target_updater, *, policy_delay: int = 1, compile: bool = False,
                 compile_mode: str | None = None, compile_backend: str = "inductor", cudagraphs: bool = False,
                 warmup: int = 5) -> None:
        if policy_delay < 1:
            raise ValueError(f"policy_delay must be >= 1, got {policy_delay}.")
        self.terms, self.optimizer, self.target_updater = terms, optimizer, target_updater
        self.policy_delay = int(policy_delay)
        self.compile, self.compile_mode, self.cudagraphs = bool(compile), compile_mode, bool(cudagraphs)
        self.compile_backend = compile_backend
        self.warmup = int(warmup)
        self.num_updates = 0
        self._variants: dict[tuple[bool, bool], Callable] = {}
        if self.cudagraphs:
            _require_capturable(optimizer)

    def __call__(self, batch: TensorDictBase, critic_only: bool = False) -> TensorDictBase:
        """One step on ``batch``; returns its loss terms (detached, safe to keep)."""
        delayed = self.num_updates % self.policy_delay != 0
        train_actor = not (critic_only or delayed)
        move_targets = critic_only or not delayed
        fn = self._variant(train_actor, move_targets)
        if self.cudagraphs:
            torch.compiler.cudagraph_mark_step_begin()
        out = fn(batch)
        self.num_updates += 1
        return out.clone() if self.cudagraphs else out  # a captured graph's outputs are overwritten by the next replay

    def step(self, batch: TensorDictBase, train_actor: bool, move_targets: bool) -> TensorDictBase:
        """The eager step: what every variant runs."""
        loss_td = self.terms.loss(batch, train_actor)
        self.terms.total(loss_td, train_actor).backward()
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        if move_targets:
            self.target_updater.step()
        return loss_td.detach()

    def _variant(self, train_actor: bool, move_targets: bool) -> Callable:
        key = (train_actor, move_targets)
        fn = self._variants.get(key)
        if fn is None:
            fn = functools.partial(self.step, train_actor=train_actor, move_targets=move_targets)
            if self.compile:
                options = {"mode": self.compile_mode} if self.compile_backend == "inductor" else {}
                # under CUDA graphs, compile on the first warm-up call after one eager call (as TorchRL's sota
                # SAC does): compiling must be done before the graph is captured, never during the capture
                fn = _after_warmup(fn, functools.partial(torch.compile, backend=self.compile_backend, **options),
                                   1 if self.cudagraphs else self.warmup)
            if self.cudagraphs:
                from tensordict.nn import CudaGraphModule

                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", UserWarning)  # "experimental": tests/test_cuda.py checks it
                    fn = CudaGraphModule(fn, in_keys=[], out_keys=[], warmup=max(self.warmup, 2))
            self._variants[key] = fn
        return fn


def _after_warmup(fn: Callable, wrap: Callable[[Callable], Callable], warmup: int) -> Callable:
    """``fn`` for the first ``warmup`` calls, then ``wrap(fn)`` (lazy states such as Adam's exist by then)."""
    calls = 0
    wrapped = None

    def call(*args, **kwargs):
        nonlocal calls, wrapped
        if calls < warmup:
            calls += 1
            return fn(*args, **kwargs)
        if wrapped is None:
            wrapped = wrap(fn)
        return wrapped(*args, **kwargs)

    return call


def _require_capturable(optimizer) -> None:
    """A CUDA graph replays the optimiser's step: its state must live on the device (``capturable=True``)."""
    inner = getattr(optimizer, "optimizers", None) or [optimizer]
    for opt in inner:
        for group in opt.param_groups:
            if not group.get("capturable", False):
                raise ValueError(
                    f"compile.cudagraphs=true needs capturable optimisers, but {type(opt).__name__} has "
                    "capturable=False: build it with capturable=True (the recipe's make_optimizer does on CUDA)."
                )


def draw_batches(sample: Callable[[int], TensorDictBase], n: int, batch_size: int,
                 generator: torch.Generator | None = None) -> list[TensorDictBase]:
    """``n`` batches of ``batch_size`` rows drawn in one ``sample(n * batch_size)``, shuffled, then split.

    One draw instead of ``n`` saves the per-call work of a sample (HER's
    relabelling and reward, the goal sampler, the prior mix, the host-to-device
    copy). The shuffle matters: ``HERReplayBuffer`` relabels the first
    ``her_ratio`` of the rows it returns and ``PriorMix`` puts the prior's rows
    last, so unshuffled parts would not be alike. After the shuffle each batch
    is a uniform draw without replacement from the ``n * batch_size`` rows: the
    same distribution as ``n`` separate samples, with the HER and prior shares
    exact over the ``n`` batches and close to them in each.

    Args:
        sample: ``sample(size)`` draws ``size`` rows (e.g. ``lambda k: rb.sample(k)``).
        n (int): how many batches.
        batch_size (int): rows a batch.
        generator (torch.Generator, optional): for the shuffle.

    Example:
        >>> batches = draw_batches(lambda k: replay_buffer.sample(k), n=100, batch_size=512)
        >>> len(batches), batches[0].shape
        (100, torch.Size([512]))
    """
    if n < 1 or batch_size < 1:
        raise ValueError(f"n and batch_size must be >= 1, got n={n}, batch_size={batch_size}.")
    rows = sample(n * batch_size)
    if rows.shape[0] != n * batch_size:
        raise ValueError(f"sample({n * batch_size}) returned {rows.shape[0]} rows.")
    if n == 1:
        return [rows]
    perm = torch.randperm(n * batch_size, generator=generator, device="cpu").to(rows.device)
    return list(rows[perm].split(batch_size))
