"""Where a learning session's SessionSave may write, through the real server and client: never
into a served map's folder or an input a served map records (`--learned-maps` is refused at
start-up), never over a map the server does not serve under that name, a name counted in the
file system's bytes, a file-system error as one typed line without a server path; and a save
(its training round, its write) blocks no other client."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import grpc
import pytest

from slamreloc.client import Client, RemoteError
from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError
from slamreloc.map.format import META
from slamreloc.proto import relocalizer_pb2 as pb
from slamreloc.proto.messages import MAX_SAVED_NAME_BYTES
from slamreloc.service.server import ServeConfig, start_server
from slamreloc.slam import live_map
from tests.fuzzing import run_cli
from tests.test_service_live import LIVE, frames  # noqa: F401 - the shared fixture

REPO = Path(__file__).resolve().parents[1]
# rounds of one epoch: the maps only need to exist, not to be good
FAST = replace(LIVE, learner=replace(LIVE.learner, warm_epochs=1, scratch_epochs=1,
                                     scratch_steps=40, final_epochs=1))
N_LEARN = 12  # frames streamed before the first save: 11 keyframes, ~10000 rows


def tree(folder: Path) -> dict[str, str]:
    """Every file under `folder` -> the MD5 of its contents."""
    return {str(p.relative_to(folder)): hashlib.md5(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def raw_save(session, name: str):
    """A SessionSave as a client that does not check names sends it (the Python client
    refuses such names itself, by the same rule): what the server answers on the wire."""
    return session._answer(pb.SessionRequest(save=pb.SessionSave(name=name))).saved


def refused(call, kind: str) -> RemoteError:
    with pytest.raises(RemoteError) as err:
        call()
    assert err.value.kind == kind, err.value
    assert "\n" not in str(err.value)
    return err.value


@pytest.fixture(scope="module")
def learning(tmp_path_factory, frames):  # noqa: F811
    """A server with only `--learned-maps` (one worker), and a learning session that has
    streamed N_LEARN frames and saved its map as "seed"."""
    folder = tmp_path_factory.mktemp("saves") / "learned"
    folder.mkdir()
    running = start_server({}, ServeConfig(port=0, watch_s=0, learned_maps=folder, live=FAST))
    client = Client(running.address, timeout_s=30)
    session = client.session(odometry="auto", learn=True)
    for f in frames[:N_LEARN]:
        session.send(f.image, camera=f.camera, depth=f.depth, timestamp=f.timestamp)
    assert session.save("seed").map_version
    yield running, folder, client, session
    session.close()
    client.close()
    running.stop()


def test_names_are_counted_in_bytes(learning):
    """Finding 7: <= 128 characters but over the file system's bytes: BAD_REQUEST naming the
    bytes, no server path, nothing written; the longest name that fits in bytes saves."""
    running, folder, client, session = learning
    before = sorted(os.listdir(folder))
    for name in ("é" * 128, "€" * 100, "\U0001d538" * 64, "é" * 121 + "a"):
        with pytest.raises(InputError, match=f"{len(name.encode())} bytes"):
            session.save(name)  # the client's own check, by the server's rule
        err = refused(lambda: raw_save(session, name), "BAD_REQUEST")
        size = len(name.encode())
        assert f"{size} bytes" in str(err) and str(MAX_SAVED_NAME_BYTES) in str(err), err
        assert str(folder) not in str(err) and "Errno" not in str(err), err
    assert sorted(os.listdir(folder)) == before
    name = "é" * (MAX_SAVED_NAME_BYTES // 2)  # 242 bytes: the writer's temporary sibling fits
    saved = session.save(name)
    assert (folder / name / META).is_file()
    assert {m.name: m.version for m in client.list_maps()}[name] == saved.map_version


def test_an_unserved_map_in_the_folder_is_not_replaced(learning):
    """Finding 6: a map left in DIR (an earlier run, another server) is not saved over
    (docs: give it as MAP first); the map this server saved under that name is."""
    running, folder, client, session = learning
    shutil.copytree(folder / "seed", folder / "oldmap")
    before = tree(folder / "oldmap")
    err = refused(lambda: session.save("oldmap"), "FAILED_PRECONDITION")
    assert "does not serve" in str(err) and str(folder) not in str(err), err
    assert err.code == grpc.StatusCode.FAILED_PRECONDITION
    assert tree(folder / "oldmap") == before
    assert "oldmap" not in {m.name for m in client.list_maps()}
    again = session.save("seed")  # its own: replaced, served anew
    assert {m.name: m.version for m in client.list_maps()}["seed"] == again.map_version


def test_a_folder_served_under_another_name_is_not_replaced(learning, tmp_path):
    """Finding 4: DIR/m served as `other`: a save of `m` is refused (folders compared, not
    names), before any training round (the session has no frame); `other` too (its name is
    served from another folder)."""
    _, seed_folder, _, _ = learning
    shutil.copytree(seed_folder / "seed", tmp_path / "m")
    before = tree(tmp_path / "m")
    running = start_server({"other": tmp_path / "m"},
                           ServeConfig(port=0, watch_s=0, learned_maps=tmp_path, live=FAST))
    try:
        with Client(running.address) as client, client.session(odometry="auto",
                                                                learn=True) as session:
            err = refused(lambda: session.save("m"), "FAILED_PRECONDITION")
            assert "'other'" in str(err) and str(tmp_path) not in str(err), err
            err = refused(lambda: session.save("other"), "FAILED_PRECONDITION")
            assert "served from elsewhere" in str(err), err
            assert [m.name for m in client.list_maps()] == ["other"]
    finally:
        running.stop()
    assert tree(tmp_path / "m") == before


def test_learned_maps_inside_a_served_map_or_its_dataset_is_refused(learning, tmp_path,
                                                                      kidnap_scene):
    """Findings 3 and 5: --learned-maps equal to or inside a served map's folder, or the
    dataset a served map records, stops the start (InputError naming `learned_maps`); a
    served map inside --learned-maps (a saved map served again) is fine."""
    _, seed_folder, _, _ = learning
    base = tmp_path / "maps" / "base"
    shutil.copytree(seed_folder / "seed", base)
    recorded = tmp_path / "recorded"  # as `slam --out` records its dataset
    shutil.copytree(base, recorded)
    meta = json.loads((recorded / META).read_text())
    meta["dataset"] = {**meta["dataset"], "root": str(Path(kidnap_scene).resolve()),
                       "kind": load_dataset(kidnap_scene).kind, "split": "kidnap"}
    (recorded / META).write_text(json.dumps(meta))
    (base / "sub").mkdir()
    inside_scene = next(p for p in Path(kidnap_scene).iterdir() if p.is_dir())
    cases = [({"base": base}, base, "is the folder of the served map 'base'"),
             ({"base": base}, base / "sub", "lies inside the folder of the served map"),
             ({"rec": recorded}, Path(kidnap_scene), "is the dataset the map records"),
             ({"rec": recorded}, inside_scene, "lies inside the dataset the map records")]
    for maps, folder, words in cases:
        before = tree(folder)
        with pytest.raises(InputError, match="`learned_maps`") as err:
            start_server(maps, ServeConfig(port=0, watch_s=0, learned_maps=folder))
        assert words in str(err.value) and "\n" not in str(err.value), err.value
        assert tree(folder) == before
    running = start_server({"base": base}, ServeConfig(port=0, watch_s=0,
                                                       learned_maps=base.parent))
    running.stop()
    # the command line: one line naming the flag, exit status 2
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    res = subprocess.run([sys.executable, "-m", "slamreloc.cli", "serve", str(base),
                          "--learned-maps", str(base), "--port", "0"], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=120)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.returncode == 2 and len(lines) == 1, res.stderr
    assert lines[0].startswith("error: ") and "--learned-maps" in lines[0], lines


@pytest.mark.parametrize("code, kind", [(errno.ENOSPC, "FAILED_PRECONDITION"),
                                        (errno.ENAMETOOLONG, "BAD_REQUEST")])
def test_a_file_system_error_is_one_typed_line(learning, monkeypatch, code, kind):
    """Finding 7's second half: an OSError while saving is a typed refusal with the system's
    reason and no server path (it was INTERNAL, with the path and a traceback)."""
    running, folder, client, session = learning

    def full(out, *args, **kwargs):
        raise OSError(code, os.strerror(code), str(out))

    monkeypatch.setattr(live_map, "save_map", full)
    err = refused(lambda: session.save("diskfull"), kind)
    assert os.strerror(code) in str(err) and str(folder) not in str(err), err
    assert "diskfull" not in {m.name for m in client.list_maps()}
    assert not (folder / "diskfull").exists()


@pytest.mark.parametrize("in_the_way", ["link", "hard link", "notes"])
def test_a_save_the_map_writer_refuses_is_one_typed_line(learning, tmp_path, in_the_way):
    """Tenth round, G3: the map writer's refusal of what is in the way (a link or a user's file
    at its lock, a user's file in the map's folder) is FAILED_PRECONDITION naming it relative
    to the learned maps' folder, never the server's path (it was INTERNAL, with a traceback);
    nothing is written or changed."""
    running, folder, client, session = learning
    name = f"g3{in_the_way[0]}{len(in_the_way)}"
    victim = tmp_path / "victim.txt"
    victim.write_text("")
    if in_the_way == "link":
        (folder / f".{name}.lock").symlink_to(victim)
    elif in_the_way == "hard link":
        os.link(victim, folder / f".{name}.lock")
    else:
        assert session.save(name).map_version
        (folder / name / "notes.txt").write_text("the operator's")
    before = tree(folder)
    err = refused(lambda: session.save(name), "FAILED_PRECONDITION")
    assert "nothing was written" in str(err) and str(folder) not in str(err), err
    assert str(tmp_path) not in str(err) and victim.read_text() == "" and tree(folder) == before
    assert client.health().serving


class Gate:
    """Holds the first call of a function until `open`; `entered` once it is held."""

    def __init__(self, monkeypatch, owner, name: str):
        self.entered, self.released = threading.Event(), threading.Event()
        original, calls = getattr(owner, name), []

        def held(*args, **kwargs):
            calls.append(1)
            if len(calls) == 1:
                self.entered.set()
                assert self.released.wait(60)
            return original(*args, **kwargs)

        monkeypatch.setattr(owner, name, held)

    def open(self) -> None:
        self.released.set()


def quick(call, seconds: float = 10.0):
    t0 = time.monotonic()
    out = call()
    assert time.monotonic() - t0 < seconds
    return out


def test_a_save_blocks_no_other_client(learning, frames, monkeypatch):  # noqa: F811
    """A save held in its training round: Localize (one worker), Health, ListMaps and
    another session's save go on. Held in its write: those still answer, and another
    session's save is refused OVERLOADED at once rather than waiting on the lock."""
    running, folder, client, session = learning
    f = frames[3]
    answers: list = []

    def save(name):
        try:
            answers.append(session.save(name))
        except RemoteError as err:
            answers.append(err)

    with Client(running.address, timeout_s=20) as other:
        for owner, name, second in ((live_map.LiveMap, "finish", None),
                                    (live_map, "save_map", "OVERLOADED")):
            gate = Gate(monkeypatch, owner, name)
            saver = threading.Thread(target=save, args=("held",))
            saver.start()
            try:
                assert gate.entered.wait(30)
                quick(lambda: other.localize(f.image, camera=f.camera, map="seed"))
                assert quick(other.health).serving
                assert "seed" in {m.name for m in quick(other.list_maps)}
                with other.session(odometry="auto", learn=True) as second_session:
                    if second is None:  # nothing learned: refused before any lock
                        refused(lambda: quick(lambda: second_session.save("second")),
                                "FAILED_PRECONDITION")
                    else:
                        err = refused(lambda: quick(lambda: second_session.save("second"), 5),
                                      second)
                        assert "another session's map is being written" in str(err), err
            finally:
                gate.open()
                saver.join(120)
            assert not saver.is_alive()
            assert not isinstance(answers[-1], RemoteError), answers[-1]
            assert answers[-1].name == "held"
            monkeypatch.undo()
    assert "held" in {m.name for m in client.list_maps()}


