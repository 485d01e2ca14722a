"""The README's quick start runs as written (with the store moved to a temporary directory)."""
from __future__ import annotations

import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_quick_start_runs(tmp_path, capsys):
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks, "the README lost its quick start"
    code = blocks[0].replace("memory/pickandplace.zarr", str(tmp_path / "m.zarr"))
    namespace: dict = {}
    exec(compile(code, str(README), "exec"), namespace)
    prior = namespace["prior"]
    assert prior.shape == (5,) and prior["mask"].all()
    assert len(namespace["rb"]) == 1000
    assert torch.all(prior["distance"][1:] >= prior["distance"][:-1])
