"""Writing a figure to a file: the formats, the resolution and the checks every racebench figure shares."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.transforms import Bbox  # noqa: E402

#: File formats of the figures (matplotlib picks the writer from the suffix) and the default resolution of PNGs.
FIGURE_FORMATS: tuple[str, ...] = ("png", "pdf", "svg")
DEFAULT_DPI = 300


def _checked(path: str | Path, fig, dpi: int) -> Path:
    """``path`` with its folder made, once its suffix and ``dpi`` are ones :func:`_save` accepts."""
    path = Path(path)
    if path.suffix.lower().lstrip(".") not in FIGURE_FORMATS or isinstance(dpi, bool) or not 20 <= dpi <= 2400:
        plt.close(fig)
        raise ValueError(f"{str(path)!r}: figures are written as {', '.join(FIGURE_FORMATS)}, at dpi in [20, 2400]")
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def _save(fig, path: str | Path, dpi: int = DEFAULT_DPI, bbox: Bbox | None = None) -> Path:
    """Write ``fig`` to ``path`` in the format of its suffix (see FIGURE_FORMATS), cropped to what is drawn
    (``bbox``, in inches, where matplotlib's own "tight" box would keep blank space)."""
    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in FIGURE_FORMATS:
        plt.close(fig)
        raise ValueError(
            f"{str(path)!r}: figures are written as {', '.join(FIGURE_FORMATS)}, not {fmt or 'no suffix'!r}"
        )
    if isinstance(dpi, bool) or not isinstance(dpi, int) or not 20 <= dpi <= 2400:
        plt.close(fig)
        raise ValueError(f"dpi must be an int in [20, 2400], got {dpi!r}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not any(getattr(ax, "name", "") == "3d" for ax in fig.axes):  # tight_layout cannot place 3D axes
        fig.tight_layout()
    # "tight" crops the blank margin and keeps legends placed outside the axes.
    fig.savefig(path, dpi=dpi, bbox_inches=bbox or "tight", pad_inches=0.05)
    plt.close(fig)
    return path
