"""Draw six held-out tracks of ``RaceObs-Unseen-v0`` from above, each with the obstacles of its evaluation episode.

The panels are evaluation episodes 0-5 (seeds 1,000,000-1,000,005: held-out tracks 0-5), exactly as an evaluation
flies them (:meth:`racebench.envs.random_tracks.RandomTrackEnv.draw_scene`). Regenerates the figure of
docs/unseen-tracks.md:

    python scripts/unseen_tracks_figure.py                      # docs/figures/unseen-tracks.png
    python scripts/unseen_tracks_figure.py --out f.pdf --episodes 0 7 42
"""

from __future__ import annotations

import argparse
from pathlib import Path

from PIL import Image

from racebench.envs.random_tracks import RandomTrackEnv
from racebench.evaluation.protocol import EVAL_SEED_BASE
from racebench.reporting.track_tops import plot_track_tops

DEFAULT_OUT = Path(__file__).resolve().parents[1] / "docs" / "figures" / "unseen-tracks.png"


def main(argv: list[str] | None = None) -> Path:
    """Write the figure; return its path."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(DEFAULT_OUT), help="figure file: .png, .pdf or .svg")
    parser.add_argument("--episodes", type=int, nargs="+", default=list(range(6)), help="evaluation episodes to draw")
    parser.add_argument("--dpi", type=int, default=110, help="resolution of a PNG (default 110: a small file)")
    args = parser.parse_args(argv)
    env = RandomTrackEnv(track="Unseen", obs_mode="state")
    try:
        scenes = [env.draw_scene(EVAL_SEED_BASE + i) for i in args.episodes]
    finally:
        env.close()
    titles = [
        f"episode {i}: {s.track.name}, {'loop' if s.track.closed_loop else 'sprint'}, {s.track.num_gates} gates"
        for i, s in zip(args.episodes, scenes, strict=True)
    ]
    out = plot_track_tops(scenes, args.out, titles, dpi=args.dpi)
    if out.suffix.lower() == ".png":  # a palette of 64 colours: the same picture in a third of the bytes
        with Image.open(out) as image:
            image.convert("RGB").quantize(64, dither=Image.Dither.NONE).save(out, optimize=True)
    print(f"wrote {out}")
    return out


if __name__ == "__main__":
    main()
