"""The tables of docs/results.md (and docs/notes/results_history.md), generated from the archives in docs/runs/.

Every figure on those pages that an archive holds is written here, not by hand:
each table is declared once below (which archives, which evaluation, which
columns) and read with the recipes' own readers (``recipes.her.tools.compare.load_run``
for a run's curve and CPU time, ``recipes.her.tools.paired`` for its per-episode
outcomes, ``recipes.her.tools.stats`` for the tests). A page holds each table
between two markers; the prose around them is hand-written::

    <!-- generated: push_clone -->
    ...
    <!-- end generated: push_clone -->

Run it from the repository root::

    python -m tools.results_page            # print every generated block
    python -m tools.results_page --check    # exit 1 with a diff if a page differs from what it prints
    python -m tools.results_page --write    # rewrite the generated blocks of the pages in place

``tests/test_results_page.py`` runs the check, so ``make test`` fails when a page
and its archives part.

Two levels of evidence are reported side by side. *Run-level*: the unit is the
run (one seed); the mean of the per-seed figures with a t-based 95% interval over
seeds, the difference of two arms' means with Welch's interval and test, and an
exact permutation test over the seed labels (with 3 runs against 3 there are 20
relabellings, so no two-sided p can be below 2/20 = 0.1). *Episode-level*: the
evaluation episodes of all seeds pooled as if independent; an exact McNemar test
on pairs of episodes (same seed, same goal) where the archives keep per-episode
outcomes, otherwise Fisher's exact test on the pooled counts.
"""
from __future__ import annotations

import argparse
import difflib
import itertools
import json
import math
import re
import statistics
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGES = ("docs/results.md", "docs/notes/results_history.md")
RUNS = "docs/runs"
CROSS_ENV = "docs/cross_env/results.json"
#: episodes of one evaluation, for the runs whose archives keep only the success rate (the commands'
#: ``logger.eval_episodes=100``; ``hand_memory`` evaluates 100 episodes too)
EPISODES = 100

_BLOCK = re.compile(r"^<!-- generated: ([\w-]+) -->\n(.*?)^<!-- end generated: ([\w-]+) -->\n", re.S | re.M)
_OPEN = re.compile(r"^<!-- generated: [\w-]+ -->$", re.M)  # a marker is a line of its own


# -- formatting ---------------------------------------------------------------------------------------------------


def kf(frames: int) -> str:
    """60000 -> '60k', 12500 -> '12.5k', 0 -> '0'."""
    return "0" if frames == 0 else f"{frames / 1000:g}k"


def f2(x: float | None) -> str:
    return "-" if x is None else f"{x:.2f}"


def pct(x: float) -> str:
    return f"{100 * x:.1f}%"


def pv(p: float | None) -> str:
    """A p-value: two significant digits (0.34, 0.013, 3.6e-24)."""
    if p is None or math.isnan(p):
        return "-"
    return "1" if p >= 0.995 else f"{p:.2g}"


def signed(x: float) -> str:
    out = f"{x:+.2f}"
    return "0.00" if out in ("+0.00", "-0.00") else out


def cpu(x: float | None) -> str:
    if x is None:
        return "not archived"
    return f"{x:.1f}" if x < 100 else f"{x:.0f}"


def slash(values, fmt=f2) -> str:
    return " / ".join(fmt(v) for v in values)


