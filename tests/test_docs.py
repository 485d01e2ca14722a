"""The README quick start, every ``python`` block of ``docs/*.md`` and every example run as written.

Docs blocks of one page run in order in one namespace (a page's later blocks
may use what its earlier ones built), in a temporary working directory so that
relative store paths land there. Examples run as subprocesses with short budgets.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOC_PAGES = sorted(p for p in (ROOT / "docs").glob("*.md") if "```python" in p.read_text())
_BLOCK = re.compile(r"```python\n(.*?)```", re.S)


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


@pytest.mark.parametrize("page", DOC_PAGES, ids=lambda p: p.name)
def test_doc_page_snippets_run(page, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {"__name__": "__docs__"}
    for i, block in enumerate(_BLOCK.findall(page.read_text())):
        exec(compile(block, f"{page.name}[block {i}]", "exec"), namespace)
    for value in list(namespace.values()):  # release writers the page left open
        close = getattr(value, "close", None)
        if callable(close) and type(value).__module__.startswith("torchrl_robotmem"):
            close()


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
