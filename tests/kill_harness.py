"""kill -9 harness: run a slamreloc command that rewrites a map many times, SIGKILL it at
random moments, and check the map after every kill.

    python -m tests.kill_harness SPEC.json      (prints a JSON report on stdout)

SPEC: {"argv": ["map", DATASET, "--out", MAP, ...],   the command, as after `slamreloc`
       "map": MAP,                                     the map folder the command rewrites
       "kills": 50, "seed": 0, "time_limit_s": 300,
       "tail_fraction": 0.5}   share of kills aimed at the write phase (after the command's
                               temporary map folder appears), the rest uniform over the run

The harness imports slamreloc once and forks one child per run; the child runs
`slamreloc.cli.main()` with the command's argv exactly as `python -m slamreloc.cli` does, so a
kill costs the command's run time rather than Python's and torch's start-up (seconds on a busy
2-core machine). The map must exist before the first run (the "previous map").

After each kill, before anything else touches the map, the harness records what is on disk;
then a "next start" (SceneMap.load in a fresh child) must load the map and its database, and
must leave no temporary or moved-aside folders beside it. The map must be either the previous
map (same checksums) or a complete new one written by a run that got past its swap. Any other
outcome is listed under "failures". Any command that rewrites a map (`pseudo-label ... --out`)
can be driven the same way.
"""

from __future__ import annotations

import json
import os
import random
import signal
import statistics
import sys
import time
from pathlib import Path


def _leftovers(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.glob(f".{out.name}.*")
                  if not p.name.endswith(".lock"))


def _fork(fn) -> int:
    pid = os.fork()
    if pid == 0:
        try:
            code = fn()
        except SystemExit as exit_:
            code = exit_.code if isinstance(exit_.code, int) else 1
        except BaseException:  # noqa: BLE001
            import traceback

            traceback.print_exc()
            code = 99
        os._exit(code or 0)
    return pid


def _run_command(argv: list[str]):
    def run():
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        from slamreloc import cli

        sys.argv = ["slamreloc", *argv]
        cli.main()
        return 0
    return run


def _check_map(out: Path, result: Path):
    """The next start: load the map and its database; report its checksums."""
    def run():
        from slamreloc.map.scene_map import SceneMap

        try:
            m = SceneMap.load(out)
            n = len(m.database.points)
            info = {"ok": True, "files": m.meta.get("files"), "n_points": n}
        except Exception as err:  # noqa: BLE001 - reported as a failure
            info = {"ok": False, "error": f"{type(err).__name__}: {err}"}
        result.write_text(json.dumps(info))
        return 0
    return run


def _wait(pid: int) -> int:
    _, status = os.waitpid(pid, 0)
    return -os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)


def _check(out: Path, scratch: Path) -> dict:
    result = scratch / "check.json"
    result.unlink(missing_ok=True)
    code = _wait(_fork(_check_map(out, result)))
    info = json.loads(result.read_text()) if result.exists() else {"ok": False,
                                                                   "error": f"exit {code}"}
    info["leftovers_after"] = _leftovers(out)
    return info


def _timed_run(argv: list[str], out: Path, kill_at: float | None, after_tmp: bool,
               poll: float = 0.002, hang_s: float = 300.0) -> dict:
    """Run once; SIGKILL `kill_at` s after start (or after the temporary folder appears)."""
    t0 = time.monotonic()
    pid = _fork(_run_command(argv))
    tmp = out.parent / f".{out.name}.tmp-{pid}"
    t_tmp = None
    deadline = None if after_tmp or kill_at is None else t0 + kill_at
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        now = time.monotonic()
        if done:
            code = -os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)
            return {"killed": False, "exit": code, "t": now - t0, "t_tmp": t_tmp}
        if t_tmp is None and tmp.exists():
            t_tmp = now - t0
            if after_tmp and kill_at is not None:
                deadline = now + kill_at
        if now - t0 > hang_s:
            os.kill(pid, signal.SIGKILL)
            _wait(pid)
            return {"killed": False, "exit": "hung", "t": now - t0, "t_tmp": t_tmp}
        if deadline is not None and now >= deadline:
            os.kill(pid, signal.SIGKILL)
            code = _wait(pid)
            return {"killed": code == -signal.SIGKILL, "exit": code, "t": now - t0,
                    "t_tmp": t_tmp}
        time.sleep(poll)


