"""Re-encode committed figures as 256-colour palette PNGs (``lnnmpc.train.png``): the same pictures, a third of
the bytes, so that the working tree that travels with every GPU call stays under its size limit.

    python experiments/scripts/shrink_pngs.py              # every PNG git tracks
    python experiments/scripts/shrink_pngs.py a.png b.png  # these

A PNG already holding a palette is left as it is (running this twice changes nothing), and one whose palette
version would not be smaller is kept. Prints each changed file's bytes before and after, then the totals.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys

from PIL import Image

from lnnmpc.train import runfolder
from lnnmpc.train.png import encode_png


def shrink(path: str) -> tuple[int, int]:
    """Re-encodes ``path`` in place (atomically) unless it holds a palette already or would not shrink;
    returns (bytes before, bytes after)."""
    before = os.path.getsize(path)
    with Image.open(path) as image:
        if image.mode == "P":
            return before, before
        data = encode_png(image)
    if len(data) >= before:
        return before, before
    runfolder.write_atomic(path, lambda f: f.write(data), binary=True)
    return before, len(data)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pngs", nargs="*", help="PNG files (default: every PNG git tracks)")
    args = p.parse_args(argv)
    pngs = args.pngs or subprocess.run(["git", "ls-files", "*.png"], capture_output=True, text=True,
                                       check=True).stdout.split()
    total_before = total_after = changed = 0
    for path in pngs:
        before, after = shrink(path)
        total_before, total_after = total_before + before, total_after + after
        if after != before:
            changed += 1
            print(f"{path}: {before:,} -> {after:,} bytes")
    print(f"{changed} of {len(pngs)} PNGs re-encoded: {total_before:,} -> {total_after:,} bytes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
