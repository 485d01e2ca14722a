"""The README quick start, every ``python`` block of ``docs/*.md`` and every example run as written.

Every ``python`` (or ``py``) block of a docs page runs as pasted into a fresh script: in
a namespace of its own whose ``__name__`` is ``"__main__"``, in a fresh temporary working
directory (relative store paths land there). A block that builds on the one before it
says so on its first line, ``# continues the block above`` (optionally followed by what
it uses, e.g. ``# continues the block above (rb, storage)``): it then runs after that
block, in its namespace and directory; a chain of such blocks is one test, named after
its first block (``recall.md[0-8]``). :data:`KNOWN_FAILING` lists the chains known to
fail (strict xfails), :data:`FULL_TIER_CHAINS` the slow ones run by ``make test-full``.
Examples run as subprocesses with short budgets.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from torchrl.data import ReplayBuffer

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
_BLOCK = re.compile(r"```py(?:thon)?\n(.*?)```", re.S)  # ```py blocks run too: no Python block escapes the test
DOC_PAGES = sorted(p for p in (ROOT / "docs").glob("*.md") if _BLOCK.search(p.read_text()))


def test_readme_quick_start_runs(tmp_path, capsys):
    blocks = _BLOCK.findall(README.read_text())
    assert blocks, "the README lost its quick start"
    code = blocks[0].replace("memory/pickandplace.zarr", str(tmp_path / "m.zarr"))
    namespace: dict = {}
    exec(compile(code, str(README), "exec"), namespace)
    prior = namespace["prior"]
    assert prior.shape == (5,) and prior["mask"].all()
    assert len(namespace["rb"]) == 1000
    assert torch.all(prior["distance"][1:] >= prior["distance"][:-1])
    # what recall is for: five different past episodes (not five steps of one), each with its context
    assert prior["episode"].unique().numel() == 5, prior["episode"]
    assert prior["next", "achieved_goal"].unique(dim=0).shape[0] == 5
    assert {"action", ("next", "is_success"), "run", "env"} <= set(prior.keys(True, True))
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("episode")]
    assert len(lines) == 5 and len(set(lines)) == 5, lines


#: a block whose first line starts with this runs after the block above it, in its namespace
CONTINUES = "# continues the block above"

#: (page, index of a chain's first block) -> (why it fails today, the error it raises): a strict xfail on that
#: chain alone, for that error alone; the page's fix makes it pass, and the entry must go with it
KNOWN_FAILING = {
}


#: (page, index of a chain's first block) -> why it is in the full tier only (slow: worker processes, Ray)
FULL_TIER_CHAINS = {
    ("distributed.md", 0): "MultiSyncCollector workers; tests/test_distributed.py covers it in the default tier",
    ("distributed.md", 1): "a Ray actor; tests/test_distributed.py covers it in the default tier",
}


def _chains(page: Path) -> list[tuple[int, list[str]]]:
    """The page's ``python`` blocks as chains ``(first block's index, blocks)``: a block whose first line
    is :data:`CONTINUES` joins the chain of the block above it; any other block starts a chain."""
    chains: list[tuple[int, list[str]]] = []
    for i, block in enumerate(_BLOCK.findall(page.read_text())):
        if block.startswith(CONTINUES) and chains:
            chains[-1][1].append(block)
        else:
            chains.append((i, [block]))
    return chains


def _chain_params():
    for page in DOC_PAGES:
        for start, blocks in _chains(page):
            name = f"{page.name}[{start}]" if len(blocks) == 1 else f"{page.name}[{start}-{start + len(blocks) - 1}]"
            known = KNOWN_FAILING.get((page.name, start))
            marks = [pytest.mark.xfail(reason=known[0], raises=known[1], strict=True)] if known else []
            if (page.name, start) in FULL_TIER_CHAINS:
                marks.append(pytest.mark.full)
            yield pytest.param(page, start, blocks, id=name, marks=marks)


def _release(namespace: dict) -> None:
    """Closes the stores a chain left open (``ZarrStorage`` / ``RobotMemory`` objects, a buffer's storage)."""
    for value in list(namespace.values()):
        # types only: an env's attribute lookup may recurse once it is closed (a TransformedEnv over a SerialEnv)
        objects = [value, vars(value).get("_storage")] if issubclass(type(value), ReplayBuffer) else [value]
        for obj in objects:
            if type(obj).__module__.startswith("torchrl_robotmem") and callable(getattr(obj, "close", None)):
                try:
                    obj.close()
                except Exception:  # noqa: BLE001 - a block may have left it half-closed on purpose
                    pass


@pytest.mark.parametrize(("page", "start", "blocks"), list(_chain_params()))
def test_doc_page_snippets_run(page, start, blocks, tmp_path, monkeypatch):
    """Each chain of blocks runs in a fresh namespace and working directory, as a reader pasting it would."""
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__main__"}  # a script's: a block guarded for spawned workers runs
    try:
        for i, block in enumerate(blocks, start):
            exec(compile(block, f"{page.name}[block {i}]", "exec"), namespace)
    finally:
        _release(namespace)


def test_doc_blocks_continue_a_block():
    """A continuation marker has a block above it to continue, and every known failure names a chain."""
    firsts = [p.name for p in DOC_PAGES if _BLOCK.findall(p.read_text())[0].startswith(CONTINUES)]
    assert not firsts, f"the first python block of {firsts} continues nothing: give it its own imports"
    starts = {(p.name, start) for p in DOC_PAGES for start, _ in _chains(p)}
    stale = sorted((set(KNOWN_FAILING) | set(FULL_TIER_CHAINS)) - starts)
    assert not stale, f"KNOWN_FAILING / FULL_TIER_CHAINS name no chain's first block: {stale} (the page changed)"


# script -> arguments that keep it to a few seconds
EXAMPLES = {
    "grow_memory.py": ["--episodes", "2", "--path", "{tmp}/grow.zarr"],
    "quickstart.py": ["--steps", "150", "--path", "{tmp}/pp.zarr"],
    "recall_in_collector.py": ["--episodes", "4", "--path", "{tmp}/fp.zarr"],
    "shadow_hand.py": ["--episodes", "3", "--path", "{tmp}/hand.zarr"],
}


def test_every_example_is_exercised():
    scripts = {p.name for p in (ROOT / "examples").glob("*.py")}
    assert scripts == set(EXAMPLES), "add the new example to EXAMPLES"


# second runs of what the default tier covers elsewhere (the Shadow Hand env in test_recipes, a growing
# memory in test_recipes' resume test, the recall transform in collectors in test_transform): full tier
FULL_TIER_EXAMPLES = {"grow_memory.py", "recall_in_collector.py", "shadow_hand.py"}


@pytest.mark.parametrize("script", [pytest.param(s, marks=pytest.mark.full) if s in FULL_TIER_EXAMPLES else s
                                    for s in sorted(EXAMPLES)])
def test_example_runs(script, tmp_path):
    args = [a.replace("{tmp}", str(tmp_path)) for a in EXAMPLES[script]]
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    for attempt in range(2):  # the second run reopens the first run's memory
        out = subprocess.run([sys.executable, str(ROOT / "examples" / script), *args], cwd=tmp_path,
                             capture_output=True, text=True, timeout=300, env=env)
        assert out.returncode == 0, f"run {attempt}: {out.stderr[-3000:]}"
    assert "Traceback" not in out.stderr


# -- links between the repository's markdown files --------------------------------------------------------

_FENCE = re.compile(r"```.*?```", re.S)
_LINK = re.compile(r"\]\(([^)\s]+)\)|^\[[^\]]+\]:\s*(\S+)", re.M)
_HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.M)


def _anchors(page: Path) -> set[str]:
    """GitHub's heading anchors of ``page``: lower case, punctuation dropped, spaces to '-', repeats '-1', '-2'."""
    seen: dict[str, int] = {}
    out = set()
    for title in _HEADING.findall(_FENCE.sub("", page.read_text())):
        slug = re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def _markdown_files() -> list[Path]:
    tracked = subprocess.run(["git", "ls-files", "*.md"], cwd=ROOT, capture_output=True, text=True)
    if tracked.returncode == 0 and tracked.stdout.strip():
        return [ROOT / p for p in tracked.stdout.split()]
    return [p for p in ROOT.rglob("*.md") if not {".venv", "bench_results", "outputs"} & set(p.parts)]


def test_markdown_links_resolve():
    """Every relative link of a tracked .md file names a file that exists, and a heading that exists in it."""
    broken = []
    for page in _markdown_files():
        for match in _LINK.finditer(_FENCE.sub("", page.read_text())):
            target = match.group(1) or match.group(2)
            if target.startswith(("http://", "https://", "mailto:")):
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
                broken.append(f"{page.relative_to(ROOT)}: {target} (no heading with that anchor in {dest.name})")
    assert not broken, "broken links:\n" + "\n".join(broken)
