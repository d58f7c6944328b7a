"""Issue 43, attack rounds 24 and 25: an output (or its folder) changed after the start-up
checks is not written over, a file rewritten in place included (C1, C2, C6, C7, D1:
`outputs.still_as_checked`), and a writer that did not check is not bound by an earlier write
(D2); sfm copies only frame images of the dataset's size (C3); a training checkpoint whose
state is not one this run would hold at its epoch is refused naming the file and the field
(C4, C5, D3-D5)."""

from __future__ import annotations

import hashlib

import cv2
import pytest
import torch

from slamreloc.errors import InputError
from slamreloc.io.outputs import atomic_file, check_outputs
from tests.fuzzing import run_cli
from tests.test_resume import CONFIG, _data, _model


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ---- C2, C7: a file output ----------------------------------------------------------------------
@pytest.mark.parametrize("put", ["file", "fifo", "link"])
def test_a_file_put_at_an_output_after_the_checks_is_kept(tmp_path, put):
    out, other = tmp_path / "report.json", tmp_path / "precious.txt"
    other.write_text("precious\n")
    check_outputs({"--report": out}, {})
    if put == "file":
        out.write_text("precious\n")
    elif put == "fifo":
        import os

        os.mkfifo(out)
    else:
        out.symlink_to(other)
    with pytest.raises(InputError, match=r"report.json: a (file|named pipe|symbolic link \(to "
                                         r".*precious.txt\)) was put there while the command "
                                         r"ran; not written \(what is there is kept\)"):
        with atomic_file(out) as tmp:
            tmp.write_text("{}")
    assert other.read_text() == "precious\n"
    assert out.is_fifo() if put == "fifo" else out.read_text() == "precious\n"
    assert [p.name for p in tmp_path.iterdir()] != [] and not [
        p for p in tmp_path.iterdir() if ".tmp-" in p.name]


def test_a_file_output_rewritten_in_place_after_the_checks_is_kept(tmp_path):
    out = tmp_path / "report.json"
    out.write_text("{}")
    check_outputs({"--report": out}, {})
    with open(out, "w") as f:  # the same inode: `echo precious > report.json`
        f.write("precious\n")
    with pytest.raises(InputError, match="report.json: a file was put there while the command "
                                         "ran; not written"):
        with atomic_file(out) as tmp:
            tmp.write_text("{}")
    assert out.read_text() == "precious\n"


def test_a_writer_that_did_not_check_is_not_bound_by_its_earlier_write(tmp_path):
    """A server saving a learned map twice, the folder restored by its operator in between."""
    from tests.test_fuzz_inputs import _tiny_map

    import shutil

    out = _tiny_map(tmp_path / "learned")
    shutil.copytree(out, tmp_path / "copy")
    shutil.rmtree(out)
    (tmp_path / "copy").rename(out)  # a byte-identical copy put back: another folder on disk
    _tiny_map(out, n=80)


def test_an_output_removed_meanwhile_or_written_twice_is_written(tmp_path):
    out = tmp_path / "report.json"
    out.write_text("{}")
    check_outputs({"--report": out}, {})
    out.unlink()  # the user removed the old one: nothing of theirs is there
    for text in ("1", "2"):  # a command writing its own output twice
        with atomic_file(out) as tmp:
            tmp.write_text(text)
    assert out.read_text() == "2"


def test_an_outputs_folder_swapped_for_a_link_is_not_written_through(tmp_path):
    (tmp_path / "sub").mkdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "r.json").write_text("theirs")
    check_outputs({"--report": tmp_path / "sub" / "r.json"}, {})
    (tmp_path / "sub").rename(tmp_path / "sub.moved")
    (tmp_path / "sub").symlink_to(elsewhere)
    with pytest.raises(InputError, match=r"r.json: its folder .*sub was replaced while the "
                                         "command ran; not written"):
        with atomic_file(tmp_path / "sub" / "r.json") as tmp:
            tmp.write_text("ours")
    assert (elsewhere / "r.json").read_text() == "theirs"


