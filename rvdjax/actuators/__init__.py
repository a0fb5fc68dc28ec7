"""Actuators: thruster sets as data, allocation, modulation and the truth under valve pulses
(DESIGN §7a). :mod:`.thrusters` (the sets), :mod:`.allocation` (wrench -> thruster forces),
:mod:`.modulation` (forces -> pulses), :mod:`.response` (the truth under pulses),
:mod:`.fire` (one control period end to end), :mod:`.sets` (the papers' vehicles)."""

from rvdjax.actuators.thrusters import Actuation, Thrusters, ThrusterSet

__all__ = ["Actuation", "Thrusters", "ThrusterSet"]