def test_a_learned_map_replaced_by_a_link_to_another_is_not_reloaded(learning,
                                                                       frames):  # noqa: F811
    """Round 4 #6: session 1 saves `lb`, session 2 `lc`; DIR/lb replaced on disk by a link to
    DIR/lc: ReloadMap("lb") is refused (typed, no server path), `lb` keeps serving what it
    served and two names never serve one folder; session 2 still saves `lc`; session 1's
    save of `lb` is refused while the link is there (a save never writes through a link),
    and taken once the operator removed it."""
    running, folder, client, session = learning
    first = session.save("lb")
    with client.session(odometry="auto", learn=True) as other:
        for f in frames[:N_LEARN]:
            other.send(f.image, camera=f.camera, depth=f.depth, timestamp=f.timestamp)
        other.save("lc")
        shutil.rmtree(folder / "lb")
        (folder / "lb").symlink_to(folder / "lc", target_is_directory=True)
        err = refused(lambda: client.reload_map("lb"), "FAILED_PRECONDITION")
        assert err.code == grpc.StatusCode.FAILED_PRECONDITION
        assert "map 'lb' not reloaded" in str(err) and "symbolic link" in str(err), err
        assert str(folder) not in str(err), err
        listed = {m.name: m for m in client.list_maps()}
        assert listed["lb"].version == first.map_version
        assert client.health().serving
        again = other.save("lc")  # its owner is not locked out
        assert {m.name: m.version for m in client.list_maps()}["lc"] == again.map_version
        err = refused(lambda: session.save("lb"), "FAILED_PRECONDITION")
        assert "a symbolic link" in str(err), err
        (folder / "lb").unlink()
        saved = session.save("lb")
        assert (folder / "lb" / META).is_file() and not (folder / "lb").is_symlink()
        assert {m.name: m.version for m in client.list_maps()}["lb"] == saved.map_version


