"""Every ``recipes/her`` command in the docs composes the run it composed before the recipe's redesign (issue 24).

The redesign renamed the prior-memory options (``memory.prior*``, ``memory.clone_anchor*``,
``memory.freeze_normalizer``, ``memory.actor_freeze_frames``, ``optim.actor_update``,
``optim.actor_lr``: now the ``prior`` config group) and moved the tools to
``python -m recipes.her.tools.*`` (issue 42 moved those that reproduce past results
to ``python -m experiments.her.*``). This check pairs each command of a doc before the
change (``--docs-base``, a git revision) with the same command after it (the working
tree), in the order they appear, and proves they are the same run:

* ``recipes/her/train.py`` commands: the old overrides are composed with the recipe's
  config at ``--recipe-base`` (read from git, nothing checked out), the new ones with
  ``recipes/her/config.yaml`` and the variants' keys (``experiments/prior_variants/variants.yaml``;
  ``python -m experiments.prior_variants.train`` commands count as ``train.py`` ones); old keys are mapped to their new names (:data:`RENAMED`)
  and every value the training loop reads is compared; the new config must also pass
  ``experiments.prior_variants.check_prior_config`` (the run would start);
* ``prior_runs`` commands: every run they launch, old ``RUNS`` against new, the same way;
* ``failures``: its trailing overrides, the same way; ``compare`` / ``clone_sensitivity``:
  the same arguments, and the new module exists.

Run it from the repository root::

    python -m experiments.her.check_commands                # every doc, prints one line a command
    python -m experiments.her.check_commands --docs-base 59b9ae5 README.md recipes/README.md

Commands are paired in order, each old one with the next new one of the same tool; a
new command with no old one is only checked to be valid. It exits non-zero if a pair
differs, an old command has no new one, or a new one is refused.
"""
from __future__ import annotations

import argparse
import glob
import importlib.util
import io
import os
import re
import shlex
import subprocess
import sys
import tarfile
import tempfile

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from experiments.prior_variants import check_prior_config

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
# the recipe's config now, with the prior-memory variants' keys (issue 42 moved them to experiments/prior_variants,
# whose variants.yaml composes recipes/her/config.yaml): every run a doc names composes there
NEW_DIR = os.path.join(ROOT, "experiments", "prior_variants")
RECIPE_BASE = "59b9ae5"  # the recipe before the redesign
DOCS_BASE = "c658576"    # the docs before their commands were renamed (docs/results.md already split by issue 24)
BASE_OF = {"recipes/README.md": RECIPE_BASE}  # renamed together with the recipe
DOCS = ["README.md", "Makefile", "recipes/README.md", "docs/*.md", "docs/notes/*.md"]

#: old config key -> new config key (keys not listed kept their name)
RENAMED = {
    "memory.prior": "prior.paths",
    "memory.prior_ratio": "prior.ratio",
    "memory.prior_ratio_final": "prior.ratio_final",
    "memory.prior_anneal_frames": "prior.anneal_frames",
    "memory.prior_bc": "prior.bc",
    "memory.prior_bc_q_filter": "prior.bc_q_filter",
    "memory.prior_bc_original_goals": "prior.bc_original_goals",
    "memory.prior_pretrain_bc": "prior.clone_steps",
    "memory.freeze_normalizer": "prior.freeze_normalizer",
    "memory.actor_freeze_frames": "prior.actor_freeze_frames",
    "memory.clone_anchor": "prior.clone_anchor",
    "memory.clone_anchor_final": "prior.clone_anchor_final",
    "memory.clone_anchor_anneal_frames": "prior.clone_anchor_anneal_frames",
    "optim.actor_update": "prior.actor_update",
    "optim.actor_lr": "prior.actor_lr",
}
#: new keys with no old key: the value the old recipe used (a hard-coded line), or None: not read by the loop
# None: not compared. The pretraining checks of issue 25 decide when pretraining stops, not what it
# trains; memory.pretrain_eval_every=0 (prior_runs) does every update, as the old recipe did
NEW_ONLY = {"num_threads": 1, "prior.name": None, "memory.pretrain_eval_every": None,
            "memory.pretrain_eval_episodes": None, "memory.pretrain_target": None, "memory.pretrain_patience": None}
