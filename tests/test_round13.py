"""Issue 43, what the twelfth round left (minor) and the thirteenth attack round found, as
regression tests."""

from __future__ import annotations

import pytest

from slamreloc.datasets import load_dataset
from slamreloc.errors import InputError
from tests.test_input_leftovers import scene, tum_folder  # noqa: F401 (a fixture)


def test_a_tum_list_going_back_in_time_is_refused(scene, tmp_path):  # noqa: F811
    """Round 12 minor: rgb.txt whose stamps went backwards was taken in file order (tracking
    ran the sequence backwards there); it is refused naming the line, as the C++ client does."""
    _, frames = scene
    root = tum_folder(frames, tmp_path / "tum")
    lines = (root / "rgb.txt").read_text().splitlines()
    lines[2], lines[3] = lines[3], lines[2]  # the second and third frames swapped
    (root / "rgb.txt").write_text("\n".join(lines) + "\n")
    earlier = lines[3].split()[0]
    with pytest.raises(InputError, match=rf"rgb.txt:4: timestamp {earlier} is earlier than "
                                         r"line 3's; the frames must be listed in time order"):
        load_dataset(root)
