"""The cells the suite measures. Until cells can be declared in a configuration file, the large cell
is built here from ``uacell.binding.cell.sized_cell``; this is the one place to switch to a file."""

from __future__ import annotations

from uacell.binding.cell import Part, demo_cell, sized_cell

# name -> (PackML units, robots, task controls per robot)
SIZES = {"large": (100, 10, 2), "units": (21, 1, 1)}


def bench_cell(name: str) -> list[tuple[str, Part]]:
    """``demo``: the demo cell; ``large``: 100 PackML units and 10 robots with two task controls each;
    ``units``: the demo robot with 21 units (RSS per unit; per robot from the large cell)."""
    if name == "demo":
        return demo_cell()
    return sized_cell(*SIZES[name])