OLD_TOOLS = {"train.py", "prior_runs.py", "compare.py", "failures.py", "clone_sensitivity.py"}
COMMAND = re.compile(r"(?:python3?|\$\(PY\)|\.venv/bin/python)\s+"
                     r"(?:-m\s+(?:recipes\.her\.(?:tools\.)?|experiments\.her\.|experiments\.prior_variants\.)(\w+)|(?:recipes/her/(?:tools/)?|experiments/her/)(\w+)\.py)")
#: where a tool's module lives now: the recipe's own tools, or the experiments' (issue 42; the recipe with the
#: prior-memory variants is ``python -m experiments.prior_variants.train``, tool ``train`` as the recipe's)
TOOL_PACKAGES = ("recipes.her.tools", "experiments.her", "experiments.prior_variants")


# -- commands in a doc ---------------------------------------------------------


def commands(text: str, variables: dict[str, str] | None = None) -> list[tuple[str, list[str]]]:
    """``(tool, arguments)`` of every recipes/her command in ``text``: code lines, ``# = ...`` lines, inline code."""
    lines = text.splitlines()
    found = []
    i = 0
    while i < len(lines):
        line = _uncomment(lines[i])
        match = COMMAND.search(line)
        if match is None:
            i += 1
            continue
        command = line[match.start():]
        while command.rstrip().endswith("\\") and i + 1 < len(lines):  # continued on the next line
            i += 1
            command = command.rstrip()[:-1] + " " + _uncomment(lines[i])
        found += [_parse(c, variables or {}) for c in _split_inline(command)]
        i += 1
    return found


def _uncomment(line: str) -> str:
    """A shell comment's text (``# = python ...``, ``#   memory.prior=...``), else the line."""
    stripped = line.strip()
    return re.sub(r"^#\s*=?\s*", "", stripped) if stripped.startswith("#") else stripped


def _split_inline(command: str) -> list[str]:
    """One command, cut at a closing backtick (inline code in prose), a shell comment or ``&&``."""
    pieces = []
    for part in re.split(r"\s&&\s", command):
        if COMMAND.search(part):
            pieces.append(part.split("`")[0].split(" # ")[0].split("  #")[0])
    return pieces


def _parse(command: str, variables: dict[str, str]) -> tuple[str, list[str]]:
    match = COMMAND.match(command)
    tool = match.group(1) or match.group(2)
    rest = command[match.end():]
    for name, value in variables.items():  # Makefile variables
        rest = rest.replace(f"$({name})", value)
    try:
        args = shlex.split(rest)
    except ValueError:  # an unbalanced quote in prose
        args = rest.split()
    return tool, args


def makefile_variables(text: str) -> dict[str, str]:
    """``NAME ?= value`` / ``NAME = value`` assignments, continuation lines joined."""
    joined = re.sub(r"\\\n\s*", " ", text)
    return {m.group(1): m.group(2).strip() for m in re.finditer(r"^(\w+)\s*\??=\s*(.*)$", joined, re.M)}


# -- configs ---------------------------------------------------------------------


def compose_config(config_dir: str, overrides: list[str]):
    """The composed config of ``overrides`` (``hydra.*`` left out: where a run writes, not what it does).

    ``config_dir``: an old recipe's directory (its ``config.yaml``), or :data:`NEW_DIR` (``variants.yaml``).
    """
    overrides = [o for o in overrides if not o.startswith("hydra.")]
    with initialize_config_dir(config_dir=config_dir, version_base="1.3"):
        return compose("variants" if config_dir == NEW_DIR else "config", overrides=overrides)


def flat(cfg) -> dict:
    """Every leaf of a config as ``{"a.b": value}``, interpolations resolved, ``hydra`` left out."""
    def walk(node: dict, prefix: str) -> dict:
        out = {}
        for key, value in node.items():
            if isinstance(value, dict):
                out.update(walk(value, f"{prefix}{key}."))
            else:
                out[f"{prefix}{key}"] = value
        return out

    container = OmegaConf.to_container(cfg, resolve=True)
    container.pop("hydra", None)
    return walk(container, "")


