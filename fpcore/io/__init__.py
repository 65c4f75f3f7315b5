"""File input/output of fpcore (the only part of fpcore that touches files).

UFF (USTB's HDF5 ultrasound file format) channel data: :func:`read_uff`, :func:`write_uff`.
"""

from fpcore.io.uff import (
    UFF_VERSION,
    UFFError,
    angles_to_sines,
    list_uff_datasets,
    read_uff,
    read_uff_json,
    sines_to_angles,
    write_uff,
    write_uff_json,
)

__all__ = [
    "UFFError",
    "UFF_VERSION",
    "read_uff",
    "write_uff",
    "list_uff_datasets",
    "read_uff_json",
    "write_uff_json",
    "sines_to_angles",
    "angles_to_sines",
]
