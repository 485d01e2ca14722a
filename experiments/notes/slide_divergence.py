"""The critic loss and actor Q of the three FetchSlide prior runs without target clipping (docs/results.md).

    python -m experiments.notes.slide_divergence bench_results/i27/links/slide100k-prior-s{0,1,2}   # from the runs
    python -m experiments.notes.slide_divergence                                                   # from the archive

Reads each run's ``train/loss_qvalue.csv`` and ``train/loss_actor.csv`` (every CSV its resumes logged), keeps a
point every 1000 frames in ``docs/runs/slide100k-prior-losses.json``, and draws ``docs/img/slide_divergence.png``.
"""
import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", ".."))
from recipes.her.tools.compare import logged_scalar  # noqa: E402

ARCHIVE = "docs/runs/slide100k-prior-losses.json"


def main(run_dirs: list[str]) -> None:
    if run_dirs:
        runs = {}
        for d in run_dirs:
            name = os.path.basename(d.rstrip("/"))
            runs[name] = {}
            for key in ("loss_qvalue", "loss_actor"):
                pts = logged_scalar(d, "train", key)
                runs[name][key] = [[f, pts[f]] for f in sorted(pts) if f % 1000 == 0]
        with open(ARCHIVE, "w") as f:
            json.dump(runs, f)
    with open(ARCHIVE) as f:
        runs = json.load(f)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for name, curves in runs.items():
        for ax, key in zip(axes, ("loss_qvalue", "loss_actor")):
            xs, ys = zip(*curves[key])
            ax.plot([x / 1000 for x in xs], [-y if key == "loss_actor" else y for y in ys], label=name)
    axes[0].set(yscale="log", xlabel="new env frames (k)", ylabel="critic loss", title="critic loss")
    axes[1].set(yscale="symlog", xlabel="new env frames (k)", ylabel="-(actor loss) = Q - alpha log pi",
                title="actor's Q (rewards are -1 / 0: Q in [-50, 0])")
    axes[1].axhline(0, color="grey", lw=0.8, ls=":")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig("docs/img/slide_divergence.png", dpi=110)


if __name__ == "__main__":
    main(sys.argv[1:])
