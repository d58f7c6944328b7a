"""Issue 43, attack round 20 (CLI side): optional dataset files taken as absent when they are
something else, a quadratic check of TUM's image list, and the viewer's port probe."""

from __future__ import annotations

import shutil
import socket
import time

import pytest

from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError


@pytest.mark.parametrize("name", ["scene.json", "seq-01/frame-000000.pose.txt"])
def test_an_optional_file_that_is_a_folder_is_refused_not_taken_as_absent(scene_dir, tmp_path,
                                                                            name):
    """X4: scene.json (or a frame's pose.txt) that is a folder, a pipe or a loop was taken as
    missing: a synthetic scene was read as 7-Scenes with other labels, a frame as unposed."""
    root = tmp_path / "scene"
    shutil.copytree(scene_dir, root)
    (root / name).unlink()
    (root / name).mkdir()
    with pytest.raises(InputError, match=f"{root / name}: .* is a folder, not a file"):
        load_dataset(root).frames("seq-01")


def test_a_long_tum_image_list_with_a_repeat_is_refused_naming_it(tmp_path):
    """X5: the repeated-image check of rgb.txt was quadratic (100k lines: 203 s) and ran
    before any image was read."""
    lines = [f"{i}.0 rgb/{i}.png" for i in range(60_000)] + ["60000.0 rgb/59999.png"]
    (tmp_path / "rgb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="image '59999' is listed more than once"):
        load_dataset(tmp_path)


def test_a_port_waiting_out_time_wait_is_free_for_the_viewer():
    """X2: the viewer's port probe bound without SO_REUSEADDR, so a port whose last
    connection was in TIME_WAIT (a viewer just stopped, a browser had been connected) counted
    as in use, where viser binds it."""
    from slamreloc.viewer.server import first_free_port

    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))
    port = server.getsockname()[1]
    server.listen()
    client = socket.create_connection(("127.0.0.1", port))
    accepted, _ = server.accept()
    accepted.close()  # the server side closes first: its port waits out TIME_WAIT
    time.sleep(0.2)
    client.close()
    server.close()
    assert first_free_port("127.0.0.1", port) == port


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory):
    from tests.test_fuzz_inputs import _tiny_map

    return _tiny_map(tmp_path_factory.mktemp("round20") / "map")


@pytest.mark.parametrize("host,words", [
    ("[::1]", "write an IPv6 address without brackets"),
    ("::ffff:127.0.0.1", "an IPv4 address written as IPv6, which the viewer cannot bind; give "
                         "127.0.0.1"),
])
def test_a_host_viser_cannot_bind_is_refused_before_anything_is_read(tiny_map, host, words):
    """X1: `view --host ::ffff:127.0.0.1` hung silently, and `--host '[::1]'` ended after the
    map was read with `[Errno -2] Name or service not known`, naming no option."""
    from tests.fuzzing import run_cli

    code, err = run_cli(["view", str(tiny_map), "--host", host, "--port", "0"], hang_s=60)
    assert code == 2 and words in err.strip().splitlines()[-1], err


@pytest.mark.parametrize("kind", ["tmpfs", "bind"])
def test_a_mount_point_as_a_folder_output_is_refused_before_the_work(tiny_map, tmp_path, kind):
    """Round 19, V4: a folder output that is a mount point (a container's volume) ran the whole
    job, then failed its rename with "Device or resource busy", naming no option. X3: a bind
    mount from the same file system is no mount point to `os.path.ismount`; the mount table
    tells it."""
    import subprocess

    from tests.fuzzing import run_cli

    source, mount = tmp_path / "source", tmp_path / "mnt"
    source.mkdir()
    mount.mkdir()
    command = (["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(mount)] if kind == "tmpfs"
               else ["mount", "--bind", str(source), str(mount)])
    if subprocess.run(command, capture_output=True).returncode:
        pytest.skip(f"cannot {' '.join(command[:2])} here (needs root and a mount namespace)")
    try:
        code, err = run_cli(["export", str(tiny_map), "--colmap", str(mount)])
        assert code == 2 and err.strip().splitlines()[-1].startswith(
            f"error: {mount}: --colmap is a mount point"), err
        assert not any(mount.iterdir())
    finally:
        subprocess.run(["umount", str(mount)], check=True)
