"""The corner map as text in the layout of Im et al. 2016 Table 1 (the format lives in stages/common/im2016_text)."""
from __future__ import annotations

import numpy as np

from stages.common.im2016_text import COLUMNS, HEADER, parse_im2016_text  # noqa: F401 - re-exported


def format_im2016_text(table, origin: dict[str, float] | None = None) -> str:
    """corner_map table (pyarrow.Table or mapping of columns) -> text in the paper's Table 1 layout; with the map's
    ENU ``origin`` ({lat_deg, lon_deg, h_m}) the text starts with frame comment lines."""
    from stages.common import im2016_text

    def column(name: str) -> np.ndarray:
        return table.column(name).to_numpy() if hasattr(table, "column") else np.asarray(table[name])

    return im2016_text.format_im2016_text(*(column(name) for name in COLUMNS), origin=origin)
