"""Resumable training: a run killed after a checkpoint and resumed ends where an uninterrupted
run ends; Ctrl-C saves the state and says how to resume."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest
import torch

import slamreloc.regressor.train as train_mod
from slamreloc.errors import InputError
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.regressor.train import TrainConfig, train_regressor
from tests.conftest import sigint_as_from_a_terminal

CONFIG = TrainConfig(epochs=6, batch_size=256, precision="fp32", checkpoint_every_s=0.0)


def _data(n=1500, seed=0):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-2, 2, (n, 3)).astype(np.float32)
    desc = np.tanh(points @ rng.normal(size=(3, 128))).astype(np.float32)
    return desc, points


def _model():
    torch.manual_seed(0)  # the same initial weights for every run
    return SceneCoordinateRegressor(RegressorConfig(128, (128, 64), head="clusters",
                                                    n_clusters=16))


class Killed(Exception):
    """Stands for kill -9 right after a checkpoint was written."""


@pytest.mark.parametrize("average_tail", [0.0, 0.7])  # 0.7: epochs 2-5, one of them before the kill
def test_killed_and_resumed_run_matches_an_uninterrupted_one(tmp_path, monkeypatch, average_tail):
    desc, points = _data()
    torch.set_num_threads(1)
    config = replace(CONFIG, average_tail=average_tail)
    reference = _model()
    train_regressor(reference, desc, points, config, "cpu", progress=False)

    saves = {"n": 0}
    real_save = train_mod.save_checkpoint

    def save_then_die(*args, **kwargs):
        real_save(*args, **kwargs)
        saves["n"] += 1
        if saves["n"] == 3:
            raise Killed

    ckpt = tmp_path / "ckpt.pt"
    monkeypatch.setattr(train_mod, "save_checkpoint", save_then_die)
    with pytest.raises(Killed):
        train_regressor(_model(), desc, points, config, "cpu", progress=False, checkpoint=ckpt)
    monkeypatch.setattr(train_mod, "save_checkpoint", real_save)
    resumed = _model()
    stats = train_regressor(resumed, desc, points, config, "cpu", progress=False,
                            checkpoint=ckpt, resume=True)
    assert stats["resumed_at_epoch"] == 3
    assert stats["averaged_epochs"] == (4 if average_tail else 0)
    for (name, a), b in zip(reference.state_dict().items(), resumed.state_dict().values()):
        assert torch.allclose(a, b, atol=1e-5), name


def test_resume_refuses_a_checkpoint_of_other_data(tmp_path):
    desc, points = _data()
    ckpt = tmp_path / "ckpt.pt"
    train_regressor(_model(), desc, points, CONFIG, "cpu", progress=False, checkpoint=ckpt)
    other_desc, other_points = _data(seed=1)
    with pytest.raises(InputError, match="other training data"):
        train_regressor(_model(), other_desc, other_points, CONFIG, "cpu", progress=False,
                        checkpoint=ckpt, resume=True)
    ckpt.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="unreadable training checkpoint"):
        train_regressor(_model(), desc, points, CONFIG, "cpu", progress=False,
                        checkpoint=ckpt, resume=True)


def test_ctrl_c_during_map_saves_state_and_says_how_to_resume(scene_dir, tmp_path):
    out = tmp_path / "m"
    cmd = [sys.executable, "-m", "slamreloc.cli", "map", str(scene_dir), "--out", str(out),
           "--epochs", "500", "--precision", "fp32"]
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "COLUMNS": "200"},
                            preexec_fn=sigint_as_from_a_terminal)
    seen = ""
    try:
        deadline = time.monotonic() + 240
        while "training on" not in seen and time.monotonic() < deadline:
            line = proc.stderr.readline()
            if not line:
                break
            seen += line
        assert "training on" in seen, seen
        time.sleep(3.0)
        proc.send_signal(signal.SIGINT)
        rest = proc.communicate(timeout=120)[1]
    finally:
        if proc.poll() is None:  # a failed check must not leave 500 epochs training
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, seen + rest
    assert "--resume" in rest and "Traceback" not in rest
    assert (tmp_path / ".m.train-checkpoint.pt").is_file()
    assert not out.exists()  # no half-written map
    # a resume with other settings is refused in one line, before any training
    res = subprocess.run(cmd[:-4] + ["--epochs", "7", "--resume"], capture_output=True,
                         text=True)
    assert res.returncode == 2 and "another config.train.epochs (500, now 7)" in res.stderr
    assert "Traceback" not in res.stderr and "features" not in res.stderr  # before any work


def test_resume_without_checkpoint_is_a_one_line_error(scene_dir, tmp_path):
    res = subprocess.run([sys.executable, "-m", "slamreloc.cli", "map", str(scene_dir), "--out",
                          str(tmp_path / "m"), "--resume"], capture_output=True, text=True)
    assert res.returncode == 2 and "no interrupted training of this map" in res.stderr
