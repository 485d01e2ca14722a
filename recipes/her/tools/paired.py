"""Goal-by-goal comparison of two arms of ``recipes/her/train.py`` runs at one frame count.

Runs with the same ``seed`` are evaluated on the same fixed goals, and each run
records every evaluation's per-episode successes in its hydra directory
(``eval_episodes.jsonl``, :func:`recipes.her.run_record.record_episodes`). This
tool pairs the two arms' runs by seed, pairs their episodes by goal, and runs
an exact McNemar test on all the pairs (:func:`recipes.her.tools.stats.mcnemar`):
the test of issue 27's recall ablations (``memory.recall.enabled``,
``replay_buffer.sampler.enabled``) against the same runs without them::

    python -m recipes.her.tools.paired --frames 30000 --out docs/runs/recall-slide.json \\
        "recall=runs/recall-s0,runs/recall-s1,runs/recall-s2" \\
        "control=runs/prior-s0,runs/prior-s1,runs/prior-s2"

An arm's label may end in ``@FRAMES`` to read that arm at another evaluation,
e.g. a run against its own first evaluation (``experiments/residual``: the learned
residual at 30k frames against the controller it started from)::

    python -m recipes.her.tools.paired --frames 30000 "residual=A-s0,A-s1" "controller@0=A-s0,A-s1"

A run is its hydra directory or its archive (``recipes.her.tools.compare
--archive``, which keeps the per-episode outcomes). It prints one markdown table
(each arm's success per seed and pooled, the discordant pairs and the p-value)
and, with ``--out``, writes the same with the outcomes themselves to a JSON file.
"""
from __future__ import annotations

import argparse
import json

from recipes.her.run_record import read_episodes
from recipes.her.tools.stats import mcnemar, wilson

__all__ = ["arm_outcomes", "compare_arms", "main", "parse_arm"]


def arm_outcomes(run_dirs: list[str], frames: int) -> dict[int, list[int]]:
    """``{seed: per-episode successes at frames}`` of an arm's runs (a seed twice in one arm is refused)."""
    out: dict[int, list[int]] = {}
    for run_dir in run_dirs:
        records = read_episodes(run_dir)
        if frames not in records:
            raise KeyError(f"{run_dir} has no evaluation at {frames} frames (it has {sorted(records)}).")
        rec = records[frames]
        if rec["seed"] in out:
            raise ValueError(f"two runs of seed {rec['seed']} in one arm ({run_dir}): pair one run a seed.")
        out[int(rec["seed"])] = [int(x) for x in rec["success"]]
    return out


def compare_arms(a: dict[int, list[int]], b: dict[int, list[int]]) -> dict:
    """Per-seed success of both arms and one McNemar test over every goal of every shared seed.

    Example:
        >>> r = compare_arms({0: [1, 1, 0, 1]}, {0: [0, 1, 0, 0]})
        >>> r["pooled"]["a"], r["pooled"]["b"], r["test"]["a_only"], r["test"]["b_only"]
        (0.75, 0.25, 2, 0)
    """
    seeds = sorted(set(a) & set(b))
    if not seeds:
        raise ValueError(f"no seed in both arms (a: {sorted(a)}, b: {sorted(b)}): pair runs of the same seeds.")
    for s in seeds:
        if len(a[s]) != len(b[s]):
            raise ValueError(f"seed {s}: {len(a[s])} episodes against {len(b[s])}; use the same logger.eval_episodes.")
    flat_a = [x for s in seeds for x in a[s]]
    flat_b = [x for s in seeds for x in b[s]]
    n = len(flat_a)
    return {
        "seeds": seeds,
        "per_seed": {s: {"a": sum(a[s]) / len(a[s]), "b": sum(b[s]) / len(b[s])} for s in seeds},
        "pooled": {"a": sum(flat_a) / n, "b": sum(flat_b) / n, "n": n,
                   "a_ci95": list(wilson(sum(flat_a), n)), "b_ci95": list(wilson(sum(flat_b), n))},
        "test": mcnemar(flat_a, flat_b),
    }


def parse_arm(spec: str, frames: int) -> tuple[str, list[str], int]:
    """``label[@FRAMES]=run,run,...`` -> (label, runs, frames of the evaluation to read).

    Example:
        >>> parse_arm("controller@0=runs/a,runs/b", 30000)
        ('controller@0', ['runs/a', 'runs/b'], 0)
    """
    if "=" not in spec:
        raise ValueError(f"an arm is label[@FRAMES]=run_dir,run_dir,...; got {spec!r}")
    name, dirs = spec.split("=", 1)
    at = frames
    if "@" in name:
        try:
            at = int(name.rsplit("@", 1)[1])
        except ValueError:
            raise ValueError(f"{name!r}: what follows @ must be a frame count, e.g. controller@0") from None
    return name, [d for d in dirs.split(",") if d], at


def table(names: tuple[str, str], frames: int, result: dict) -> str:
    a, b = names
    lines = [f"| at {frames} frames | " + " | ".join(f"seed {s}" for s in result["seeds"]) + " | pooled | p (McNemar) |",
             "|---|" + "---|" * (len(result["seeds"]) + 2)]
    t = result["test"]
    for key, name in (("a", a), ("b", b)):
        cells = [f"{result['per_seed'][s][key]:.2f}" for s in result["seeds"]]
        p = f"{t['p']:.3g} ({t['a_only']} vs {t['b_only']} discordant)" if key == "a" else ""
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {result['pooled'][key]:.3f} | {p} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m recipes.her.tools.paired", description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, required=True, help="the evaluation to compare (frames collected)")
    parser.add_argument("--out", default=None, help="write the result, with the outcomes, to this JSON file")
    parser.add_argument("arms", nargs=2, help="label[@FRAMES]=run,run,... (each run's hydra.run.dir or its archived "
                                              ".json; @FRAMES reads that arm at another evaluation)")
    args = parser.parse_args(argv)
    names, outcomes = [], []
    for spec in args.arms:
        try:
            name, dirs, at = parse_arm(spec, args.frames)
        except ValueError as err:
            parser.error(str(err))
        names.append(name)
        outcomes.append(arm_outcomes(dirs, at))
    result = compare_arms(*outcomes)
    print(table(tuple(names), args.frames, result))
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"arms": names, "frames": args.frames, **result,
                       "outcomes": {n: {str(s): o[s] for s in result["seeds"]} for n, o in zip(names, outcomes)}},
                      f, indent=1)
    return result


if __name__ == "__main__":
    main()
