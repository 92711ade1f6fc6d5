"""The README and the pages in docs/: their Python examples run as written (each in a fresh
interpreter, from a folder that holds the data paths they name), their links lead somewhere, and
the result tables they show are the committed records in benchmarks/results."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]
BLOCKS = [(page, code) for page in PAGES for code in re.findall(r"```python\n(.*?)```", page.read_text(), re.S)]
RESULTS = ROOT / "benchmarks" / "results"
#: the README's results table: its columns and where each value is in a metrics.json record
README_COLUMNS = {
    "mIoU avg": lambda r: r["miou"]["avg"],
    "IoU avg": lambda r: r["iou"]["avg"],
    "moving mIoU avg": lambda r: r["miou_moving"]["avg"],
    "mean-L2 avg (m)": lambda r: r["l2_mean"]["avg"],
    "L2 at 3 s (m)": lambda r: r["l2_at"]["3s"],
    "collision avg (%)": lambda r: None if r["collision"]["avg"] is None else 100 * r["collision"]["avg"],
}


def _table_rows(text: str, first_header: str) -> tuple[list[str], dict[str, list[str]]]:
    """The header and the rows (by first cell) of the markdown table whose first header cell is
    ``first_header``."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"| {first_header} |"))
    header = [c.strip() for c in lines[start].strip("|").split("|")]
    rows = {}
    for line in lines[start + 2 :]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows[cells[0].strip("`")] = cells[1:]
    return header[1:], rows


def _record_rows(record: dict) -> dict:
    """A metrics.json record under today's row names: one written before the headline row planned
    without the route command names that row ``t3former_no_command`` and the one given the
    command ``t3former``."""
    if "t3former_no_command" not in record:
        return record
    names = {"t3former_no_command": "t3former", "t3former": "t3former_command"}
    return {names.get(name, name): row for name, row in record.items()}


def _anchor(heading: str) -> str:
    """GitHub's anchor of a markdown heading."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def test_the_pages_have_examples():
    assert len([code for page, code in BLOCKS if page == README]) >= 3
    assert len(BLOCKS) >= 5


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_example_runs(index, tmp_path):
    page, code = BLOCKS[index]
    if "data/occ3d" in code:  # the Occ3D example: a synthetic export in the Occ3D layout stands in
        from t3fast.data.export import export_synthetic

        info = export_synthetic(tmp_path / "data" / "occ3d", "val", 1, 11, progress=False)
        for name in re.findall(r"data/(nuscenes_infos_\w+\.pkl)", code):
            shutil.copy(info, tmp_path / "data" / name)
    result = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, f"{page.name} example failed:\n{code}\n{result.stderr[-3000:]}"


def test_the_readme_is_short_and_leads_to_the_docs():
    text = README.read_text()
    assert len(text.splitlines()) <= 400
    for page in ("how-it-works.md", "results.md", "training.md", "reliability.md"):
        assert f"](docs/{page})" in text and (ROOT / "docs" / page).is_file()


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_links_lead_to_files_and_headings(page):
    text = page.read_text()
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+://", target):
            continue
        path, _, anchor = target.partition("#")
        file = page if not path else (page.parent / path).resolve()
        assert file.exists(), f"{page.name}: link to {target}: no {file}"
        if anchor and file.suffix == ".md":
            headings = {_anchor(h) for h in re.findall(r"^#+ (.+)$", file.read_text(), re.M)}
            assert anchor in headings, f"{page.name}: link to {target}: no such heading in {file.name}"


def test_the_readme_results_are_the_committed_test_record():
    record = _record_rows(json.loads((RESULTS / "wm-test-metrics.json").read_text()))
    header, rows = _table_rows(README.read_text(), "method")
    assert header == [*README_COLUMNS, "what it is"]
    # the headline row plans without the route command; the row given it is named so
    assert {"t3former", "t3former_command", "t3former_gt_ego", "warp_gt_ego", "track_gt_ego"} <= set(rows)
    for name, cells in rows.items():
        for column, cell in zip(README_COLUMNS, cells):
            value = README_COLUMNS[column](record[name])
            assert cell == ("-" if value is None else f"{value:.2f}"), f"README {name}, {column}: {cell}"


ABLATION_ROWS = ("| own_frames", "| no_delta", "| single_scale", "| bev")


def test_the_results_page_shows_the_committed_ablation_rows():
    committed = [line for line in (RESULTS / "wm-test-ablations-metrics.md").read_text().splitlines()
                 if line.startswith(ABLATION_ROWS)]
    page = (ROOT / "docs" / "results.md").read_text().splitlines()
    missing = [line for line in committed if line not in page]
    assert committed and not missing, f"docs/results.md lacks rows of the ablation record: {missing[:2]}"
