"""Print the SHA-256 of every file of a dataset folder, one `digest  path` line per file, sorted by path.

Two runs' outputs compare with `diff` (or `--against OTHER`, which prints the files whose bytes differ
and those only one folder has, and exits 1 when any do). dataset.yaml names the output folder and
records the run's times, so two folders always differ there; `--skip` leaves such files out.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path


def digests(folder: Path, skip: set[str]) -> dict[str, str]:
    """Relative path -> SHA-256 hex of every file under `folder`, except the names in `skip`."""
    out = {}
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        rel = path.relative_to(folder).as_posix()
        if path.name not in skip:
            out[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("folder", type=Path)
    ap.add_argument("--against", type=Path, default=None, help="another dataset folder to compare with")
    ap.add_argument("--skip", action="append", default=[], help="a file name to leave out (repeatable)")
    args = ap.parse_args()
    mine = digests(args.folder, set(args.skip))
    if args.against is None:
        for rel, digest in mine.items():
            print(f"{digest}  {rel}")
        return
    other = digests(args.against, set(args.skip))
    differ = sorted(r for r in mine.keys() & other.keys() if mine[r] != other[r])
    alone = sorted(mine.keys() ^ other.keys())
    for rel in differ:
        print(f"differs: {rel}")
    for rel in alone:
        print(f"only in {'the first' if rel in mine else 'the second'}: {rel}")
    same = len(mine.keys() & other.keys()) - len(differ)
    print(f"{same} files identical, {len(differ)} differ, {len(alone)} in one folder only")
    sys.exit(1 if differ or alone else 0)


if __name__ == "__main__":
    main()