def test_a_learned_maps_folder_replaced_while_serving_takes_no_save(learning, tmp_path):
    """Round 5, finding 4: `--learned-maps` swapped at run time for a link to another folder,
    another folder, a file, or removed: a save is refused (FAILED_PRECONDITION, no server
    path), nothing is written anywhere and the folder is not re-created; the same folder put
    back takes saves again."""
    running, folder, client, session = learning
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    aside = folder.with_name(folder.name + ".aside")
    folder.rename(aside)
    try:
        for make, words in ((lambda: folder.symlink_to(elsewhere), "symbolic link"),
                            (folder.mkdir, "another folder"),
                            (lambda: folder.write_text("x"), "not a folder"),
                            (lambda: None, "removed")):
            make()
            err = refused(lambda: session.save("second"), "FAILED_PRECONDITION")
            assert words in str(err) and str(folder) not in str(err), err
            assert not any(elsewhere.iterdir())
            if folder.is_symlink() or folder.is_file():
                folder.unlink()
            elif folder.is_dir():
                assert not any(folder.iterdir())
                folder.rmdir()
        assert not os.path.lexists(folder)  # a save never re-creates it
    finally:
        aside.rename(folder)
    assert session.save("seed").map_version


def test_saves_under_new_names_are_bounded(tmp_path, frames):  # noqa: F811
    """Round 6, finding 4: one session saved map after map under new names, each staying
    loaded (16 MB of memory apiece), without bound. `max_learned_maps` bounds the new names
    (OVERLOADED, nothing written); saving over a map already saved is always taken."""
    folder = tmp_path / "learned"
    folder.mkdir()
    running = start_server({}, ServeConfig(port=0, watch_s=0, learned_maps=folder, live=FAST,
                                           max_learned_maps=1))
    try:
        with Client(running.address, timeout_s=30) as client:
            session = client.session(odometry="auto", learn=True)
            for f in frames[:N_LEARN]:
                session.send(f.image, camera=f.camera, depth=f.depth, timestamp=f.timestamp)
            assert session.save("first").map_version
            err = refused(lambda: session.save("second"), "OVERLOADED")
            assert "max_learned_maps" in str(err), err
            assert session.save("first").map_version  # over its own: taken
            session.close()
        assert sorted(os.listdir(folder)) == ["first"]
    finally:
        running.stop()
    code, err = run_cli(["serve", "--max-learned-maps", "3", str(tmp_path / "m")])
    assert code == 2 and "--learned-maps" in err and err.count("\n") == 1, err


