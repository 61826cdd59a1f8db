"""The colours of the maps, shared by the plots and the rendered previews: the static map in
red and the objects in blues and greens, as in the paper's Figure 7."""

from __future__ import annotations

STATIC_COLOUR = "#d62728"  # matplotlib's tab:red
OBJECT_COLOURS = ("#1f77b4", "#2ca02c", "#9467bd", "#17becf", "#bcbd22", "#ff7f0e", "#8c564b", "#e377c2")
"""matplotlib's tab:blue, green, purple, cyan, olive, orange, brown, pink: object K takes the
(K-1)-th, cycling."""


def object_colour(object_id: int) -> str:
    """The hex colour of object ``object_id`` (1-based)."""
    return OBJECT_COLOURS[(int(object_id) - 1) % len(OBJECT_COLOURS)]


def rgb(hex_colour: str) -> tuple[int, int, int]:
    """``#rrggbb`` -> ``(r, g, b)`` 0-255."""
    value = hex_colour.lstrip("#")
    return int(value[0:2], 16), int(value[2:4], 16), int(value[4:6], 16)
