"""Dataset folders (symlinks, 7-Scenes layout) for the map-update scenario on RedKitchen.

    OUT/labelled/seq-01     frames 0-199 of seq-01, with poses (the labelled map)
    OUT/unlabelled/seq-01   frames 200-399 of seq-01, colour + depth only: NO pose files, so
                            registration cannot read the truth (score with --truth SOURCE)
    OUT/queries/seq-02      all of seq-02 with poses (the test split)
    OUT/full/seq-01         the labelled + unlabelled frames with poses (the true-pose
                            reference map)

Usage: python scripts/make_redkitchen_update_split.py ../shared/data/7scenes_redkitchen \
           --out /tmp/rk_split [--n-labelled 200] [--n-unlabelled N (default: the rest)]
The data stays where it is (research licence): only links are written.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path


def link_frames(src_seq: Path, dst_seq: Path, frames: list[str], with_pose: bool) -> int:
    dst_seq.mkdir(parents=True, exist_ok=True)
    n = 0
    for stem in frames:
        for path in src_seq.glob(f"{stem}.*"):
            if path.name.endswith(".pose.txt") and not with_pose:
                continue
            (dst_seq / path.name).symlink_to(path.resolve())
        n += 1
    return n


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("source", type=Path, help="7-Scenes redkitchen folder (seq-01, seq-02)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--n-labelled", type=int, default=200)
    ap.add_argument("--n-unlabelled", type=int, default=None, help="default: the rest")
    args = ap.parse_args()
    src = args.source
    seq1 = sorted({p.name.split(".")[0] for p in (src / "seq-01").glob("frame-*.color.*")})
    seq2 = sorted({p.name.split(".")[0] for p in (src / "seq-02").glob("frame-*.color.*")})
    if not seq1 or not seq2:
        raise SystemExit(f"error: {src}: expected seq-01/ and seq-02/ with frame-*.color.* files")
    if args.out.exists():
        shutil.rmtree(args.out)
    k = args.n_labelled
    end = len(seq1) if args.n_unlabelled is None else k + args.n_unlabelled
    if k < 2 or end - k < 2 or end > len(seq1):
        raise SystemExit(f"error: {src}/seq-01 has {len(seq1)} frames: cannot take {k} labelled "
                         f"and {end - k} unlabelled ones (each at least 2, together at most {len(seq1)})")
    parts = {"labelled": ("seq-01", seq1[:k], True, "TrainSplit.txt", "sequence1"),
             "unlabelled": ("seq-01", seq1[k:end], False, "TrainSplit.txt", "sequence1"),
             "queries": ("seq-02", seq2, True, "TestSplit.txt", "sequence2"),
             "full": ("seq-01", seq1[:end], True, "TrainSplit.txt", "sequence1")}
    for name, (seq, frames, pose, split_file, line) in parts.items():
        n = link_frames(src / seq, args.out / name / seq, frames, pose)
        (args.out / name / split_file).write_text(line + "\n")
        print(f"{args.out / name}: {n} frames of {seq}{'' if pose else ' (no poses)'}")


if __name__ == "__main__":
    main()
