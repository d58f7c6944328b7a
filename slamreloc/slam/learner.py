"""The background learner of a live map: training rounds of the scene-coordinate regressor on
a thread of their own while the tracker keeps running.

`submit(descriptors, points)` hands the learner the database as it stands (map frame, metres;
rows in the order they were added); when no round is running, one starts at once on a thread,
else the newest submission waits for the running round to end (older ones are dropped: only
the newest placement of the keyframes is worth learning). A round trains a copy of the
published model and publishes the copy when it ends: the swap is one reference assignment, so
a reader has either the old model or the new one, never a half-trained one.

- A warm round starts from the published weights, at a reduced rate, on a bounded window: the
  rows added since the last round plus a uniform sample of the older ones (replay), at most
  `round_rows` in all, so its cost does not grow with the map and a new place is learned
  within a round or two.
- A scratch round (normalisation, prototypes and regions fitted anew, on every row, at most
  `scratch_steps` optimisation steps) runs when there is no model yet, when the rows have
  grown by `regrow` times since the last one, when more rows came since the last round than a
  warm window holds (`round_rows`: a warm round would leave some new places out, and so many
  new rows are new ground its regions were not fitted to; RedKitchen at 18 frames/s: 48k new
  rows, the newest 30k trained warm to 8.8 cm, places seen 20-25 s in waited 80 s), or when
  the last warm round ended far above the last scratch round's training distance
  (`refit_ratio`): a model's regions, prototypes and output scaling are fitted to the part
  of the scene it first saw, and warm rounds cannot teach it places far outside that part.
- The final round (`submit(..., final=True)`, at the end of a session) trains every row for
  `final_epochs`, on the keyframes' final placement: warm, or from scratch where the last warm
  round fitted badly.
"""

from __future__ import annotations

import copy
import threading
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from slamreloc.errors import Diverged
from slamreloc.regressor.model import RegressorConfig, SceneCoordinateRegressor
from slamreloc.regressor.train import TrainConfig, train_regressor


@dataclass(frozen=True)
class LearnerConfig:
    """Epochs per round (warm-started and from scratch) and the growth that forces a scratch
    round; `train`: the rest of the training settings (`TrainConfig`); `background`: rounds on
    the learner's thread (live) or on the submitting one (reproducible)."""

    warm_epochs: int = 4
    scratch_epochs: int = 6
    scratch_steps: int = 600  # at most this many optimisation steps in a scratch round
    round_rows: int = 30000  # rows of a warm round: the new ones, then replayed old ones
    final_epochs: int = 12
    warm_lr_scale: float = 0.5
    regrow: float = 2.0
    # a warm round that ends above `refit_ratio` times the last scratch round's training
    # distance, and above `refit_floor_m`, has met places the model's regions and prototypes do
    # not cover: the next round (the final one too) starts from scratch
    refit_ratio: float = 3.0
    refit_floor_m: float = 0.05
    min_rows: int = 500  # fewer labelled rows: no round yet
    # torch threads of the rounds (set on the learner's own thread: OpenMP's count is per
    # thread), so that the tracker keeps the other cores; 0: torch's default
    threads: int = 1
    train: TrainConfig = field(default_factory=lambda: TrainConfig(lr_halvings=2))
    device: str = "cpu"
    # False: each submission's round runs on the submitting thread before `submit` returns, so
    # the rounds, and the map, do not depend on the machine's speed (the tracker waits)
    background: bool = True


@dataclass(frozen=True)
class Round:
    """One finished round: when it started and ended (seconds since the learner started), the
    rows it trained on, whether it started from scratch, its final training distance (m)."""

    started_s: float
    ended_s: float
    n_rows: int
    scratch: bool
    final_loss_m: float | None
    version: int  # the model version it published


class _Stopped(Exception):
    """A round ended by `BackgroundLearner.stop`."""