def run(spec: dict) -> dict:
    out = Path(spec["map"])
    argv = spec["argv"]
    rng = random.Random(spec.get("seed", 0))
    scratch = out.parent / f"killharness-{os.getpid()}"
    scratch.mkdir(exist_ok=True)
    start = time.monotonic()
    report = {"kills": 0, "runs": 0, "completed_runs": 0, "kept_previous_map": 0,
              "replaced_by_complete_map": 0, "kills_in_write_phase": 0,
              "leftovers_seen_after_kill": 0, "failures": [], "kill_times": []}
    previous = _check(out, scratch)
    if not previous["ok"]:
        raise SystemExit(f"the map must exist and load before the first run: {previous}")
    if spec.get("warmup", True):
        # one complete run in this process first: the children inherit its one-time lazy
        # initialisation (OpenCV, oneDNN, pycolmap), so each run costs its real work only
        devnull = os.open(os.devnull, os.O_WRONLY)
        saved = os.dup(1), os.dup(2)
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        try:
            from slamreloc import cli

            sys.argv = ["slamreloc", *argv]
            try:
                cli.main()
            except SystemExit as exit_:
                if exit_.code:
                    raise SystemExit(f"warm-up run failed with exit {exit_.code}") from None
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
    # calibration: one complete run gives the run time and when the write phase starts
    calib = _timed_run(argv, out, None, after_tmp=True)
    if calib["exit"] != 0 or calib["t_tmp"] is None:
        raise SystemExit(f"calibration run failed: {calib}")
    previous = _check(out, scratch)
    # kill windows follow the recent complete runs (a busy machine's run times drift)
    totals, writes = [calib["t"]], [max(calib["t"] - calib["t_tmp"], 0.01)]
    report.update(calibration_run_s=round(totals[0], 3), calibration_write_s=round(writes[0], 3))
    while report["kills"] < spec.get("kills", 50):
        if time.monotonic() - start > spec.get("time_limit_s", 300):
            report["failures"].append("time limit reached before all kills")
            break
        total = statistics.median(totals[-5:])
        write = statistics.median(writes[-5:])
        tail = rng.random() < spec.get("tail_fraction", 0.5)
        # tail: from the temporary folder's appearance to a little past the run's end
        at = rng.uniform(0, write * 1.2) if tail else rng.uniform(0, total * 1.1)
        res = _timed_run(argv, out, at, after_tmp=tail, hang_s=max(60.0, 30 * total))
        report["runs"] += 1
        on_disk = {"map_exists": out.exists(), "leftovers": _leftovers(out)}
        info = _check(out, scratch)
        if res["killed"]:
            report["kills"] += 1
            report["kill_times"].append(round(res["t"], 3))
            report["kills_in_write_phase"] += res["t_tmp"] is not None
            report["leftovers_seen_after_kill"] += bool(on_disk["leftovers"])
        elif res["exit"] == 0:
            report["completed_runs"] += 1
            totals.append(res["t"])
            if res["t_tmp"] is not None:
                writes.append(max(res["t"] - res["t_tmp"], 0.01))
        else:
            report["failures"].append(f"run exited {res['exit']} without being killed")
        if not info["ok"]:
            report["failures"].append(f"after {res} with {on_disk}: map does not load: "
                                      f"{info['error']}")
        elif info["leftovers_after"]:
            report["failures"].append(f"leftovers after the next start: "
                                      f"{info['leftovers_after']}")
        elif info["files"] == previous["files"]:
            report["kept_previous_map"] += res["killed"]
        else:
            report["replaced_by_complete_map"] += res["killed"]
        if info["ok"]:
            previous = info
    report["total_s"] = round(time.monotonic() - start, 1)
    report.update(run_s=round(statistics.median(totals), 3),
                  write_phase_s=round(statistics.median(writes), 3))
    for p in scratch.iterdir():
        p.unlink()
    scratch.rmdir()
    return report


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import torch

    torch.set_num_threads(1)  # no thread pools in the forking parent
    import slamreloc.cli  # noqa: F401 - imported once, before forking
    import slamreloc.map.build  # noqa: F401

    print(json.dumps(run(json.loads(Path(sys.argv[1]).read_text()))))