def effective_old(cfg) -> dict:
    """An old config's values under their new names, with the values the old recipe hard-coded."""
    values = {RENAMED.get(k, k): v for k, v in flat(cfg).items()}
    values.update({k: v for k, v in NEW_ONLY.items() if v is not None})
    return values


def effective_new(cfg) -> dict:
    return {k: v for k, v in flat(cfg).items() if NEW_ONLY.get(k, 0) is not None}


def differences(old: dict, new: dict) -> list[str]:
    return [f"{k}: {old.get(k, '<absent>')!r} -> {new.get(k, '<absent>')!r}"
            for k in sorted(set(old) | set(new)) if old.get(k, "<absent>") != new.get(k, "<absent>")]


# -- the old recipe, read from git -------------------------------------------------


def extract(rev: str, path: str, into: str) -> str:
    """``path`` of the repository at ``rev``, unpacked under ``into`` (``git archive``; nothing checked out)."""
    blob = subprocess.run(["git", "-C", ROOT, "archive", rev, path], check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(blob)) as tar:
        tar.extractall(into, filter="data")
    return os.path.join(into, path)


def git_text(rev: str, path: str) -> str | None:
    proc = subprocess.run(["git", "-C", ROOT, "show", f"{rev}:{path}"], capture_output=True, text=True)
    return proc.stdout if proc.returncode == 0 else None


def tool_exists(tool: str) -> bool:
    """Whether ``python -m`` finds ``tool`` in one of :data:`TOOL_PACKAGES`."""
    return any(importlib.util.find_spec(f"{package}.{tool}") is not None for package in TOOL_PACKAGES)


