"""Write the held-out tracks of ``RaceObs-Unseen-v0``: ``tracks/unseen/unseen-000.yaml`` ... ``unseen-099.yaml``.

Track ``i`` is the generator's track of track seed ``2,000,000,000 + i``
(:func:`racebench.envs.random_tracks.make_unseen_track`), far from the training range ``[0, 10^9)`` that
``RaceObs-Random-v0`` draws from. The files are data: the env reads them, never this script, and
``tests/test_unseen_tracks.py`` checks that this script rewrites them byte for byte.

    python scripts/make_unseen_tracks.py            # (re)write the files
    python scripts/make_unseen_tracks.py --check    # exit 1 if a file differs from what the generator makes
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from racebench.envs.random_tracks import UNSEEN_TRACK_SEED_BASE, UNSEEN_TRACKS, make_unseen_track, unseen_track_path
from racebench.sim.track_generator import track_yaml
from racebench.utils.files import atomic_write


def unseen_text(index: int) -> str:
    """The committed text of held-out track ``index``."""
    seed = UNSEEN_TRACK_SEED_BASE + index
    header = f"RaceObs-Unseen-v0 held-out track {index}: track seed {seed} (scripts/make_unseen_tracks.py)"
    return track_yaml(make_unseen_track(index), header)


def main(argv: list[str] | None = None) -> int:
    """Write (or with ``--check`` compare) every held-out track file; return the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="compare the files with the generator's, write nothing")
    args = parser.parse_args(argv)
    differ = []
    for index in range(UNSEEN_TRACKS):
        path: Path = unseen_track_path(index)
        text = unseen_text(index)
        if args.check:
            if not path.is_file() or path.read_text() != text:
                differ.append(str(path))
        else:
            atomic_write(path, text)
    if differ:
        print(f"{len(differ)} held-out track files differ from the generator's: {', '.join(differ[:5])}")
        return 1
    print(f"{'checked' if args.check else 'wrote'} {UNSEEN_TRACKS} held-out tracks in {unseen_track_path(0).parent}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
