"""The table of guidance families: one module each, one line here.

A family supplies pure functions and a layout to the closed-loop kernel
(:class:`rvdjax.loop.family.Family`); a scenario names its family by the table key.
"""

from rvdjax.families import docking, phases, poseidyn, rendezvous
from rvdjax.loop.family import Family

__all__ = ["FAMILIES", "get_family"]

FAMILIES: dict[str, Family] = {
    "rendezvous": rendezvous.FAMILY,  # paper 000 Sec. IV.A: 3-D CW, moving keep-out spheres
    "planar-docking": docking.FAMILY,  # papers 000 Sec. IV.B and 002: rotating target
    "poseidyn": poseidyn.FAMILY,  # paper 001: rotating hyperplane, entry cone
    "three-phase": phases.FAMILY,  # paper 003: rendezvous, approach, docking
}


def get_family(name: str) -> Family:
    """Look a family up by name; ValueError listing the known names otherwise."""
    try:
        return FAMILIES[name]
    except KeyError:
        raise ValueError(f"unknown family {name!r}; known: {', '.join(FAMILIES)}") from None