class BackgroundLearner:
    """Trains and publishes the regressor of a live map (see the module's docstring)."""

    def __init__(self, model_config: RegressorConfig, config: LearnerConfig = LearnerConfig(),
                 initial: SceneCoordinateRegressor | None = None, initial_rows: int = 0,
                 on_round: callable | None = None):
        """initial: a trained model to start from (a prior map's: warm rounds from it), trained
        on the first `initial_rows` rows the learner will be given; on_round(round, model):
        called on the learner's thread after each published round."""
        self.model_config, self.config = model_config, config
        self.model: SceneCoordinateRegressor | None = initial  # the published model
        self.version = 0 if initial is None else 1
        self.trained_rows = 0  # rows in the database when the published model's round began
        self._seen = initial_rows if initial is not None else 0  # rows trained on so far
        self._scratch_rows = 0 if initial is None else None  # rows at the last scratch round
        self._scratch_loss_m: float | None = None  # its final training distance
        self._stale = False  # the last warm round fitted badly: the next starts from scratch
        self._pending: tuple[np.ndarray, np.ndarray, bool] | None = None
        self._rng = np.random.default_rng(config.train.seed)
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stopping = threading.Event()  # `stop`: rounds end at their next step
        self._t0 = time.perf_counter()
        self.rounds: list[Round] = []
        self.error: BaseException | None = None  # a round's failure, raised by `check`
        self.on_round = on_round
        self.busy_s = 0.0  # wall seconds spent in rounds

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def submit(self, descriptors: np.ndarray, points: np.ndarray, final: bool = False) -> None:
        """The database as it stands: (N, D) descriptors, (N, 3) map-frame points (metres),
        in the order the rows were added; `final`: the session's last round."""
        self.check()
        if len(points) < self.config.min_rows:
            return
        with self._lock:
            if self._stopping.is_set():
                return
            if self.config.background:
                self._pending = (descriptors, points, final)
                if not self.running:
                    self._thread = threading.Thread(target=self._run, name="slamreloc-learner",
                                                    daemon=True)
                    self._thread.start()
                return
        try:
            self._round(descriptors, points, final)
        except _Stopped:
            pass

    def check(self) -> None:
        """Raise the failure of a round, if one failed."""
        if self.error is not None:
            raise self.error

    def wait(self, timeout_s: float | None = None) -> None:
        """Until the running round (and any waiting submission) has ended."""
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)
        self.check()

    def stop(self, timeout_s: float | None = None) -> None:
        """End the learner: the waiting submission is dropped, the running round ends at its
        next step without publishing, and this returns once its thread has ended (or after
        `timeout_s`). The published model stays; no round starts after this. A process must
        not exit with the thread inside torch (its forced unwinding aborts the process)."""
        with self._lock:
            self._stopping.set()
            self._pending = None
        thread = self._thread
        if thread is not None:
            thread.join(timeout_s)

    def _run(self) -> None:
        if self.config.threads > 0:
            torch.set_num_threads(self.config.threads)  # this thread's own OpenMP team
        try:
            while True:
                with self._lock:
                    job, self._pending = self._pending, None
                if job is None or self._stopping.is_set():
                    return
                self._round(*job)
        except _Stopped:
            return
        except BaseException as e:  # noqa: BLE001 - handed to the tracker's thread by check()
            self.error = e

    def _check_stop(self, *_) -> None:
        """After each step and epoch: a `stop` ends the round there (a server's stop, a
        session's cancel wait one step, not an epoch that grows with the session)."""
        if self._stopping.is_set():
            raise _Stopped

    def _round(self, descriptors: np.ndarray, points: np.ndarray, final: bool) -> None:
        c = self.config
        start = time.perf_counter()
        n = len(points)
        scratch = self.model is None or self._stale or (
            not final and self._scratch_rows is not None
            and (n >= c.regrow * self._scratch_rows or n - self._seen > c.round_rows))
        rows = np.arange(n)
        if scratch:
            model = SceneCoordinateRegressor(self.model_config)
            steps_per_epoch = max(1, n // c.train.batch_size)
            epochs = max(1, min(c.scratch_epochs, c.scratch_steps // steps_per_epoch))
            if final:  # the map that is saved: as long as a final warm round
                epochs = max(epochs, c.final_epochs)
            train = replace(c.train, epochs=epochs)
        else:
            model = copy.deepcopy(self.model).requires_grad_(True)
            train = replace(c.train, epochs=c.final_epochs if final else c.warm_epochs,
                            lr=c.train.lr * c.warm_lr_scale)
            if not final:
                rows = self._window(n)
        try:
            stats = train_regressor(model, descriptors[rows].astype(np.float32), points[rows],
                                    train, c.device, progress=False, fine_tune=not scratch,
                                    on_epoch_end=self._check_stop, on_step=self._check_stop)
        except Diverged:  # the published model stays; the next round starts from scratch
            self._stale = True
            self.busy_s += time.perf_counter() - start
            return
        model.eval().requires_grad_(False)  # published: read by the tracker, never trained
        self.model = model  # the swap: readers hold either the old model or this one
        self.version += 1
        self.trained_rows = n
        self._seen = n
        loss = stats["final_loss_m"]
        if scratch:
            self._scratch_rows, self._scratch_loss_m = n, loss
        self._stale = (not scratch and loss is not None and self._scratch_loss_m is not None
                       and loss > max(c.refit_ratio * self._scratch_loss_m, c.refit_floor_m))
        end = time.perf_counter()
        self.busy_s += end - start
        r = Round(start - self._t0, end - self._t0, len(rows), scratch, stats["final_loss_m"],
                  self.version)
        self.rounds.append(r)
        if self.on_round is not None:
            self.on_round(r, model)

    def _window(self, n: int) -> np.ndarray:
        """A warm round's rows: those added since the last round (the newest `round_rows` of
        them), then a uniform sample of the older ones up to `round_rows` in all."""
        budget = self.config.round_rows
        new = np.arange(min(self._seen, n), n)[-budget:]
        old = np.arange(0, n - len(new))
        k = min(len(old), budget - len(new))
        sample = self._rng.choice(old, size=k, replace=False) if k > 0 else old[:0]
        return np.sort(np.concatenate([sample, new]))

