"""The paper's plot style: small sans-serif type, thin lines, no top/right spines."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

#: matplotlib rc settings of cobel's paper figures (Frontiers-style single/double columns)
PAPER_RC = {
    "font.family": "sans-serif",
    "font.sans-serif": ["Arial", "Helvetica", "DejaVu Sans"],
    "font.size": 8,
    "axes.titlesize": 9,
    "axes.labelsize": 8,
    "xtick.labelsize": 7,
    "ytick.labelsize": 7,
    "legend.fontsize": 7,
    "legend.frameon": False,
    "axes.linewidth": 0.8,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "lines.linewidth": 1.2,
    "savefig.bbox": "tight",
    "savefig.pad_inches": 0.02,
    "pdf.fonttype": 42,  # editable text in the PDF
}


@contextlib.contextmanager
def paper_style() -> Iterator[None]:
    """Apply :data:`PAPER_RC` inside a ``with`` block."""
    import matplotlib

    with matplotlib.rc_context(PAPER_RC):
        yield