# ---- C1: export --colmap's folder ---------------------------------------------------------------
def test_a_link_put_at_export_colmap_while_it_runs_is_refused(small_map, tmp_path, monkeypatch):
    import slamreloc.map.export as export

    victim, out = tmp_path / "victim", tmp_path / "model"
    victim.mkdir()
    (victim / "notes.txt").write_text("precious\n")
    real_mark = export._write_export_mark

    def mark_then_link(folder, scene_map):
        real_mark(folder, scene_map)
        out.symlink_to(victim)

    monkeypatch.setattr(export, "_write_export_mark", mark_then_link)
    code, err = run_cli(["export", str(small_map.root), "--colmap", str(out)])
    assert code == 2 and err.strip().splitlines()[-1].startswith(
        f"error: {out}: a symbolic link (to {victim}) was put there while the command ran"), err
    assert out.is_symlink() and [p.name for p in victim.iterdir()] == ["notes.txt"]
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".model.")]


# ---- C3: sfm's copies of a dataset's frames --------------------------------------------------
def test_sfm_takes_a_dataset_frame_image_only_of_the_datasets_size(tmp_path):
    from slamreloc.sfm import checked_image

    path = tmp_path / "frame.png"
    cv2.imwrite(str(path), (255 * torch.rand(480, 640, 3).numpy()).astype("uint8"))
    assert checked_image(path)[1].shape == (480, 640, 3)
    with pytest.raises(InputError, match=r"frame.png: image is 640x480, the dataset's images "
                                         "are 320x240"):
        checked_image(path, (320, 240))


# ---- C4, C5: a damaged training checkpoint ------------------------------------------------------
def _opt_state(state):
    state["optimizer"]["state"][0]["exp_avg"] = torch.zeros(3, 3)


def _nan(state):
    next(iter(state["model"].values()))[...] = float("nan")


def _shape(state):
    key = next(iter(state["model"]))
    state["model"][key] = torch.zeros(3, 3)


DAMAGE = [  # (the field named, the damage)
    ("optimizer", lambda s: s.update(optimizer={})),
    ("optimizer", _opt_state),
    ("average", lambda s: s.pop("average")),
    ("average", lambda s: s["average"]["sums"].popitem()),
    ("generator", lambda s: s.update(generator=torch.zeros(5, dtype=torch.uint8))),
    ("model", _shape),
    ("model", _nan),
    ("scheduler", lambda s: s["scheduler"].update(last_epoch="q")),
    ("scheduler", lambda s: s["scheduler"].update(gamma=10.0)),
    ("epoch", lambda s: s.update(epoch="x")),
    ("epoch", lambda s: s.update(epoch=10 ** 12)),
    ("epoch", lambda s: s.update(epoch=-5)),
    ("losses", lambda s: s.update(losses="abc")),
    ("losses", lambda s: s.update(losses=[float("nan")] * len(s["losses"]))),
    ("average", lambda s: s["average"].update(count=10 ** 6)),
    ("optimizer", lambda s: s["optimizer"]["state"][0].update(step=torch.tensor(-5.0))),
    ("optimizer", lambda s: s["optimizer"]["state"][0]["exp_avg_sq"].mul_(-1).sub_(1)),
    ("optimizer", lambda s: s["optimizer"]["param_groups"][0].update(lr=50.0)),
    ("scheduler", lambda s: s["scheduler"].update(last_epoch=0, _step_count=1)),
]


@pytest.mark.parametrize("field, damage", DAMAGE,
                         ids=[f"{field}-{i}" for i, (field, _) in enumerate(DAMAGE)])
def test_a_damaged_checkpoint_is_refused_naming_it_and_the_field(tmp_path, field, damage):
    from slamreloc.regressor.train import train_regressor

    desc, points = _data()
    ckpt = tmp_path / "ckpt.pt"
    train_regressor(_model(), desc, points, CONFIG, "cpu", progress=False, checkpoint=ckpt)
    state = torch.load(ckpt, weights_only=True)
    damage(state)
    torch.save(state, ckpt)
    before = _sha(ckpt)
    with pytest.raises(InputError, match=rf"{ckpt}: unreadable training checkpoint "
                                         rf"\('{field}'"):
        train_regressor(_model(), desc, points, CONFIG, "cpu", progress=False,
                        checkpoint=ckpt, resume=True)
    assert _sha(ckpt) == before
