"""fpcore — the fingerprint method, exact and fast (numerics only: no network, no services).

Find, localise and characterise targets in strongly scattering media from plane-wave reflection
matrices with the fingerprint likelihood index γ (Le Ber et al.; see docs/design.md §4 for conventions).

    >>> import fpcore
    >>> imager = fpcore.Imager(fpcore.ImagingConfig(grid, band=(1.8e6, 2.6e6), n_freq=40))
    >>> pw = imager.plane_waves(acquisition)
    >>> fp = fpcore.from_calibration(calibration, r0, pw.out_sines, (1.8e6, 2.6e6), 40, diameter=10e-3)
    >>> gamma = imager.gamma(pw, fp)
"""

from .acquisition import (
    Acquisition,
    PlaneWaveData,
    PlaneWaveSequence,
    Probe,
    Spectrum,
    output_sines,
    to_plane_waves,
)
from .background import NullLevel
from .fingerprint import (
    Fingerprint,
    angular_mask,
    from_calibration,
    mirror_fingerprint,
    moving_fingerprint,
    point_fingerprint,
    time_gate,
    whiten,
)
from .grid import Grid, Roi
from .kernel import GridTransform, direct_sum, wavevectors
from .likelihood import Imager, ImagingConfig
from .locate import Located, locate, locate_union, union_pfa
from .metrics import Detection, contrasts, cramer_rao_precision, detect, paper_pfa
from .time_weighting import inverse_variance_weighted
from .truth import TargetTruth, Truth

__version__ = "0.1.0"

__all__ = [
    "Acquisition",
    "Detection",
    "Fingerprint",
    "Grid",
    "GridTransform",
    "Imager",
    "NullLevel",
    "ImagingConfig",
    "Located",
    "PlaneWaveData",
    "PlaneWaveSequence",
    "Probe",
    "Roi",
    "Spectrum",
    "TargetTruth",
    "Truth",
    "angular_mask",
    "contrasts",
    "cramer_rao_precision",
    "detect",
    "direct_sum",
    "from_calibration",
    "inverse_variance_weighted",
    "locate",
    "locate_union",
    "mirror_fingerprint",
    "moving_fingerprint",
    "output_sines",
    "paper_pfa",
    "point_fingerprint",
    "time_gate",
    "to_plane_waves",
    "union_pfa",
    "wavevectors",
    "whiten",
]
