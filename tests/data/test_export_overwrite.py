"""``data export-synthetic`` never mixes two exports of a split: a folder holding one (or files
no export wrote) needs ``--overwrite``, which deletes only what the earlier export wrote."""

from __future__ import annotations

import pickle

from t3fast.commands.main import main

EXPORT = ["data", "export-synthetic", "--split", "val", "--out"]


def frames(out) -> list[str]:
    return sorted(p.relative_to(out).as_posix() for p in (out / "gts").rglob("labels.npz"))


def test_a_second_export_needs_overwrite_which_removes_only_the_old_export(tmp_path, capsys):
    out = tmp_path / "exp"
    assert main([*EXPORT, str(out), "--scenes", "2", "--frames", "12"]) == 0
    info = out / "synthetic_infos_val.pkl"
    before = {p: p.read_bytes() for p in [info, *(out / "gts").rglob("labels.npz")]}
    capsys.readouterr()

    assert main([*EXPORT, str(out), "--scenes", "1", "--frames", "11"]) == 2
    assert capsys.readouterr().err == (
        f"t3fast data export-synthetic: --out {out} is not empty (synthetic_infos_val.pkl, gts/synthetic-val-00000, "
        "gts/synthetic-val-00001): pass --overwrite to replace the val export there (it deletes only the info "
        "file and frames an export wrote)\n"
    )
    assert {p: p.read_bytes() for p in before} == before and len(frames(out)) == 24

    (out / "notes.txt").write_text("mine")
    (out / "gts" / "synthetic-val-00000" / "mine.txt").write_text("mine too")
    assert main([*EXPORT, str(out), "--scenes", "1", "--frames", "11", "--overwrite"]) == 0
    assert frames(out) == [f"gts/synthetic-val-00000/synthetic-val-00000-{t:03d}/labels.npz" for t in range(11)]
    with open(info, "rb") as f:
        infos = pickle.load(f)["infos"]
    assert list(infos) == ["synthetic-val-00000"] and len(infos["synthetic-val-00000"]) == 11
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "gts" / "synthetic-val-00000" / "mine.txt").read_text() == "mine too"


def test_other_files_need_overwrite_and_other_splits_do_not(tmp_path, capsys):
    out = tmp_path / "exp"
    out.mkdir()
    (out / "README").write_text("x")
    assert main([*EXPORT, str(out), "--scenes", "1", "--frames", "11"]) == 2
    assert f"--out {out} is not empty (README): pass --overwrite" in capsys.readouterr().err
    assert not (out / "gts").exists()

    (out / "README").unlink()
    assert main([*EXPORT, str(out), "--scenes", "1", "--frames", "11"]) == 0
    test = ["data", "export-synthetic", "--split", "test", "--out", str(out), "--scenes", "1", "--frames", "11"]
    assert main(test) == 0  # the test split beside the val split: nothing of it to replace
    assert len(frames(out)) == 22 and (out / "synthetic_infos_val.pkl").is_file()