def test_a_map_a_killed_writer_moved_aside_is_put_back_and_not_saved_over(learning):
    """Attack round 16, S1: with `lm` absent and a killed writer's `.lm.old-PID` holding a
    map, a save of `lm` passed its check, then the writer's lock put the map back and the
    save replaced it (its surface.npz lost). The target is checked again under the map's
    write lock, as the clean-up leaves it: the map put back is one this server does not
    serve, and is kept whole."""
    running, folder, client, session = learning
    aside = folder / ".lm.old-999999"
    shutil.copytree(folder / "seed", aside)
    before = tree(aside)
    err = refused(lambda: session.save("lm"), "FAILED_PRECONDITION")
    assert "does not serve" in str(err) and str(folder) not in str(err), err
    assert tree(folder / "lm") == before and not aside.exists()
    assert "lm" not in {m.name for m in client.list_maps()}
    shutil.rmtree(folder / "lm")


def test_a_reload_loop_never_holds_a_save_off(learning, monkeypatch):
    """Attack round 16, S3: a client reloading a learned map in a loop held that map's save
    off (the save's own load was refused while one ran, and the loop started the next first)
    for up to `load_timeout_s`, with other sessions' saves refused meanwhile. While a save
    puts its map in, no other load of it starts: the save waits for the one running, then
    loads its own; the loop's reloads meanwhile are refused OVERLOADED, saying why."""
    from slamreloc.service import maps

    running, folder, client, session = learning
    load = maps.ServedMap.load

    def slow(name, path):  # a large map: every load takes a while, so one always runs
        time.sleep(0.3)
        return load(name, path)

    monkeypatch.setattr(maps.ServedMap, "load", staticmethod(slow))
    stop, answers = threading.Event(), []

    def reload_loop():
        with Client(running.address, timeout_s=30) as other:
            while not stop.is_set():
                try:
                    answers.append(other.reload_map("seed").map.version)
                except RemoteError as err:
                    answers.append(err)

    loopers = [threading.Thread(target=reload_loop) for _ in range(2)]  # one always waiting
    for looper in loopers:
        looper.start()
    try:
        while not answers:
            time.sleep(0.05)
        saved = quick(lambda: session.save("seed"))  # 1.5 s here; 14 s before, or up to
        # `load_timeout_s`
    finally:
        stop.set()
        for looper in loopers:
            looper.join(60)
    assert saved.map_version == {m.name: m.version for m in client.list_maps()}["seed"]
    waits = [a for a in answers if isinstance(a, RemoteError)]
    assert all(a.kind == "OVERLOADED" for a in waits), waits
    assert any("being replaced by a session's save" in str(a) for a in waits), waits