def load_module(path: str, name: str):
    """A module from a file (the old ``prior_runs.py``), without touching ``sys.path``."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# -- one pair ------------------------------------------------------------------------


class Checker:
    """Compares old and new commands; ``old_dir`` holds the recipe at ``RECIPE_BASE``."""

    def __init__(self, old_dir: str) -> None:
        from experiments.her import prior_runs

        self.old_dir = old_dir
        self._seen: dict[tuple, list[str]] = {}  # (old, new) -> differences: docs repeat the same runs
        self.placeholders = 0  # commands with a placeholder that neither recipe composes
        self.old_runs = load_module(os.path.join(old_dir, "prior_runs.py"), "old_prior_runs")
        self.new_runs = prior_runs

    def same_run(self, old: list[str], new: list[str]) -> list[str]:
        """Differences between the runs ``train.py OLD`` and ``train.py NEW`` compose (empty: the same run)."""
        key = (tuple(old), tuple(new))
        if key not in self._seen:
            self._seen[key] = self._compare(old, new)
        return self._seen[key]

    def _compare(self, old: list[str], new: list[str]) -> list[str]:
        try:
            old_cfg = compose_config(self.old_dir, old)
        except Exception as err:  # a placeholder (``...``, ``NAME``): it never composed a run
            self.placeholders += 1
            try:
                compose_config(NEW_DIR, new)
            except Exception:
                return []  # neither composes: a sketch in prose, not a command
            return [f"the old command did not compose ({type(err).__name__}) but the new one does"]
        try:
            new_cfg = compose_config(NEW_DIR, new)
            check_prior_config(new_cfg)
        except Exception as err:
            return [f"the new command is refused: {err}"]
        return differences(effective_old(old_cfg), effective_new(new_cfg))

    def runs_of(self, module, args: list[str]) -> list[str]:
        """The runs a ``prior_runs`` command launches (``--only a,b``; all of them without it)."""
        only = next((a.split("=", 1)[1] for a in args if a.startswith("--only=")), None)
        if only is None and "--only" in args[:-1]:
            only = args[args.index("--only") + 1]
        return [n for n in (only or "").split(",") if n] or list(module.RUNS)

    def check(self, new: tuple[str, list[str]]) -> list[str]:
        """A command with no old counterpart: it composes a run the recipe accepts, or its module exists."""
        tool, args = new
        if tool == "train":
            try:
                check_prior_config(compose_config(NEW_DIR, args))
            except Exception as err:  # any refusal (a bad key, prior.* that do not go together) is the finding
                return [f"refused: {err}"]
            return []
        return [] if tool_exists(tool) else [f"no module {tool} in {' or '.join(TOOL_PACKAGES)}"]

    def pair(self, old: tuple[str, list[str]], new: tuple[str, list[str]] | None) -> list[str]:
        if new is None:
            return ["no longer in the doc"]
        (old_tool, old_args), (new_tool, new_args) = old, new
        if old_tool != new_tool:
            return [f"different tools: {old_tool} vs {new_tool}"]
        if old_tool == "train":
            return self.same_run(old_args, new_args)
        if old_tool == "prior_runs":
            names = self.runs_of(self.old_runs, old_args)
            if names != self.runs_of(self.new_runs, new_args):
                return ["prior_runs: other runs"]
            problems = []
            for name in names:
                if name not in self.new_runs.RUNS:
                    problems.append(f"{name}: no such run any more")
                    continue
                diff = self.same_run(self.old_runs.command(name, "ROOT")[2:], self.new_runs.command(name, "ROOT")[2:])
                problems += [f"{name}: {d}" for d in diff]
            return problems
        if old_tool == "failures" and old_args[1:]:
            return (["failures: other agent"] if old_args[:1] != new_args[:1] else []) + self.same_run(
                ["logger.eval_episodes=100", *old_args[1:]], ["logger.eval_episodes=100", *new_args[1:]])
        if not tool_exists(new_tool):
            return [f"no module {new_tool} in {' or '.join(TOOL_PACKAGES)}"]
        return [] if old_args == new_args else [f"other arguments: {old_args} vs {new_args}"]


def align(old: list, new: list) -> list[tuple]:
    """Old and new commands paired in order, each old one with the next new one of the same tool.

    A new command with no old one is paired with ``None`` (only checked to be valid); an
    old one with no new one with ``None`` as the new (a command the docs lost).
    """
    pairs, j = [], 0
    for cmd in old:
        k = next((k for k in range(j, len(new)) if new[k][0] == cmd[0]), None)
        if k is None:
            pairs.append((cmd, None))
            continue
        pairs += [(None, n) for n in new[j:k]] + [(cmd, new[k])]
        j = k + 1
    return pairs + [(None, n) for n in new[j:]]


def doc_files(patterns: list[str]) -> list[str]:
    files = []
    for pattern in patterns:
        files += sorted(os.path.relpath(p, ROOT) for p in glob.glob(os.path.join(ROOT, pattern)))
    return files


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("files", nargs="*", help=f"docs to check (default: {' '.join(DOCS)})")
    p.add_argument("--docs-base", default=DOCS_BASE, help="git revision of the docs before the rename")
    p.add_argument("--recipe-base", default=RECIPE_BASE, help="git revision of the recipe before the redesign")
    p.add_argument("--base-of", action="append", default=[], metavar="FILE=REV",
                   help="another docs base for one file (e.g. a file created after --docs-base)")
    args = p.parse_args(argv)
    bases = {**BASE_OF, **dict(b.split("=", 1) for b in args.base_of)}
    failed = checked = 0
    with tempfile.TemporaryDirectory() as tmp:
        checker = Checker(extract(args.recipe_base, "recipes/her", tmp))
        for path in doc_files(args.files or DOCS):
            new_text = open(os.path.join(ROOT, path)).read()
            old_text = git_text(bases.get(path, args.docs_base), path)
            if old_text is None:
                print(f"{path}: not in {bases.get(path, args.docs_base)}: give its base with --base-of {path}=REV")
                failed += bool(commands(new_text))
                continue
            variables = makefile_variables(new_text) if path.endswith("Makefile") else {}
            old_cmds = [c for c in commands(old_text, variables) if f"{c[0]}.py" in OLD_TOOLS or c[0] == "train"]
            for old, new in align(old_cmds, commands(new_text, variables)):
                checked += 1
                problems = checker.check(new) if old is None else checker.pair(old, new)
                failed += bool(problems)
                verdict = ("valid (new)" if old is None else "same run") if not problems else "DIFFERENT: " + "; ".join(problems)
                shown = new if new is not None else old
                print(f"{path}: {shown[0]} {' '.join(shown[1])[:150]}\n    {verdict}")
    print(f"{checked} commands checked, {failed} failed ({checker.placeholders} with placeholders that never composed)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
