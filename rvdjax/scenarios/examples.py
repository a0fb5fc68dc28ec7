"""Scenarios that no paper has: how a user adds a case (one record).

``vbar-400km-heavy-target``: the three-phase guidance of paper 003 flying a V-bar approach to a
heavier target (a 180 kg microsatellite instead of a 14 kg CubeSat) in a lower orbit (400 km,
51.6 deg), starting 2 km behind on V-bar. Everything but the target, the orbit and the start
is the thesis' tuning (Tables 3.1-3.2) with the thesis scenarios' assumptions; the target's
mass and 0.5 m^2 cross-section only matter with the drag truth.
"""

from __future__ import annotations

from rvdjax.actuators import sets
from rvdjax.scenarios import Scenario
from rvdjax.scenarios.paper003 import ASSUMPTIONS, THESIS_N, physical

SCENARIOS = (
    Scenario(
        name="vbar-400km-heavy-target",
        family="three-phase",
        source="rvdjax example (no paper): paper 003's guidance, another target and orbit",
        description="three-phase V-bar approach from 2 km to a 180 kg target at 400 km",
        physical={
            **physical("vbar"),
            "altitude_m": 400e3,
            "target_mass": 180.0,
            "cd_target": 2.2,
            "target_area_m2": 0.5,
        },
        x0=(0.0, -2000.0, 0.0, 0.0, 0.0, 0.0),
        config=dict(N=THESIS_N),
        n_steps=300,
        published={},
        assumptions=(
            "example scenario, no published figures: target 180 kg, 0.5 m^2, C_D 2.2 at 400 km "
            "(inclined 51.6 deg); chaser and guidance as paper 003's V-bar case, starting at "
            "rest 2 km behind the target on V-bar",
            *ASSUMPTIONS[2:],
        ),
        thrusters=sets.CUBESAT_6U,
    ),
)
