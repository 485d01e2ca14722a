"""docs/results.md (and docs/notes/results_history.md) say what the archives in docs/runs say.

``python -m tools.results_page --check`` regenerates every table between ``<!-- generated: NAME -->`` markers from
the archives and diffs it against the page; these tests run that check on the repository, and on a copy whose
archive was changed, to show that the check can fail.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tools import results_page

ROOT = Path(__file__).resolve().parents[1]


def _copy_docs(tmp_path: Path) -> Path:
    """The pages and the archives they are generated from, under ``tmp_path`` (a repository root)."""
    for page in results_page.PAGES:
        (tmp_path / page).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / page, tmp_path / page)
    shutil.copytree(ROOT / results_page.RUNS, tmp_path / results_page.RUNS)
    (tmp_path / results_page.CROSS_ENV).parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(ROOT / results_page.CROSS_ENV, tmp_path / results_page.CROSS_ENV)
    return tmp_path


def test_results_page_matches_the_archives():
    diff = results_page.check(ROOT)
    assert not diff, ("docs/results.md or docs/notes/results_history.md differ from docs/runs; "
                      "run `python -m tools.results_page --write`:\n" + diff[:6000])


def test_a_changed_archive_figure_fails_the_check(tmp_path, capsys):
    root = _copy_docs(tmp_path)
    assert results_page.check(root) == ""
    path = root / results_page.RUNS / "scratch-push-s1.json"  # FetchPush from scratch, seed 1: 0.09 at 60k
    run = json.loads(path.read_text())
    assert run["curve"][-1] == [60000, 0.09]
    run["curve"][-1][1] = 0.19
    path.write_text(json.dumps(run))

    diff = results_page.check(root)
    assert "0.19" in diff and "0.09" in diff
    assert results_page.main(["--check", "--root", str(root)]) == 1
    assert "python -m tools.results_page --write" in capsys.readouterr().out
    assert results_page.main(["--write", "--root", str(root)]) == 0  # the page follows the archive again
    assert results_page.check(root) == ""
    assert "0.04 / 0.19 / 0.07" in (root / "docs/results.md").read_text()


def test_a_hand_edit_inside_a_generated_block_fails_the_check(tmp_path):
    root = _copy_docs(tmp_path)
    page = root / "docs/results.md"
    text = page.read_text()
    start = text.index("<!-- generated: slide_100k -->")
    edited = text[:start] + text[start:].replace("0.21", "0.25", 1)
    assert edited != text
    page.write_text(edited)
    assert "0.25" in results_page.check(root)


def test_blocks_must_be_declared_closed_and_on_a_page(tmp_path):
    root = _copy_docs(tmp_path)
    page = root / "docs/results.md"
    page.write_text(page.read_text() + "\n<!-- generated: nowhere -->\n<!-- end generated: nowhere -->\n")
    with pytest.raises(ValueError, match="no block 'nowhere'"):
        results_page.check(root)
    page.write_text((ROOT / "docs/results.md").read_text().replace("<!-- end generated: hand -->\n", ""))
    with pytest.raises(ValueError):
        results_page.check(root)


def test_run_level_statistics():
    """With 3 runs against 3 no two-sided permutation p is below 2/20 = 0.1, however far apart the arms."""
    perm = results_page.permutation([0.95, 0.97, 0.90], [0.04, 0.09, 0.07])
    assert perm == {"p": 0.1, "floor": 0.1, "relabellings": 20}
    assert results_page.permutation([1, 2, 3, 4, 5], [6, 7, 8, 9, 10])["floor"] == pytest.approx(2 / 252)
    m, lo, hi = results_page.t_interval([0.2, 0.29, 0.3])
    assert lo < m < hi and hi - m == pytest.approx(4.303 * 0.0551 / 3**0.5, rel=1e-2)
    w = results_page.welch([0.26, 0.23, 0.20], [0.20, 0.29, 0.30])
    assert w["diff"] == pytest.approx(-0.1 / 3) and 0.3 < w["p"] < 0.6 and w["lo"] < 0 < w["hi"]
    assert results_page.welch([1.0, 1.0], [1.0, 1.0])["p"] is None
