"""Forward model: realistic plane-wave acquisitions of targets in strongly scattering media (docs/design.md §6).

Frequency-domain and exact where it can be: partial-wave (Faran) spheres and cylinders evaluated at the
elements, Born and Foldy–Lax point scatterers, ballistic extinction, interface echo, a statistical
multiple-scattering background, the transducer band and electronic noise. Conventions: numpy's
e^{-i2πft} spectra, outgoing e^{-ikr}, plane-wave delays τ = (u_x s_x + u_y s_y)/c0 (docs/design.md §3–4).

    >>> import fpcore.simulate as sim
    >>> sc = sim.scenario("sinking-sphere", quick=True, seed=0)
    >>> acq = next(sc.frames()); acq.ground_truth.targets[0].position   # acq.truth: the JSON object
    >>> cal = sc.calibration("sphere1")
"""

from .foldy_lax import (
    coherent_wave,
    cross_section,
    foldy_lax_excitation,
    passive_strength,
    point_strength,
    random_slab,
)
from .medium import DiffuseBackground, ScatteringLayer
from .partial_wave import (
    Elastic,
    cylinder_coefficients,
    fluid_cylinder_coefficients,
    fluid_sphere_coefficients,
    rigid_cylinder_coefficients,
    rigid_sphere_coefficients,
    sphere_coefficients,
)
from .scenarios import (
    SCENARIOS,
    bipennate_orientation,
    fast_cylinder,
    lesion_marker,
    muscle_fibres,
    scenario,
    sinking_cylinder,
    sinking_sphere,
)
from .scene import Placement, Scenario
from .targets import PAPER_SPHERE_MATERIAL, ElasticCylinder, ElasticSphere, MirrorSegment, PointCluster, Target
from .waves import Band, TimeWindow, green, incident_phase, radiate_points

__all__ = [
    "Band",
    "DiffuseBackground",
    "Elastic",
    "ElasticCylinder",
    "ElasticSphere",
    "MirrorSegment",
    "PAPER_SPHERE_MATERIAL",
    "Placement",
    "PointCluster",
    "SCENARIOS",
    "Scenario",
    "ScatteringLayer",
    "Target",
    "TimeWindow",
    "bipennate_orientation",
    "fast_cylinder",
    "coherent_wave",
    "cross_section",
    "cylinder_coefficients",
    "fluid_cylinder_coefficients",
    "fluid_sphere_coefficients",
    "foldy_lax_excitation",
    "green",
    "incident_phase",
    "lesion_marker",
    "muscle_fibres",
    "passive_strength",
    "point_strength",
    "radiate_points",
    "random_slab",
    "rigid_cylinder_coefficients",
    "rigid_sphere_coefficients",
    "scenario",
    "sinking_cylinder",
    "sinking_sphere",
    "sphere_coefficients",
]
