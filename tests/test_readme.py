"""The README's Python examples run as written (each in a fresh interpreter, from a folder that
holds the data paths they name)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"
BLOCKS = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)


def test_the_readme_has_examples():
    assert len(BLOCKS) >= 5


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_example_runs(index, tmp_path):
    code = BLOCKS[index]
    if "data/occ3d" in code:  # the Occ3D example: a synthetic export in the Occ3D layout stands in
        from t3fast.data.export import export_synthetic

        info = export_synthetic(tmp_path / "data" / "occ3d", "val", 1, 11, progress=False)
        for name in re.findall(r"data/(nuscenes_infos_\w+\.pkl)", code):
            shutil.copy(info, tmp_path / "data" / name)
    result = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"README example {index + 1} failed:\n{code}\n{result.stderr[-3000:]}"