def table(head: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


# -- statistics ---------------------------------------------------------------------------------------------------


def _mean(xs):
    return sum(xs) / len(xs)


def t_interval(xs: list[float]) -> tuple[float, float | None, float | None]:
    """Mean of per-run figures and its t-based 95% interval over runs (``None`` bounds for one run)."""
    from scipy.stats import t

    m = _mean(xs)
    if len(xs) < 2:
        return m, None, None
    s = math.sqrt(sum((x - m) ** 2 for x in xs) / (len(xs) - 1))
    half = float(t.ppf(0.975, len(xs) - 1)) * s / math.sqrt(len(xs))
    return m, m - half, m + half


def welch(a: list[float], b: list[float]) -> dict:
    """Difference of means ``a - b``, Welch's 95% interval and two-sided p (``None`` with no spread in either)."""
    from scipy.stats import t

    diff = _mean(a) - _mean(b)
    va = sum((x - _mean(a)) ** 2 for x in a) / (len(a) - 1) / len(a)
    vb = sum((x - _mean(b)) ** 2 for x in b) / (len(b) - 1) / len(b)
    se = math.sqrt(va + vb)
    if se == 0:
        return {"diff": diff, "lo": None, "hi": None, "p": None}
    df = (va + vb) ** 2 / ((va**2 / (len(a) - 1) if va else 0) + (vb**2 / (len(b) - 1) if vb else 0))
    half = float(t.ppf(0.975, df)) * se
    return {"diff": diff, "lo": diff - half, "hi": diff + half, "p": float(2 * t.sf(abs(diff) / se, df))}


def permutation(a: list[float], b: list[float]) -> dict:
    """Exact two-sided permutation test of the difference of means over every relabelling of the runs.

    Example:
        >>> r = permutation([0.9, 0.95, 0.97], [0.04, 0.09, 0.07])
        >>> r["p"], r["floor"], r["relabellings"]
        (0.1, 0.1, 20)
    """
    pooled = [*a, *b]
    stats = []
    for idx in itertools.combinations(range(len(pooled)), len(a)):
        pick = set(idx)
        stats.append(abs(_mean([pooled[i] for i in idx]) - _mean([x for i, x in enumerate(pooled) if i not in pick])))
    observed = abs(_mean(a) - _mean(b))
    n = len(stats)
    p = sum(s >= observed - 1e-12 for s in stats) / n
    floor = sum(s >= max(stats) - 1e-12 for s in stats) / n
    return {"p": p, "floor": floor, "relabellings": n}


def fisher(sa: int, na: int, sb: int, nb: int) -> float:
    from scipy.stats import fisher_exact

    return float(fisher_exact([[sa, na - sa], [sb, nb - sb]]).pvalue)


# -- what the archives hold -------------------------------------------------------------------------------------


@dataclass
class ArmData:
    """One arm, read: per seed its success, per-episode outcomes (if archived), CPU-s and where they were read."""

    label: str
    seeds: list[int]
    values: list[float]
    outcomes: dict[int, list[int]] | None
    cpu: list[float | None]
    cpu_frames: list[int | None]
    frames: list[int | None]

    def counts(self) -> tuple[int, int]:
        """Pooled successes and episodes (from the outcomes, else the rates times :data:`EPISODES`)."""
        if self.outcomes is not None:
            flat = [x for s in self.seeds for x in self.outcomes[s]]
            return sum(flat), len(flat)
        return sum(round(v * EPISODES) for v in self.values), EPISODES * len(self.values)


@dataclass(frozen=True)
class Runs:
    """Archives ``docs/runs/<pattern % seed>.json`` of ``recipes/her`` runs, read at ``at`` frames (``None``: each
    run's last evaluation)."""

    label: str
    pattern: str
    seeds: tuple[int, ...] = (0, 1, 2)
    at: int | None = None

    def paths(self, root: Path) -> list[str]:
        return [str(root / RUNS / f"{self.pattern.format(s)}.json") for s in self.seeds]

    def runs(self, root: Path) -> list[dict]:
        from recipes.her.tools.compare import load_run

        return [load_run(p) for p in self.paths(root)]

    def read(self, root: Path) -> ArmData:
        from recipes.her.tools.paired import arm_outcomes

        values, frames = [], []
        runs = self.runs(root)
        for path, run in zip(self.paths(root), runs):
            at = {int(x): float(y) for x, y in run["curve"]}
            f = max(at) if self.at is None else self.at
            if f not in at:
                raise KeyError(f"{path}: no evaluation at {f} frames")
            values.append(at[f])
            frames.append(f)
        try:
            outcomes = {}
            for path, f, seed, value in zip(self.paths(root), frames, self.seeds, values):
                outcomes[seed] = arm_outcomes([path], f)[seed]
                if abs(sum(outcomes[seed]) / len(outcomes[seed]) - value) > 1e-9:
                    raise ValueError(f"{path}: the curve and the episodes disagree at {f} frames")
        except KeyError:
            outcomes = None  # archived before runs kept per-episode outcomes
        return ArmData(self.label, list(self.seeds), values, outcomes, [r["cpu_s"] for r in runs],
                       [int(r["curve"][-1][0]) for r in runs], frames)

    def curve(self, root: Path, seed: int) -> dict[int, float]:
        run = self.runs(root)[self.seeds.index(seed)]
        return {int(x): float(y) for x, y in run["curve"]}


@dataclass(frozen=True)
class CrossEnvArm:
    """One arm of the scripted FetchSlide experiment, ``docs/cross_env/results.json`` (a seed is a replicate:
    its own memory and its own evaluation env seeds)."""

    label: str
    key: str

    def read(self, root: Path) -> ArmData:
        with open(root / CROSS_ENV) as f:
            res = json.load(f)
        outcomes = {i: [int(x) for x in o] for i, o in enumerate(res["outcomes"][self.key])}
        seeds = sorted(outcomes)
        values = [sum(outcomes[s]) / len(outcomes[s]) for s in seeds]
        return ArmData(self.label, seeds, values, outcomes, [None] * len(seeds), [None] * len(seeds),
                       [None] * len(seeds))


@dataclass(frozen=True)
class HandArm:
    """Lines of a ``experiments.her.hand_memory`` result file (``docs/runs/*.jsonl``) for a ``what``, at the
    round whose memory holds ``rows`` rows (``None``: the last round); one line a seed."""

    label: str
    file: str
    what: str
    seeds: tuple[int, ...] = (0,)
    rows: int | None = None
    horizon: int = 1

    def lines(self, root: Path) -> list[dict]:
        with open(root / RUNS / self.file) as f:
            return [json.loads(line) for line in f if line.strip()]

    def rounds(self, root: Path, seed: int) -> list[dict]:
        out = [d for d in self.lines(root)
               if d["what"] == self.what and d.get("seed") == seed and d.get("horizon") == self.horizon]
        return sorted(out, key=lambda d: d["round"])

    def read(self, root: Path) -> ArmData:
        picked = []
        for s in self.seeds:
            rounds = self.rounds(root, s)
            pick = rounds[-1] if self.rows is None else next(d for d in rounds if d["memory_rows"] == self.rows)
            picked.append(pick)
        outcomes = ({s: [int(c) for c in d["outcomes"]] for s, d in zip(self.seeds, picked)}
                    if all("outcomes" in d for d in picked) else None)  # archived before the tool kept them
        return ArmData(self.label, list(self.seeds), [d["success"] for d in picked], outcomes,
                       [d["cpu_s"] for d in picked], [d["memory_rows"] for d in picked],
                       [d["memory_rows"] for d in picked])


# -- comparisons --------------------------------------------------------------------------------------------------


def compare(a: ArmData, b: ArmData) -> dict:
    """Run-level and episode-level comparison of arm ``a`` (with the memory) against arm ``b``."""
    from recipes.her.tools.paired import compare_arms

    out = {"a": a, "b": b, "run": welch(a.values, b.values), "perm": permutation(a.values, b.values),
           "ci_a": t_interval(a.values), "ci_b": t_interval(b.values)}
    if a.outcomes is not None and b.outcomes is not None and a.seeds == b.seeds:
        r = compare_arms(a.outcomes, b.outcomes)
        t = r["test"]
        out["episode"] = {"test": "McNemar", "p": t["p"], "a_only": t["a_only"], "b_only": t["b_only"],
                          "pooled_a": r["pooled"]["a"], "pooled_b": r["pooled"]["b"], "n": r["pooled"]["n"]}
    else:
        (sa, na), (sb, nb) = a.counts(), b.counts()
        out["episode"] = {"test": "Fisher", "p": fisher(sa, na, sb, nb), "sa": sa, "na": na, "sb": sb, "nb": nb,
                          "pooled_a": sa / na, "pooled_b": sb / nb, "n": na}
    return out


def run_level(c: dict, short: bool = False) -> str:
    """Each arm's mean over runs [t 95% CI], the difference [Welch 95% CI] and its tests; ``short``: the difference
    and the tests alone."""
    w, perm = c["run"], c["perm"]
    ci = "" if w["lo"] is None else f" [{signed(max(-1.0, w['lo']))}, {signed(min(1.0, w['hi']))}]"
    floor = f" (the floor for {len(c['a'].values)} vs {len(c['b'].values)})" if perm["p"] <= perm["floor"] else ""
    welch_p = "Welch p: no spread" if w["p"] is None else f"Welch p = {pv(w['p'])}"
    tests = f"{signed(w['diff'])}{ci}, {welch_p}; permutation p = {pv(perm['p'])}{floor}"
    if short:
        return tests
    return f"mean {interval(c['a'].values)} vs {interval(c['b'].values)}, difference {tests}"


def episode_level(c: dict) -> str:
    e = c["episode"]
    if e["test"] == "McNemar":
        return (f"{e['pooled_a']:.3f} vs {e['pooled_b']:.3f} of {e['n']} paired episodes, McNemar p = {pv(e['p'])} "
                f"({e['a_only']} vs {e['b_only']} discordant)")
    return f"{e['sa']}/{e['na']} vs {e['sb']}/{e['nb']} episodes, Fisher p = {pv(e['p'])}"


def interval(xs: list[float]) -> str:
    m, lo, hi = t_interval(xs)
    if lo is None:
        return f"{f2(m)} (one run: no run-level interval)"
    return f"{f2(m)} [{f2(max(0.0, lo))}, {f2(min(1.0, hi))}]"


def wilson_text(successes: int, n: int) -> str:
    from recipes.her.tools.stats import wilson

    lo, hi = wilson(successes, n)
    return f"{successes}/{n}, Wilson 95% CI [{lo:.2f}, {hi:.2f}]"


def costs(arm: ArmData) -> str:
    """CPU-s per run at its last archived evaluation, with that evaluation's frames where they differ from the
    frames the arm is read at."""
    parts = []
    for c, at, read in zip(arm.cpu, arm.cpu_frames, arm.frames):
        where = "" if c is None or at == read or at is None else f" (at {kf(at)})"
        parts.append(cpu(c) + where)
    if all(c is None for c in arm.cpu):
        return "not archived"
    return " / ".join(parts)


# -- the blocks -------------------------------------------------------------------------------------------------

PUSH_CLONE = Runs("cloned, anchored", "anchor100-push-s{}", at=0)
PUSH_SCRATCH = Runs("from scratch", "scratch-push-s{}", at=60000)
# The clone arms run TD3 with the anchor, a frozen normaliser and no random frames; the scratch arm is the plain SAC
# recipe: those rows compare two recipes, not the memory alone (issue 42), and say so.
PUSH_SCRATCH_SAC = Runs("the plain SAC recipe from scratch: another algorithm and settings, not only no memory",
                        "scratch-push-s{}", at=60000)
PUSH_PRIOR60 = Runs("noisy memory as prior", "prior-push-s{}", at=60000)
PNP_CLONE = Runs("own memory cloned", "clone-pnp-s{}", at=0)
PNP_NOISY = Runs("own noisy memory cloned", "clonenoisy-pnp-s{}", at=0)
PNP_PUSH = Runs("FetchPush memory as prior", "pushprior-pnp-s{}", at=60000)
PNP_SCRATCH = Runs("from scratch", "scratch-pnp-s{}", at=60000)
PNP_SCRATCH_SAC = Runs("the plain SAC recipe from scratch: another algorithm and settings, not only no memory",
                       "scratch-pnp-s{}", at=60000)
SLIDE_MEMORY = CrossEnvArm("pooled memory", "pooled_memory")
SLIDE_CONTROL = CrossEnvArm("pooled control", "pooled_control")
SLIDE_AT = 65000  # the last evaluation every clamped FetchSlide run has (prior-clip-s1 stopped there)
SLIDE_PRIOR = Runs("pooled memory as prior", "slide100k-prior-clip-s{}", at=SLIDE_AT)
SLIDE_SCRATCH = Runs("from scratch", "slide100k-scratch-clip-s{}", at=SLIDE_AT)
SLIDE_SCRATCH_END = Runs("from scratch, 100k", "slide100k-scratch-clip-s{}", at=100000)
SLIDE30_CONTROL = Runs("control (prior, clamped targets)", "slide100k-prior-clip-s{}", at=30000)
SLIDE30_RECALL = Runs("+ `RecallTransform`", "slide30k-recall-clip-s{}", at=30000)
SLIDE30_SAMPLER = Runs("+ `GoalSimilaritySampler`", "slide30k-sampler-clip-s{}", at=30000)
PUSH30_CONTROL = Runs("control (prior, clamped targets)", "push30k-prior-clip-s{}", at=30000)
PUSH30_RECALL = Runs("+ `RecallTransform`", "push30k-recall-clip-s{}", at=30000)
PUSH30_SAMPLER = Runs("+ `GoalSimilaritySampler`", "push30k-sampler-clip-s{}", at=30000)
PUSH30_SAC = Runs("SAC+HER from the memory", "push30k-prior-clip-s{}", at=30000)
PUSH30_K50 = Runs("memory learning, k = 50", "push30k-improve-k50-s{}", at=30000)
PUSH30_K5 = Runs("memory learning, k = 5", "push30k-improve-k5-s{}", at=30000)
PUSH30_RESIDUAL = Runs("residual SAC, penalty 30", "push30k-residual-s{}", at=30000)
PUSH30_RESIDUAL3 = Runs("residual SAC, penalty 3", "push30k-residual-pen3-s{}", seeds=(0,), at=30000)
HAND_GCSL = HandArm("GCSL from random data", "hand_gcsl_random.jsonl", "gcsl", seeds=(0, 1, 2))
HAND_CLONE = HandArm("hindsight clone of the SAC run's memory", "hand_memory.jsonl", "clone")
HAND_GCSL_MEMORY = HandArm("GCSL on the SAC run's memory", "hand_memory.jsonl", "gcsl")
HAND_SAC = Runs("SAC+HER from scratch", "hand_reach-s{}-out", seeds=(0, 1))
#: issue 43 on HandReach: GCSL from 10k random frames, 28 rounds of 100 episodes (150k frames in all), with and
#: without GoalProposer goals in half the collection episodes; then a second run on each first run's memory
HAND43_GCSL_CONTROL = HandArm("GCSL", "hand43-gcsl-control.jsonl", "gcsl", seeds=(0, 1, 2))
HAND43_GCSL_PROPOSE = HandArm("GCSL + GoalProposer", "hand43-gcsl-propose.jsonl", "gcsl", seeds=(0, 1, 2))
HAND43_GCSL_QUARTER = HandArm("GCSL + GoalProposer, rate 0.25", "hand43-gcsl-propose25.jsonl", "gcsl", seeds=(0, 1, 2))
HAND43_GCSL_NEAR = HandArm("GCSL + GoalProposer, near the env's goal", "hand43-gcsl-near.jsonl", "gcsl",
                           seeds=(0, 1, 2))
HAND43_GCSL_REACHED = HandArm("GCSL + GoalProposer, reached in 2 episodes", "hand43-gcsl-reached2.jsonl", "gcsl",
                              seeds=(0, 1, 2))
HAND43_SECOND = {"control": HandArm("second run, GCSL", "hand43-gcsl-second-control.jsonl", "gcsl", seeds=(0, 1, 2)),
                 "propose": HandArm("second run, GCSL + GoalProposer", "hand43-gcsl-second-propose.jsonl", "gcsl",
                                    seeds=(0, 1, 2))}


@dataclass(frozen=True)
class Headline:
    """One row of the summary: the arm with the memory against the one without."""

    task: str
    buys: str
    memory: Runs | CrossEnvArm
    control: Runs | CrossEnvArm
    link: str


HEADLINES = (
    Headline("FetchPush-v4 (3), 500 scripted episodes, actor cloned", "a policy before the first env frame",
             PUSH_CLONE, PUSH_SCRATCH_SAC, "#the-actor-cloned-from-the-memory-kept-by-the-anchor"),
    Headline("FetchPush-v4 (3), 500 noisy scripted episodes as half of every batch", "replay data: a plateau below 0.9",
             PUSH_PRIOR60, PUSH_SCRATCH, "#the-memory-as-replay-data-only-a-plateau-below-09"),
    Headline("FetchPush-v4 (3), the noisy memory read by the controller that wrote it (k = 50)",
             "0.95 within 30k new frames, by recall", PUSH30_K50, PUSH30_SAC,
             "#goal-2-fetchpush-from-the-noisy-memory-to-095-within-30k-new-frames"),
    Headline("FetchPickAndPlace-v4 (3), its own 500 scripted episodes, cloned", "a policy before the first env frame",
             PNP_CLONE, PNP_SCRATCH_SAC, "#fetchpickandplace-v4"),
    Headline("FetchPickAndPlace-v4 (3), a FetchPush memory as prior", "pushing, not lifting", PNP_PUSH, PNP_SCRATCH,
             "#fetchpickandplace-v4"),
    Headline("FetchSlide-v4 (5 replicates x 200 episodes), scripted controller, FetchPush + FetchSlide memory",
             "recalled strike parameters", SLIDE_MEMORY, SLIDE_CONTROL,
             "#cross-environment-fetchslide-from-fetchpush-and-fetchslide-memories"),
    Headline("FetchSlide-v4 (3), SAC+HER, the same memory as prior", "every seed to 0.5 within 100k",
             SLIDE_PRIOR, SLIDE_SCRATCH, "#to-100k-frames-three-seeds-issue-27-goal-1"),
    Headline("FetchSlide-v4 (3), prior memory + `RecallTransform`", "no gain", SLIDE30_RECALL, SLIDE30_CONTROL,
             "#recalltransform-and-goalsimilaritysampler-issue-27-goal-4"),
    Headline("FetchSlide-v4 (3), prior memory + `GoalSimilaritySampler`", "no gain", SLIDE30_SAMPLER,
             SLIDE30_CONTROL, "#recalltransform-and-goalsimilaritysampler-issue-27-goal-4"),
    Headline("FetchPush-v4 (3), noisy prior + `RecallTransform`", "no gain", PUSH30_RECALL, PUSH30_CONTROL,
             "#recalltransform-and-goalsimilaritysampler-issue-27-goal-4"),
    Headline("FetchPush-v4 (3), noisy prior + `GoalSimilaritySampler`", "no gain", PUSH30_SAMPLER, PUSH30_CONTROL,
             "#recalltransform-and-goalsimilaritysampler-issue-27-goal-4"),
    Headline("HandReach-v3 (3), GCSL from random data + `GoalProposer` (half the collection episodes)",
             "no gain: lower on every seed", HAND43_GCSL_PROPOSE, HAND43_GCSL_CONTROL,
             "#handreach-v3-gcsl-three-seeds-with-and-without-the-proposer"),
)


def _frames_of(arm: ArmData) -> str:
    fs = {f for f in arm.frames}
    if fs == {None}:
        return "-"
    return kf(fs.pop()) if len(fs) == 1 else slash(arm.frames, kf)


def summary(root: Path) -> str:
    rows = []
    for h in HEADLINES:
        c = compare(h.memory.read(root), h.control.read(root))
        a, b = c["a"], c["b"]
        at_a, at_b = _frames_of(a), _frames_of(b)
        frames = f"{at_a} / {at_b}" if at_a != "-" else "200 episodes a replicate"
        cost = costs(a)
        if isinstance(h.memory, CrossEnvArm):
            with open(root / CROSS_ENV) as f:
                cost = f"{json.load(f)['seconds']:.0f} s wall for all arms"
        rows.append([
            f"[{h.task}]({h.link})", h.buys,
            f"**{slash(a.values)}** ({a.label}) vs {slash(b.values)} ({b.label})",
            run_level(c), episode_level(c), frames, cost,
        ])
    hand = HAND_GCSL.read(root)
    (s, n) = hand.counts()
    rows.append([
        "[HandReach-v3 (3), GCSL from random data](#shadow-hand-handreach-v3)", "supervised rounds climb, slowly",
        f"**{slash(hand.values)}** at {_frames_of(hand)} frames in all (SAC+HER from scratch: "
        f"{slash(HAND_SAC.read(root).values)} at {slash(HAND_SAC.read(root).frames, kf)})",
        f"mean {interval(hand.values)} (t, over seeds)", f"pooled {wilson_text(s, n)}", _frames_of(hand),
        slash(hand.cpu, cpu) + f" (the tool's CPU; the {kf(HAND_GCSL.rounds(root, 0)[0]['memory_rows'])} random "
                               "frames before it not counted)",
    ])
    head = ["task (seeds)", "what the memory buys", "success per seed: with memory vs without",
            "run-level: mean of the seeds [95% t-CI], with vs without; difference [95% Welch CI], tests",
            "episode-level: pooled episodes, test", "frames (with / without)", "CPU-s per run, with memory"]
    return table(head, rows)


def _curve_rows(root: Path, arms: list[tuple[str, str, int]], frames: list[int],
                target: float | None = None) -> list[list[str]]:
    """One row a run ``(label, archive pattern, seed)``: its success at ``frames``, the first evaluation at or
    above ``target`` and its CPU-s at its last evaluation."""
    from recipes.her.run_record import first_reach

    rows = []
    for label, pattern, seed in arms:
        run = Runs(label, pattern, (seed,)).runs(root)[0]
        at = {int(x): float(y) for x, y in run["curve"]}
        cells = [f2(at[f]) if f in at else "" for f in frames]
        extra = []
        if target is not None:
            reach = first_reach(run["curve"], target)
            extra.append("-" if reach is None else f"**{kf(reach)}**")
        extra.append(f"{cpu(run['cpu_s'])} at {kf(int(run['curve'][-1][0]))}" if run["cpu_s"] is not None
                     else "not archived")
        rows.append([label, *cells, *extra])
    return rows


def push_clone(root: Path) -> str:
    clone, scratch = PUSH_CLONE.read(root), PUSH_SCRATCH.read(root)
    c = compare(clone, scratch)
    head = (f"**At frame 0, cloned (TD3, anchor, frozen normaliser): {slash(clone.values)}; the plain SAC recipe "
            f"from scratch at 60k frames: {slash(scratch.values)}** (two recipes, not the memory alone). "
            f"Run-level: {run_level(c)}. Episode-level: {episode_level(c)}.")
    frames = [0, 2500, 5000, 7500, 10000, 12500]
    rows = []
    for seed in clone.seeds:
        at = PUSH_CLONE.curve(root, seed)
        sc = PUSH_SCRATCH.curve(root, seed)
        rows.append([str(seed), *[(f"**{f2(at[f])}**" if at[f] >= 0.9 else f2(at[f])) if f in at else ""
                                  for f in frames],
                     f"{f2(sc[60000])} ({f2(max(sc.values()))}), {cpu(scratch.cpu[clone.seeds.index(seed)])}"])
    t = table(["seed", *[kf(f) for f in frames], "from scratch: at 60k (best), CPU-s"], rows)
    return head + "\n\n" + t


def push_replay(root: Path) -> str:
    prior, scratch = PUSH_PRIOR60.read(root), PUSH_SCRATCH.read(root)
    c = compare(prior, scratch)
    head = (f"**At 60k frames: {slash(prior.values)} with the noisy memory as prior; {slash(scratch.values)} from "
            f"scratch.** Run-level: {run_level(c)}. Episode-level: {episode_level(c)}.")
    rows = []
    for arm, data in ((PUSH_PRIOR60, prior), (PUSH_SCRATCH, scratch)):
        cells = []
        for seed, c_s in zip(data.seeds, data.cpu):
            curve = arm.curve(root, seed)
            cells.append(f"{f2(curve[60000])} ({f2(max(curve.values()))}), {cpu(c_s)}")
        means = [f2(_mean([arm.curve(root, s)[f] for s in data.seeds])) for f in (20000, 40000, 60000)]
        rows.append([f"{arm.label}: final (best), CPU-s", *cells, " / ".join(means)])
    return head + "\n\n" + table(["run", "seed 0", "seed 1", "seed 2", "mean at 20k / 40k / 60k"], rows)


def _lowest(curve: dict[int, float], upto: int) -> float:
    return min(y for x, y in curve.items() if x <= upto)


def push_goal2(root: Path) -> str:
    from recipes.her.tools.paired import arm_outcomes, compare_arms

    k50, sac = PUSH30_K50.read(root), PUSH30_SAC.read(root)
    c = compare(k50, sac)
    start = Runs("", PUSH30_K50.pattern, at=0).read(root)
    head = (f"**Recall (k = 50): {slash(start.values)} at 0 new frames, {slash(k50.values)} at 30k; lowest evaluation "
            f"on the way {slash([_lowest(PUSH30_K50.curve(root, s), 30000) for s in k50.seeds])}.** Against SAC+HER "
            f"from the same memory at 30k ({slash(sac.values)}): run-level {run_level(c)}; episode-level "
            f"{episode_level(c)}.")
    rows = []
    for arm in (PUSH30_K50, PUSH30_K5, PUSH30_RESIDUAL, PUSH30_RESIDUAL3, PUSH30_SAC):
        data = arm.read(root)
        cells = []
        for seed in (0, 1, 2):
            if seed not in arm.seeds:
                cells.append("")
                continue
            curve = arm.curve(root, seed)
            cells.append(f"{f2(curve[0])} / {f2(curve[30000])} ({f2(_lowest(curve, 30000))})")
        if arm is PUSH30_SAC or len(arm.seeds) < 2:
            paired, runlvl = "", ""
        else:
            paths = arm.paths(root)
            r = compare_arms(arm_outcomes(paths, 30000), arm_outcomes(paths, 0))
            t = r["test"]
            paired = (f"{r['pooled']['a']:.3f} vs {r['pooled']['b']:.3f}, p = {pv(t['p'])} "
                      f"({t['a_only']} vs {t['b_only']})")
            if arm is PUSH30_RESIDUAL:
                r10 = compare_arms(arm_outcomes(paths, 10000), arm_outcomes(paths, 0))
                paired += (f"; at 10k {r10['pooled']['a']:.3f} vs {r10['pooled']['b']:.3f}, "
                           f"p = {pv(r10['test']['p'])}")
            diffs = [arm.curve(root, s)[30000] - arm.curve(root, s)[0] for s in arm.seeds]
            m, lo, hi = t_interval(diffs)
            runlvl = f"{signed(m)} [{signed(lo)}, {signed(hi)}]"
        rows.append([arm.label, *cells, runlvl, paired, slash(data.cpu, cpu)])
    head_row = ["at 0 / 30k new frames (lowest evaluation from 0 to 30k)", "seed 0", "seed 1", "seed 2",
                "run-level: 30k minus 0, mean [95% t-CI over seeds]", "episode-level: 30k vs 0 (McNemar, discordant)",
                "training CPU-s per run"]
    return head + "\n\n" + table(head_row, rows)


def _ablation(root: Path, control: Runs, arms: tuple[Runs, ...]) -> str:
    ctl = control.read(root)
    rows = [[ctl.label, *[f2(v) for v in ctl.values], interval(ctl.values), "", "", costs(ctl)]]
    for arm in arms:
        data = arm.read(root)
        c = compare(data, ctl)
        rows.append([data.label, *[f2(v) for v in data.values], interval(data.values), run_level(c, short=True),
                     episode_level(c), costs(data)])
    head = ["at 30k frames", "seed 0", "seed 1", "seed 2", "run-level: mean [95% t-CI]",
            "run-level vs control: difference [95% CI], tests", "episode-level vs control (paired by seed and goal)",
            "CPU-s per run"]
    return table(head, rows)


def slide_goal4(root: Path) -> str:
    return _ablation(root, SLIDE30_CONTROL, (SLIDE30_RECALL, SLIDE30_SAMPLER))


def push_goal4(root: Path) -> str:
    return _ablation(root, PUSH30_CONTROL, (PUSH30_RECALL, PUSH30_SAMPLER))


def pnp(root: Path) -> str:
    clone, noisy, push, scratch = (a.read(root) for a in (PNP_CLONE, PNP_NOISY, PNP_PUSH, PNP_SCRATCH))
    c1, c2 = compare(clone, scratch), compare(push, scratch)
    head = (f"**Its own memory cloned (TD3, frozen normaliser): {slash(clone.values)} at frame 0; the plain SAC recipe "
            f"from scratch at 60k: {slash(scratch.values)}** (two recipes, not the memory alone) "
            f"(run-level {run_level(c1)}; episode-level {episode_level(c1)}). A FetchPush memory as prior: "
            f"{slash(push.values)} at 60k (run-level {run_level(c2, short=True)}; episode-level {episode_level(c2)}).")
    anchor = Runs("", "anchor100-pnp-s{}", seeds=(0,))
    a0 = anchor.curve(root, 0)
    rows = [
        ["own memory (500 scripted episodes, default parameters), cloned: frame 0", *[f2(v) for v in clone.values],
         costs(clone) + " before frame 0"],
        ["own memory, noisy parameters, cloned: frame 0", *[f2(v) for v in noisy.values],
         costs(noisy) + " before frame 0"],
        [f"own memory cloned, `prior.clone_anchor=100`: {slash(sorted(a0), kf)} frames", slash(a0.values()), "", "",
         f"{cpu(anchor.runs(root)[0]['cpu_s'])} at {kf(max(a0))}"],
    ]
    for arm, data in ((PNP_PUSH, push), (PNP_SCRATCH, scratch)):
        rows.append([f"{arm.label}: 60k (best)",
                     *[f"{f2(v)} ({f2(max(arm.curve(root, s).values()))})" for s, v in zip(data.seeds, data.values)],
                     costs(data)])
    return head + "\n\n" + table(["run", "seed 0", "seed 1", "seed 2", "CPU-s"], rows)


def slide_scripted(root: Path) -> str:
    with open(root / CROSS_ENV) as f:
        res = json.load(f)
    c = compare(SLIDE_MEMORY.read(root), SLIDE_CONTROL.read(root))
    head = (f"**Pooled memory against pooled control: {signed(c['run']['diff'])}** "
            f"(per replicate {slash(c['a'].values)} against {slash(c['b'].values)}). Run-level: {run_level(c)}. "
            f"Episode-level: {episode_level(c)}. Cost: {res['seconds']:.0f} s for the scripted arms.")
    labels = {"baseline": "baseline (tuned defaults)", "push_control": "Push control", "push_memory": "Push memory",
              "pooled_control": "pooled control", "pooled_memory": "**pooled memory**",
              "pooled_mixed": "pooled, env-blind"}
    rows = []
    for key, label in labels.items():
        arm = res["summary"]["arms"][key]
        lo, hi = arm["ci95"]
        rows.append([label, f"{pct(arm['rate'])} ({arm['successes']}/{arm['n']})", f"{pct(lo)} - {pct(hi)}",
                     slash(arm["per_seed"]), interval(arm["per_seed"])])
    return head + "\n\n" + table(["arm", "success (episode-level)", "95% CI (Wilson, episode-level)",
                                  "per replicate", "run-level: mean [95% t-CI over replicates]"], rows)


def slide_learned(root: Path) -> str:
    with open(root / CROSS_ENV) as f:
        learned = json.load(f)["learned"]
    rows = []
    for p_run, s_run in zip(learned["runs"]["prior"], learned["runs"]["scratch"]):
        at = {int(x): y for x, y in p_run["curve"]}
        sc = [y for _, y in s_run["curve"]]
        rows.append([str(p_run["seed"]), f"{f2(at[10000])} / {f2(at[30000])}", cpu(p_run["cpu_s"]),
                     f"{f2(min(sc))}-{f2(max(sc))}", cpu(s_run["cpu_s"])])
    return table(["seed", "prior memory at 10k / 30k", "CPU-s", "from scratch to 30k", "CPU-s"], rows)


SLIDE_FRAMES = [10000, 20000, 30000, 40000, 50000, 60000, 65000, 70000, 75000, 80000, 90000, 100000]


def slide_100k(root: Path) -> str:
    prior, scratch, end = SLIDE_PRIOR.read(root), SLIDE_SCRATCH.read(root), SLIDE_SCRATCH_END.read(root)
    c = compare(prior, scratch)
    from recipes.her.run_record import first_reach

    reach = [first_reach([[x, y] for x, y in sorted(SLIDE_PRIOR.curve(root, s).items())], 0.5) for s in prior.seeds]
    head = (f"**With the memory as prior every seed reaches 0.5: at {slash(reach, kf)} frames. From scratch: "
            f"{slash(end.values)} at 100k.** At {kf(SLIDE_AT)}, the last evaluation all six runs share: "
            f"{slash(prior.values)} against {slash(scratch.values)}; run-level {run_level(c)}; episode-level "
            f"{episode_level(c)}.")
    arms = [(f"prior, seed {s} (`prior-clip-s{s}`)", "slide100k-prior-clip-s{}", s) for s in (0, 1, 2)]
    arms += [(f"from scratch, seed {s} (`scratch-clip-s{s}`)", "slide100k-scratch-clip-s{}", s) for s in (0, 1, 2)]
    rows = _curve_rows(root, arms, SLIDE_FRAMES, target=0.5)
    return head + "\n\n" + table(["run", *[kf(f) for f in SLIDE_FRAMES], "first >= 0.5", "CPU-s (at the last evaluation)"],
                                 rows)


def hand(root: Path) -> str:
    sac = HAND_SAC.read(root)
    clone = HAND_CLONE.read(root)
    gcsl = HAND_GCSL_MEMORY.read(root)
    random = HAND_GCSL.read(root)
    s, n = random.counts()
    head = (f"**From scratch SAC+HER ends at {slash(sac.values)} ({slash(sac.frames, kf)} frames). Its memory cloned "
            f"with hindsight goals: {f2(clone.values[0])} at 0 new frames ({cpu(clone.cpu[0])} CPU-s); GCSL rounds on "
            f"it: {f2(gcsl.values[0])} after {kf(gcsl.frames[0] - clone.frames[0])} new frames "
            f"({cpu(gcsl.cpu[0])} CPU-s), one seed. GCSL from random data, three seeds: {slash(random.values)} at "
            f"{_frames_of(random)} frames in all** (run-level mean {interval(random.values)}; episode-level pooled "
            f"{wilson_text(s, n)}).")
    cols = [10000, 30000, 50000, 75000, 100000, 125000, 150000]
    rows = []
    for seed in HAND_GCSL.seeds:
        rounds = {d["memory_rows"]: d for d in HAND_GCSL.rounds(root, seed)}
        best = max(d["success"] for d in rounds.values())
        rows.append([f"seed {seed}", *[f2(rounds[f]["success"]) for f in cols], f2(best),
                     cpu(rounds[max(rounds)]["cpu_s"])])
    t = table(["GCSL from random data: frames in all", *[kf(f) for f in cols], "best",
               "CPU-s of the rounds (the random collection not counted)"], rows)
    return head + "\n\n" + t


# -- the history page (docs/notes/results_history.md) ------------------------------------------------------------

#: SAC+HER on FetchPush from a scripted memory, at 30k new frames: (label, archive pattern, seeds)
PUSH_VARIANTS = (
    ("noisy memory, unclamped targets, 3000 pretraining updates (`prior-push`)", "prior-push-s{}", (0, 1, 2)),
    ("noisy memory, clamped targets, the recipe's defaults now (`push30k-prior-clip`)", "push30k-prior-clip-s{}",
     (0, 1, 2)),
    ("+ LayerNorm critics (`ln-prior-push`)", "ln-prior-push-s{}", (0, 1)),
    ("+ prior share annealed 0.5 -> 0.1 over 30k (`anneal-push`)", "anneal-push-s{}", (0,)),
    ("+ Q-filtered cloning of the memory's actions (`bc-push`)", "bc-push-s{}", (0, 1, 2)),
    ("+ two updates a frame (`utd2-push`)", "utd2-push-s{}", (0, 1)),
    ("the memory at **default** parameters instead (`cleanprior-push`)", "cleanprior-push-s{}", (0, 1, 2)),
    ("no memory (`scratch-push`)", "scratch-push-s{}", (0, 1, 2)),
)

#: the default-parameter FetchPush memory cloned into the actor, then online RL (``prior_runs`` names)
CLONE_VARIANTS = (
    ("SAC + Q-filtered BC (`clone-push`)", "clone-push-s{}", (0, 1, 2)),
    ("TD3 + BC, weight 0.4 (`clonetd3-push`)", "clonetd3-push-s{}", (0, 1, 2)),
    ("TD3 + BC, weight 4 (`clonetd3bc4-push`)", "clonetd3bc4-push-s{}", (0, 1)),
    ("... imitating original-goal rows only (`clonetd3og-push`)", "clonetd3og-push-s{}", (0, 1)),
    ("... actor frozen for the first 10k frames (`clonefreeze-push`)", "clonefreeze-push-s{}", (0, 1)),
    ("... frozen normaliser, 100x smaller actor lr (`keep-push`)", "keep-push-s{}", (0, 1, 2)),
    ("CRR actor loss (`crr-push`)", "crr-push-s{}", (0, 1, 2)),
    ("CRR, exploration noise 0.05 (`crrlow-push`)", "crrlow-push-s{}", (0,)),
    ("anchor, weight 10 (`anchor-push`)", "anchor-push-s{}", (0,)),
    ("anchor, weight 100 (`anchor100-push`)", "anchor100-push-s{}", (0, 1, 2)),
)


def history_push_variants(root: Path) -> str:
    rows = []
    for label, pattern, seeds in PUSH_VARIANTS:
        arm = Runs(label, pattern, seeds)
        cells = []
        for seed in (0, 1, 2):
            if seed not in seeds:
                cells.append("")
                continue
            curve = arm.curve(root, seed)
            if 30000 in curve:
                cells.append(f"{f2(curve[30000])} ({f2(max(y for x, y in curve.items() if x <= 30000))})")
            else:
                last = max(curve)
                cells.append(f"{f2(curve[last])} at {kf(last)}, stopped")
        rows.append([label, *cells])
    return table(["at 30k new frames (best evaluation up to 30k)", "seed 0", "seed 1", "seed 2"], rows)


def history_clone_variants(root: Path) -> str:
    frames = [0, 2500, 5000, 7500, 10000, 12500]
    rows = []
    for label, pattern, seeds in CLONE_VARIANTS:
        arm = Runs(label, pattern, seeds)
        for seed in seeds:
            curve = arm.curve(root, seed)
            rows.append([label, str(seed), *[f2(curve[f]) if f in curve else "" for f in frames]])
    return table(["the clone, then online", "seed", *[kf(f) for f in frames]], rows)


HISTORY_SLIDE_FRAMES = [10000, 20000, 30000, 40000, 45000, 50000, 55000, 60000, 65000, 70000, 75000, 80000, 85000,
                        90000, 95000, 100000]
HISTORY_SLIDE_RUNS = (
    *[(f"seed {s}, unclamped targets (`prior-s{s}`)", "slide100k-prior-s{}", s) for s in (0, 1, 2)],
    ("from scratch, seed 0, unclamped (`scratch-s0`)", "slide100k-scratch-s{}", 0),
    *[(f"seed {s}, clamped targets (`prior-clip-s{s}`)", "slide100k-prior-clip-s{}", s) for s in (0, 1, 2)],
    *[(f"from scratch, clamped, seed {s} (`scratch-clip-s{s}`)", "slide100k-scratch-clip-s{}", s) for s in (0, 1, 2)],
)


def history_slide_100k(root: Path) -> str:
    rows = _curve_rows(root, list(HISTORY_SLIDE_RUNS), HISTORY_SLIDE_FRAMES, target=0.5)
    return table(["run", *[kf(f) for f in HISTORY_SLIDE_FRAMES], "first >= 0.5", "CPU-s (at the last evaluation)"],
                 rows)


def history_hand(root: Path) -> str:
    frames = list(range(0, 65000, 5000))
    rows = []
    for label, arm, seed in (("SAC seed 0", HAND_SAC, 0), ("SAC seed 1", HAND_SAC, 1),
                             ("DDPG seed 0", Runs("", "hand_reach-ddpg-s{}-out", (0,)), 0)):
        curve = arm.curve(root, seed)
        rows.append([label, *[f2(curve[f]) if f in curve else "" for f in frames]])
    return table(["frames", *[kf(f) for f in frames]], rows)


def history_hand_clone(root: Path) -> str:
    lines = HAND_CLONE.lines(root)
    cover = next(d for d in lines if d["what"] == "cover")
    clones = sorted((d for d in lines if d["what"] == "clone"), key=lambda d: d["horizon"])
    gcsl = HAND_GCSL_MEMORY.rounds(root, 0)
    first = (f"Memory cover: of {cover['pinch_goals']} pinch goals, {pct(cover['within_0.01'])} lie within 0.01 of a "
             f"state the run reached, {pct(cover['within_0.02'])} within 0.02 (median distance to the nearest "
             f"{cover['nearest_median']:.4f}).")
    t = table(["relabelling horizon h", *[str(d["horizon"]) for d in clones]],
              [["evaluated success (100 episodes)", *[f2(d["success"]) for d in clones]],
               ["CPU-s", *[cpu(d["cpu_s"]) for d in clones]]])
    g = table(["GCSL on the memory: new frames", *[kf(d["new_frames"]) for d in gcsl]],
              [["success", *[f2(d["success"]) for d in gcsl]], ["CPU-s (cumulative)", *[cpu(d["cpu_s"]) for d in gcsl]]])
    return first + "\n\n" + t + "\n\n" + g


def reach_second(root: Path) -> str:
    """FetchReach: the first run from scratch, then a second run (fresh networks) on its memory, pretraining stopped
    on held-out goals (issue 42): archives ``reach-first-s{s}.json`` / ``reach-second-s{s}.json`` (the runs'
    summaries)."""
    rows, frames, zero = [], [], []
    for s in range(5):
        first = json.loads((root / "docs" / "runs" / f"reach-first-s{s}.json").read_text())
        second = json.loads((root / "docs" / "runs" / f"reach-second-s{s}.json").read_text())
        checks = ", ".join(f"{u}: {f2(x)}" for u, x in second["pretrain_checks"])
        rows.append([str(s), f"{first['frames_to_target']:,} ({cpu(first['cpu_s'])})", f"{second['memory_rows_before']:,}",
                     f"{second['pretrain_updates']} ({checks})", f2(second["curve"][0][1]),
                     f"{second['frames_to_target']:,}", cpu(second["cpu_s"])])
        frames.append(first["frames_to_target"])
        zero.append(second["frames_to_target"])
    t = table(["seed", "first run: frames to 0.95 (training CPU-s)", "memory rows", "second run: pretraining updates "
               "(held-out checks, 20 episodes each)", "second run at frame 0 (evaluation goals)",
               "second run: new frames to 0.95", "second run: training CPU-s"], rows)
    head = (f"**The second run reached 0.95 after {' / '.join(f'{z:,}' for z in zero)} new frames; the first needed "
            f"{' / '.join(f'{f:,}' for f in frames)}.** Pretraining stopped on held-out goals (seeds disjoint from the "
            f"evaluation's); the frame-0 figure is the evaluation made after it stopped.")
    return f"{head}\n\n{t}"


PNP43_CONTROL = Runs("SAC+HER from scratch", "pnp43-control-s{}", seeds=(0,))
PNP43_PROPOSER = Runs("SAC+HER from scratch + GoalProposer", "pnp43-propose-s{}", seeds=(0,))
HAND43_CONTROL = Runs("SAC+HER from scratch", "hand43-control-s{}", seeds=(0,))
HAND43_PROPOSER = Runs("SAC+HER from scratch + GoalProposer", "hand43-propose-s{}", seeds=(0,))


def _proposer_pilot(root: Path, control_arm: Runs, proposer_arm: Runs,
                    every: int | None = None) -> tuple[str, str, dict]:
    """One seed an arm, the same recipe with and without the proposer: the headline, the per-evaluation table and
    the proposer's counters (``proposer`` of the run's summary, archived as ``<run>-summary.json`` beside it).

    ``every``: the table shows the evaluations at multiples of this many frames (and a "best" column), not all."""
    from recipes.her.tools.paired import compare_arms

    control, proposer = control_arm.read(root), proposer_arm.read(root)
    curves = {arm.label: arm_curve for arm, arm_curve in
              ((control_arm, control_arm.curve(root, 0)), (proposer_arm, proposer_arm.curve(root, 0)))}
    frames = sorted(next(iter(curves.values())))
    shown = frames if every is None else [f for f in frames if f % every == 0]
    best = [] if every is None else ["best"]
    rows = [[label, *[f2(c[f]) for f in shown], *([f2(max(c.values()))] if best else []), cpu(arm.cpu[0])]
            for (label, c), arm in zip(curves.items(), (control, proposer))]
    t = table(["arm (seed 0)", *[kf(f) for f in shown], *best, "CPU-s"], rows)
    name = proposer_arm.pattern.format(0)
    summary = json.loads((root / RUNS / f"{name}-summary.json").read_text())["proposer"]
    ep = compare_arms(proposer.outcomes, control.outcomes)["test"]
    head = (f"**At {kf(frames[-1])} frames: {f2(proposer.values[0])} with the proposer, {f2(control.values[0])} "
            f"without** (one seed an arm: no run-level figure; episode-level, the same {len(control.outcomes[0])} goals: McNemar p = "
            f"{pv(ep['p'])}, {ep['a_only']} vs {ep['b_only']} discordant). The proposer chose the goal of "
            f"{summary['proposed']} training episodes ({summary['kept']} kept the env's own, before the memory held "
            f"`warmup_rows`), in {summary['seconds']:.2f} s of the run's {cpu(proposer.cpu[0])} CPU-s.")
    return head, t, summary


def _ms_a_goal(summary: dict) -> float:
    """The proposer's time a proposed goal, in ms, from a run's ``summary.json`` proposer counters."""
    return 1000 * summary["seconds"] / max(summary["proposed"], 1)


def pnp_proposer_pilot(root: Path) -> str:
    """Issue 43's pilot: FetchPickAndPlace from nothing, one seed an arm, the same recipe with and without the proposer
    (archives ``pnp43-{control,propose}-s0.json``, the runs' summaries beside them)."""
    head, t, _ = _proposer_pilot(root, PNP43_CONTROL, PNP43_PROPOSER)
    return f"{head}\n\n{t}"


PNP43_60K_CONTROL = Runs("SAC+HER from scratch", "pnp43-60k-control-s{}", seeds=(0,))
PNP43_60K_PROPOSER = Runs("SAC+HER from scratch + GoalProposer", "pnp43-60k-propose-s{}", seeds=(0,))


def pnp_proposer_60k(root: Path) -> str:
    """Issue 43 on FetchPickAndPlace to 60k frames: seed 0, the recipe with and without the proposer, side by side
    (archives ``pnp43-60k-{control,propose}-s0.json``, the runs' summaries beside them)."""
    head, t, summary = _proposer_pilot(root, PNP43_60K_CONTROL, PNP43_60K_PROPOSER)
    return f"{head} That is {_ms_a_goal(summary):.0f} ms a proposed goal.\n\n{t}"


PNP43_150K_CONTROL = Runs("SAC+HER from scratch", "pnp43-150k-control-s{}", seeds=(0, 1, 2))
PNP43_150K_PROPOSER = Runs("SAC+HER from scratch + GoalProposer", "pnp43-150k-propose-s{}", seeds=(0, 1, 2))


def pnp_proposer_150k(root: Path) -> str:
    """Issue 43 on FetchPickAndPlace to 150k frames (the goal's budget): the recipe with and without the proposer,
    a run an arm for each seed archived (``pnp43-150k-{control,propose}-sS.json``, the runs' summaries beside
    them; seed 0's runs are its 60k runs resumed). One seed: the pilot's figures; more: run-level figures."""
    if len(PNP43_150K_CONTROL.seeds) == 1:
        head, t, summary = _proposer_pilot(root, PNP43_150K_CONTROL, PNP43_150K_PROPOSER, every=15000)
        return (f"{head} That is {_ms_a_goal(summary):.0f} ms a proposed goal (the proposer's counters start again in a "
                f"resumed process: these are the last segment's, 75k to 150k frames). The table shows the evaluations "
                f"every 15k frames (of one every 2.5k) and the best of them all.\n\n{t}")
    control, propose = PNP43_150K_CONTROL.read(root), PNP43_150K_PROPOSER.read(root)
    c = compare(propose, control)
    summaries = [json.loads((root / RUNS / f"{PNP43_150K_PROPOSER.pattern.format(seed)}-summary.json").read_text())
                 ["proposer"] for seed in PNP43_150K_PROPOSER.seeds]
    head = (f"**At {_frames_of(propose)} frames: {slash(propose.values)} with the proposer, {slash(control.values)} "
            f"without** (seeds {slash(propose.seeds, str)}). Run-level: {run_level(c)}. Episode-level: "
            f"{episode_level(c)}. The proposer's time a proposed goal: "
            f"{slash([_ms_a_goal(x) for x in summaries], lambda x: f'{x:.0f}')} ms (each run's last process).")
    every = 15000
    rows, curves = [], {}
    for arm in (PNP43_150K_CONTROL, PNP43_150K_PROPOSER):
        for seed in arm.seeds:
            curves[arm.label, seed] = arm.curve(root, seed)
    shown = sorted({f for curve in curves.values() for f in curve if f % every == 0})
    for arm in (PNP43_150K_CONTROL, PNP43_150K_PROPOSER):
        data = arm.read(root)
        for seed, cpu_s in zip(arm.seeds, data.cpu):
            curve = curves[arm.label, seed]  # "-": no evaluation at that frame (a stop and resume passed it)
            rows.append([f"{arm.label}, seed {seed}", *[f2(curve[f]) if f in curve else "-" for f in shown],
                         f2(max(curve.values())), cpu(cpu_s)])
    t = table(["arm, seed", *[kf(f) for f in shown], "best", "CPU-s"], rows)
    return (f"{head} The table shows the evaluations every 15k frames (of one every 2.5k) and the best of them "
            f"all.\n\n{t}")


def hand_proposer_pilot(root: Path) -> str:
    """Issue 43's second pilot: HandReach from nothing, one seed an arm, 30k frames, with and without the proposer
    (archives ``hand43-{control,propose}-s0.json``, the runs' summaries beside them)."""
    head, t, summary = _proposer_pilot(root, HAND43_CONTROL, HAND43_PROPOSER)
    return (f"{head} That is {_ms_a_goal(summary):.0f} ms a proposed goal. One seed, a pilot: no conclusion either way.\n\n{t}")


#: the frames in all (10k random first) at which the GCSL tables show the evaluated success
GCSL_FRAMES = [10000, 30000, 50000, 75000, 100000, 125000, 150000]


def _gcsl_rounds_table(root: Path, arms: list[HandArm]) -> str:
    """One row a seed of each arm: its success at :data:`GCSL_FRAMES`, its best round and its CPU-s."""
    rows = []
    for arm in arms:
        for seed in arm.seeds:
            rounds = {d["memory_rows"]: d for d in arm.rounds(root, seed)}
            rows.append([f"{arm.label}, seed {seed}",
                         *[f2(rounds[f]["success"]) if f in rounds else "-" for f in GCSL_FRAMES],
                         f2(max(d["success"] for d in rounds.values())), cpu(rounds[max(rounds)]["cpu_s"])])
    return table(["frames in all (10k random first)", *[kf(f) for f in GCSL_FRAMES], "best",
                  "CPU-s of the rounds (the random collection not counted)"], rows)


def hand_gcsl_proposer(root: Path) -> str:
    """Issue 43 on HandReach: GCSL with and without the proposer, three seeds each, to 150k frames in all."""
    control, propose = HAND43_GCSL_CONTROL.read(root), HAND43_GCSL_PROPOSE.read(root)
    c = compare(propose, control)
    lasts = [HAND43_GCSL_PROPOSE.rounds(root, seed)[-1] for seed in propose.seeds]
    cost = [100 * last["propose_s"] / last["cpu_s"] for last in lasts]
    per_goal = [1000 * last["propose_s"] / last["proposed"] for last in lasts]
    head = (f"**At {_frames_of(propose)} frames in all: {slash(propose.values)} with the proposer, "
            f"{slash(control.values)} without.** Run-level: {run_level(c)}. Episode-level: {episode_level(c)}. "
            f"The proposer chose {slash([last['proposed'] for last in lasts], str)} goals a run (of 2,800 "
            f"collection episodes) in {slash(cost, lambda x: f'{x:.1f}')}% of the runs' CPU time "
            f"({slash(per_goal, lambda x: f'{x:.0f}')} ms a goal).")
    return head + "\n\n" + _gcsl_rounds_table(root, [HAND43_GCSL_CONTROL, HAND43_GCSL_PROPOSE])


def _gcsl_arm_against_control(root: Path, arm: HandArm, what: str, cost: bool = False) -> str:
    """A later proposer arm, fixed before it ran, against the same control (and the first arm, rate 0.5);
    ``cost``: with the proposer's time a proposed goal (each seed's last round)."""
    control, other = HAND43_GCSL_CONTROL.read(root), arm.read(root)
    c = compare(other, control)
    half = HAND43_GCSL_PROPOSE.read(root)
    head = (f"**At {_frames_of(other)} frames in all: {slash(other.values)} {what}, {slash(control.values)} "
            f"without** (and {slash(half.values)} with the first arm, half of the episodes among every stored "
            f"goal, above). Run-level: {run_level(c)}. Episode-level: {episode_level(c)}.")
    if cost:
        lasts = [arm.rounds(root, seed)[-1] for seed in arm.seeds]
        per_goal = [1000 * last["propose_s"] / last["proposed"] for last in lasts]
        head += f" {slash(per_goal, lambda x: f'{x:.0f}')} ms a proposed goal."
    return head + "\n\n" + _gcsl_rounds_table(root, [arm])


def hand_gcsl_proposer_quarter(root: Path) -> str:
    """Issue 43 on HandReach: the second proposer arm, fixed before it ran (a quarter of the collection episodes),
    against the same control."""
    return _gcsl_arm_against_control(root, HAND43_GCSL_QUARTER, "with the proposer in a quarter of the collection "
                                                                "episodes")


def hand_gcsl_proposer_near(root: Path) -> str:
    """Issue 43 on HandReach: the third proposer arm, fixed before it ran (half of the collection episodes, the
    candidates the stored goals nearest the env's goal), against the same control."""
    return _gcsl_arm_against_control(root, HAND43_GCSL_NEAR, "with the proposer's candidates near the env's goal",
                                     cost=True)


def hand_gcsl_proposer_reached(root: Path) -> str:
    """Issue 43 on HandReach: the fourth proposer arm, fixed before it ran (half of the collection episodes, only
    candidates the memory reached within the success distance in at least 2 episodes: MEGA's filter counted in
    the memory), against the same control."""
    return _gcsl_arm_against_control(root, HAND43_GCSL_REACHED, "with the proposer's candidates limited to goals reached in "
                                     "at least 2 stored episodes", cost=True)


#: the GCSL arms of issue 43 on HandReach, by the name their memories carry (bench_results/i43/gcsl/NAME-sS.zarr)
HAND43_GCSL_ARMS = {"control": HAND43_GCSL_CONTROL, "propose": HAND43_GCSL_PROPOSE, "propose25": HAND43_GCSL_QUARTER,
                    "near": HAND43_GCSL_NEAR, "reached2": HAND43_GCSL_REACHED}


def hand_gcsl_fit_cover(root: Path) -> str:
    """Issue 43, goal 4 on HandReach: is GCSL's plateau the fit or the data? Fresh clones of the control's seed-0
    memory with more Adam steps (held-out and evaluation goals), and each run's memory's cover of the evaluation's
    pinch goals against the success the run reached (archives ``hand43-gcsl-fit-s0.jsonl``, ``hand43-gcsl-cover.jsonl``)."""
    with open(root / RUNS / "hand43-gcsl-fit-s0.jsonl") as f:
        clones = [json.loads(line) for line in f if line.strip()]
    rows = []
    for steps in sorted({d["steps"] for d in clones}):
        at = {d.get("eval_seed", "eval"): d for d in clones if d["steps"] == steps}
        held, ev = at[min(k for k in at if k != "eval")], at["eval"]
        rows.append([f"{steps:,}", f2(held["success"]), f2(ev["success"]), f"{ev['loss']:.4f}", cpu(ev["cpu_s"])])
    fit = table(["Adam steps (one fresh clone of the 150k rows)", "success, 100 held-out goals",
                 "success, the 100 evaluation goals", "last batch's loss", "CPU-s"], rows)
    with open(root / RUNS / "hand43-gcsl-cover.jsonl") as f:
        cover = [json.loads(line) for line in f if line.strip()]
    rows, xs, ys = [], [], []
    for name, arm in HAND43_GCSL_ARMS.items():
        final = dict(zip(arm.seeds, arm.read(root).values))
        for seed in arm.seeds:
            c = next(d for d in cover if d["memories"][0].endswith(f"/{name}-s{seed}.zarr"))
            xs.append(c["within_0.01"])
            ys.append(final[seed])
            rows.append([f"{arm.label}, seed {seed}", pct(c["within_0.01"]), pct(c["within_0.02"]),
                         f"{c['nearest_median']:.4f}", f2(final[seed])])
    r = statistics.correlation(xs, ys)
    head = (f"**More fitting stops paying at about 20k Adam steps; the runs' success goes with what their memories "
            f"cover.** Across the {len(xs)} runs, the share of the evaluation's pinch goals with a stored achieved "
            f"goal within the success distance (0.01) and the run's success at 150k frames correlate at r = {r:.2f}.")
    return (head + "\n\n" + fit + "\n\n" +
            table(["memory after 150k frames (run, seed)", "pinch goals within 0.01", "within 0.02",
                   "median distance to the nearest", "the run's success at 150k"], rows))


HAND43_GCSL_LONG = HandArm("GCSL, seed 0, to 400k frames", "hand43-gcsl-long-control-s0.jsonl", "gcsl")
#: the frames in all at which the long run's table shows the evaluated success
GCSL_LONG_FRAMES = [10000, 50000, 100000, 150000, 200000, 250000, 300000, 350000, 400000]


def hand_gcsl_long(root: Path) -> str:
    """Issue 43, goal 4 on HandReach: the control's GCSL (seed 0) carried past 150k frames (archive
    ``hand43-gcsl-long-control-s0.jsonl``; its first 28 rounds repeat the control run of the table above)."""
    rounds = {d["memory_rows"]: d for d in HAND43_GCSL_LONG.rounds(root, 0)}
    last = rounds[max(rounds)]
    best = max(rounds.values(), key=lambda d: (d["success"], -d["memory_rows"]))
    shown = [f for f in GCSL_LONG_FRAMES if f in rounds]
    t = table(["frames in all (10k random first)", *[kf(f) for f in shown], "best", "CPU-s of the rounds"],
              [[HAND43_GCSL_LONG.label, *[f2(rounds[f]["success"]) for f in shown], f2(best["success"]),
                cpu(last["cpu_s"])]])
    tail = [d["success"] for f, d in sorted(rounds.items()) if f > max(rounds) - 50000]  # the last 10 rounds
    head = (f"**At {kf(max(rounds))} frames in all: {f2(last['success'])}; the best evaluation {f2(best['success'])}, "
            f"at {kf(best['memory_rows'])}; the last 10 rounds {f2(min(tail))}-{f2(max(tail))}** (one seed, the "
            f"control's settings; the first 28 rounds repeat the control's seed 0 exactly).")
    return f"{head}\n\n{t}"


def hand_gcsl_second(root: Path) -> str:
    """Issue 43 goal 3 on HandReach: a second run (fresh networks) on each first run's memory: the new frames it
    needed to reach the first run's final success (the first run: 150k frames in all)."""
    rows = []
    for name, first_arm in (("control", HAND43_GCSL_CONTROL), ("propose", HAND43_GCSL_PROPOSE)):
        second = HAND43_SECOND[name]
        for seed in second.seeds:
            target = first_arm.rounds(root, seed)[-1]
            rounds = second.rounds(root, seed)
            hit = next((d for d in rounds if d["success"] >= target["success"]), None)
            first_frames = target["memory_rows"]
            rows.append([f"{first_arm.label}, seed {seed}", f2(target["success"]), kf(first_frames),
                         f2(rounds[0]["success"]),
                         (f"{kf(hit['new_frames'])} ({100 * hit['new_frames'] / first_frames:.0f}%)" if hit else
                          f"not within {kf(rounds[-1]['new_frames'])} (best {f2(max(d['success'] for d in rounds))})"),
                         cpu(rounds[-1]["cpu_s"])])
    return table(["first run", "its final success", "its frames", "second run at 0 new frames",
                  "new frames to reach it (share of the first's)", "second run's CPU-s"], rows)


BLOCKS: dict[str, Callable[[Path], str]] = {
    "summary": summary,
    "hand_gcsl_proposer": hand_gcsl_proposer,
    "hand_gcsl_proposer_quarter": hand_gcsl_proposer_quarter,
    "hand_gcsl_proposer_near": hand_gcsl_proposer_near,
    "hand_gcsl_proposer_reached": hand_gcsl_proposer_reached,
    "hand_gcsl_second": hand_gcsl_second,
    "pnp_proposer_pilot": pnp_proposer_pilot,
    "pnp_proposer_60k": pnp_proposer_60k,
    "pnp_proposer_150k": pnp_proposer_150k,
    "hand_gcsl_long": hand_gcsl_long,
    "hand_gcsl_fit_cover": hand_gcsl_fit_cover,
    "hand_proposer_pilot": hand_proposer_pilot,
    "reach_second": reach_second,
    "push_clone": push_clone,
    "push_replay": push_replay,
    "push_goal2": push_goal2,
    "push_goal4": push_goal4,
    "slide_goal4": slide_goal4,
    "pnp": pnp,
    "slide_scripted": slide_scripted,
    "slide_learned": slide_learned,
    "slide_100k": slide_100k,
    "hand": hand,
    "history_push_variants": history_push_variants,
    "history_clone_variants": history_clone_variants,
    "history_slide_100k": history_slide_100k,
    "history_hand": history_hand,
    "history_hand_clone": history_hand_clone,
}


# -- the pages --------------------------------------------------------------------------------------------------


def render(root: Path = ROOT) -> dict[str, str]:
    """``{name: markdown}`` of every block, read from the archives under ``root``."""
    return {name: fn(root).rstrip("\n") for name, fn in BLOCKS.items()}


def fill(text: str, blocks: dict[str, str], page: str = "page") -> tuple[str, list[str]]:
    """``text`` with every generated block replaced by ``blocks``; the names it holds."""
    names: list[str] = []

    def sub(m: re.Match) -> str:
        name, end = m.group(1), m.group(3)
        if name != end:
            raise ValueError(f"{page}: block {name!r} closed by {end!r}")
        if name not in blocks:
            raise ValueError(f"{page}: no block {name!r} is declared in tools/results_page.py")
        names.append(name)
        return f"<!-- generated: {name} -->\n{blocks[name]}\n<!-- end generated: {name} -->\n"

    out = _BLOCK.sub(sub, text)
    opened = len(_OPEN.findall(text))
    if opened != len(names):
        raise ValueError(f"{page}: {opened} blocks opened, {len(names)} closed")
    return out, names


def pages(root: Path = ROOT) -> dict[str, tuple[str, str]]:
    """``{page: (text now, text generated)}``; every declared block must appear exactly once over the pages."""
    blocks = render(root)
    out, seen = {}, []
    for page in PAGES:
        path = root / page
        text = path.read_text()
        new, names = fill(text, blocks, page)
        seen += names
        out[page] = (text, new)
    missing = sorted(set(blocks) - set(seen))
    twice = sorted({n for n in seen if seen.count(n) > 1})
    if missing or twice:
        raise ValueError(f"blocks on no page: {missing}; blocks on a page twice: {twice}")
    return out


def check(root: Path = ROOT) -> str:
    """The diff between the pages and what they should hold ('' when they match)."""
    diff = []
    for page, (text, new) in pages(root).items():
        diff += difflib.unified_diff(text.splitlines(keepends=True), new.splitlines(keepends=True),
                                     f"{page} (now)", f"{page} (from {RUNS})")
    return "".join(diff)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m tools.results_page", description=__doc__.split("\n")[0])
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--check", action="store_true", help="exit 1 with a diff if a page differs from the archives")
    mode.add_argument("--write", action="store_true", help="rewrite the generated blocks of the pages in place")
    p.add_argument("--root", default=str(ROOT), help="the repository root to read docs/ from (default: this one)")
    args = p.parse_args(argv)
    root = Path(args.root)
    if args.check:
        diff = check(root)
        if diff:
            sys.stdout.write(diff)
            print(f"\n{', '.join(PAGES)}: differ from {RUNS}; `python -m tools.results_page --write` rewrites them.")
            return 1
        print(f"{', '.join(PAGES)}: every generated block matches {RUNS}.")
        return 0
    if args.write:
        for page, (text, new) in pages(root).items():
            if new != text:
                (root / page).write_text(new)
                print(f"rewrote {page}")
        return 0
    for name, md in render(root).items():
        print(f"<!-- generated: {name} -->\n{md}\n<!-- end generated: {name} -->\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
